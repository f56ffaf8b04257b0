"""What the CLI and the API share about probe queries, so `lightfield sh` and GET /sh (and
`lightfield unity` and GET /unity) give the same answer: the map heights the SH products are
evaluated at and the Unity grid's parser. Each adapter turns a ValueError into its own error
(a usage error, a 400)."""
from __future__ import annotations

SH_ENVMAP_HEIGHT = 128  # the main-light fit needs the rows to isolate a small light; SH only band 2
UNITY_SH_HEIGHT = 32  # the Unity grid stores band-2 SH only, which need little resolution
UNITY_GRID_DEFAULT = (3, 2, 3)
UNITY_GRID_AXIS_MAX = 64


def parse_grid(text: str) -> tuple[int, int, int]:
    """'NX,NY,NZ' -> probes per axis, each 1..UNITY_GRID_AXIS_MAX; ValueError names the rule."""
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(1 <= v <= UNITY_GRID_AXIS_MAX for v in values):
        raise ValueError(f"grid must be three integers in 1..{UNITY_GRID_AXIS_MAX} 'NX,NY,NZ', got {text!r}")
    return values  # type: ignore[return-value]
