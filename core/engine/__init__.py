"""Estimation engine: capture loading, distillation, the stored artefact and its queries.

Kept import-free on purpose: importing one engine module must not pull in the
distillation loop (and vice versa), and the CLI imports submodules lazily.
"""
