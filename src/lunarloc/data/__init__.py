"""Data: traverse CSVs, `.lac` archives, playback agent, simulated site."""
