"""Building blocks of every field kind (core.fields.kinds), none of which knows a kind:
settings (FieldSettings, the strict base of every settings section), normalization
(SceneBounds: world <-> normalised coordinates), encodings (positional, grid, equirect,
time codes, time gain), lattice (the room lattice of maps), emitters (small bright sources
as spheres) and surfaces (observed surfaces). They import nothing else of core.fields."""
