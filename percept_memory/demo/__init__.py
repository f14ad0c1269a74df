"""The demo's own world: a generated kitchen week with its ground truth (what `pmem demo`
loads beside the real RoboSherlock data, and what tests and benchmarks score against). Not a
way in: the ingest service takes its scenes as it takes anyone's."""
