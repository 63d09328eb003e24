"""Destination server, durable delivery and the built-in destination plugins."""
