"""Field kinds: base (LightField, the shell every kind extends, and build_field), config
(FieldConfig: kind, shared component settings, one settings section per kind), registry
(@register_field: the kinds by name) and the built-in kinds mlp, grid and trunk, which
register when core.fields is imported. A new kind is one module plus its registration.
They import core.fields.components, never core.fields.stored."""
