"""One-shot global localization: search, screen, register, uncertainty, large maps, kernel
warm-up."""
