"""Localization over time: the online loop's state and the per-tick component an agent calls."""
