"""An example DC plugin package: one measurement, registered by its entry point only."""
