"""`lightfield bench`: what accuracy costs in time (issue 7). See bench/README.md.

Other scripts in this directory (sim_speed.py, ...) are standalone micro-benchmarks; the
suite proper is `bench.run` (driven by `cli/bench.py`)."""
