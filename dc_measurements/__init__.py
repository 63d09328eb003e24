"""Measurement server and the built-in measurement plugins."""
