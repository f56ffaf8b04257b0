"""Estimation engine: capture loading, distillation, the stored artefact and its queries.

Kept import-free on purpose: `import core.engine.artefact` must not pull in the
distillation loop (and vice versa), and the CLI imports submodules lazily.
"""
