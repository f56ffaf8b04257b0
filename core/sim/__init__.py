"""Scene simulator: spec (pydantic), ray caster, renderer, suites, capture/training export, oracle prior.

See docs/simulator.md. Heavy submodules (export, oracle) are imported explicitly by callers.
"""
