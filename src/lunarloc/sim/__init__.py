"""The simulator: procedural sites, the rover, the renderer, synthetic rock fields."""
