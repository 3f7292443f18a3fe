"""Data: Mitsuba 3 scene recipes, the path tracer that renders frame bundles, and the dataset generator."""
