"""Benchmark scripts that print JSON (``scenesig bench NAME``); nothing in the library imports them."""
