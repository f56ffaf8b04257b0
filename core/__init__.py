"""lightfield core: pure torch/numpy library (no web or queue imports)."""
