"""scenesig: mapping."""
