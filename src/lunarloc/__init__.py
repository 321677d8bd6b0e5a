"""lunarloc: rock-landmark global localization for planetary rovers."""
__version__ = "0.1.0"
