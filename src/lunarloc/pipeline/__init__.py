"""Applications: whole-traverse runs, detection, sources, references, scenarios, campaigns,
benchmarks."""
