"""scenesig: localiser."""
