"""Benchmarks of what accuracy costs in time (issue 7). See bench/README.md.

Every bench is registered by name in bench/registry.py (`lightfield bench list`, `lightfield
bench run NAME`); the suite proper is `bench.run` (driven by `cli/bench.py`), and the scripts
that fit product constants are in bench/calibration/."""
