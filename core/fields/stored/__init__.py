"""The stored product: artefact (a trained field on disk with its metadata, loaded and
queried) and bake (its env maps on a lattice, the fast query path)."""
