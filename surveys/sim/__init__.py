"""The simulated survey world (the embedded default data)."""
