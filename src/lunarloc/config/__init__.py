"""Run configuration: one config that round-trips, and its presets."""
