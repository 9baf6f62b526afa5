"""scenesig: signatures."""
