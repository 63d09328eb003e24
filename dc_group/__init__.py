"""DC's group server: merges records of several topics that belong together in time."""
