"""scenesig: surveys."""
