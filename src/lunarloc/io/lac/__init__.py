"""LAC archives (the Lunar Autonomy Challenge recorder's format) and the playback agent."""
