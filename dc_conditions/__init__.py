"""Built-in condition plugins."""
