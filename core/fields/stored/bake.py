"""Baked fast path: env maps precomputed on a lattice of positions (and times), interpolated.

`bake(artefact, grid=(nx, ny, nz), times=K, height=h)` evaluates the field once at the nodes
of a regular lattice spanning the artefact's box (and K keyframes over its time range when
the field has a time input) and keeps the env maps. A query then costs one multilinear
blend of 8 (16 with time) maps plus a resize, independent of the field's size.

Interpolation is LINEAR in radiance (a cache of radiance: blending preserves energy; a
light moving between nodes cross-fades instead of vanishing). The price is accuracy
between nodes and below the baked resolution; `bench/query_latency.py` measures it.

Saved as `baked.safetensors` next to the artefact (atomic: temp file + os.replace) with
the SHA-256 of the weights it was baked from, so a re-estimated artefact never answers
from a stale bake, and the SHA-256 of its own maps, so a corrupted bake is refused (and
re-baked by `load_or_bake`) instead of answering with garbage.
"""
from __future__ import annotations

import json
import logging
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load as load_safetensors_bytes, save_file

from core.conventions import equirect_width
from core.envmap import resize_envmap, upsample_envmaps
from core.fields.components.encodings import lattice_corners
from core.fields.components.normalization import SceneBounds
from core.fields.stored.artefact import (
    ArtefactError,
    LightFieldArtefact,
    QueryError,
    check_height,
    extrapolation_flags,
    query_positions,
    query_times,
)
from core.integrity import sha256_bytes

log = logging.getLogger("lightfield.fields")

BAKED_FILE = "baked.safetensors"
BAKE_SCHEMA_VERSION = 1
DEFAULT_GRID = (5, 5, 5)
DEFAULT_TIMES = 4
DEFAULT_HEIGHT = 32
MAX_BAKED_BYTES = 1 << 30  # refuse bakes over 1 GiB of float32 maps


@dataclass
class BakedField:
    maps: torch.Tensor  # [K, nx, ny, nz, h, 2h, 3] radiance; K = 1 without a time input
    bounds: SceneBounds
    uses_time: bool
    source_sha256: str  # weights the maps were baked from

    @property
    def grid(self) -> tuple[int, int, int]:
        return tuple(self.maps.shape[1:4])

    @property
    def times(self) -> int:
        return int(self.maps.shape[0])

    @property
    def height(self) -> int:
        return int(self.maps.shape[4])

    # ------------------------------------------------------------------ queries
    def envmap(self, x, t=None, height: int | None = None) -> tuple[torch.Tensor, dict]:
        """Interpolated env map [H, 2H, 3] at x [3], t, and flags (as LightFieldArtefact.envmap)."""
        x = query_positions(x, "x")
        if x.shape[0] != 1:
            raise QueryError(f"x must be one position [3], got {x.shape[0]}")
        hdr, flags = self.envmaps(x, None if t is None else [t], height)
        return hdr[0], flags[0]

    def envmaps(self, xs, ts, height: int | None = None) -> tuple[torch.Tensor, list[dict]]:
        xs = query_positions(xs, "xs")
        ts_t = query_times(ts, xs.shape[0], self.bounds, self.uses_time)
        height = self.height if height is None else check_height(height)
        has_time_axis = self.maps.shape[0] > 1
        dims = tuple(self.maps.shape[:4]) if has_time_axis else self.grid
        node, weight = lattice_corners(self._lattice_coords(xs, ts_t if has_time_axis else None), dims)
        flat = self.maps.reshape(-1, *self.maps.shape[4:])
        # each query's 8 (16) corner maps summed in a fixed order, one corner at a time over the
        # whole batch: elementwise work, so a query's answer is bit-identical whatever else is
        # batched with it (a [P, nodes] matrix product rounds differently with P)
        rows = flat.reshape(flat.shape[0], -1)
        weight = weight.to(flat.dtype)
        blended = weight[:, 0, None] * rows.index_select(0, node[:, 0])
        for k in range(1, node.shape[1]):
            blended.addcmul_(weight[:, k, None], rows.index_select(0, node[:, k]))
        blended = blended.reshape(xs.shape[0], *flat.shape[1:])  # [P, h, 2h, 3]
        return self._resize(blended, height), extrapolation_flags(self.bounds, xs, ts_t)

    def _resize(self, maps: torch.Tensor, height: int) -> torch.Tensor:
        """[P, h, 2h, 3] -> [P, height, 2 height, 3]: area-correct down, bilinear up (core.envmap)."""
        if height < self.height:
            return torch.stack([resize_envmap(m, height) for m in maps])
        return upsample_envmaps(maps, height)

    def _lattice_coords(self, xs: torch.Tensor, ts: torch.Tensor | None) -> torch.Tensor:
        """[-1, 1] lattice coordinates (t first when there is a time axis), clamped to the box."""
        xn = self.bounds.normalize_x(xs).clamp(-1.0, 1.0)
        if ts is None:
            return xn
        tn = self.bounds.normalize_t(ts).clamp(-1.0, 1.0)
        return torch.cat((tn[:, None], xn), dim=-1)

    # ------------------------------------------------------------------ storage
    def save(self, artefact_dir) -> Path:
        """Write `baked.safetensors` into the artefact directory atomically; return its path."""
        target = Path(artefact_dir) / BAKED_FILE
        header = {
            "schema_version": str(BAKE_SCHEMA_VERSION),
            "bounds": json.dumps(self.bounds.to_dict()),
            "uses_time": json.dumps(self.uses_time),
            "source_sha256": self.source_sha256,
            "maps_sha256": _maps_sha256(self.maps),
        }
        fd, tmp = tempfile.mkstemp(prefix=f".{BAKED_FILE}.tmp-", dir=target.parent)
        os.close(fd)
        try:
            save_file({"maps": self.maps.contiguous()}, tmp, metadata=header)
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
            os.replace(tmp, target)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return target

    @classmethod
    def load(cls, artefact: LightFieldArtefact) -> "BakedField":
        """The bake stored next to `artefact`; ArtefactError when missing, corrupt or stale."""
        path = artefact.path / BAKED_FILE
        if not path.is_file():
            raise ArtefactError(f"artefact {artefact.path} has no {BAKED_FILE}")
        data = path.read_bytes()
        try:
            maps = load_safetensors_bytes(data)["maps"]
            header = _safetensors_metadata(data)
        except (SafetensorError, KeyError, ValueError, RuntimeError) as exc:
            raise ArtefactError(f"{BAKED_FILE} cannot be read: {exc}") from exc
        if header.get("schema_version") != str(BAKE_SCHEMA_VERSION):
            raise ArtefactError(f"{BAKED_FILE}: unsupported schema_version {header.get('schema_version')!r}")
        if header.get("source_sha256") != artefact.weights_sha256:
            raise ArtefactError(f"{BAKED_FILE} is stale: it was baked from other weights than {artefact.path}")
        if maps.ndim != 7 or maps.shape[-1] != 3 or maps.shape[5] != 2 * maps.shape[4] or maps.dtype != torch.float32:
            raise ArtefactError(
                f"{BAKED_FILE}: 'maps' has shape {tuple(maps.shape)} / {maps.dtype}, expected [K,nx,ny,nz,h,2h,3] "
                "float32"
            )
        if header.get("maps_sha256") != _maps_sha256(maps):
            raise ArtefactError(f"{BAKED_FILE}: checksum mismatch (missing, or the maps were corrupted after baking)")
        if not torch.isfinite(maps).all():
            raise ArtefactError(f"{BAKED_FILE}: 'maps' contains non-finite values")
        return cls(maps, artefact.bounds, artefact.uses_time, artefact.weights_sha256)


def bake(
    artefact: LightFieldArtefact,
    grid: tuple[int, int, int] = DEFAULT_GRID,
    times: int = DEFAULT_TIMES,
    height: int = DEFAULT_HEIGHT,
    probes_per_batch: int = 8,
) -> BakedField:
    """Evaluate `artefact` on a lattice of env maps (`times` keyframes when it uses time)."""
    grid = tuple(int(n) for n in grid)
    if len(grid) != 3 or min(grid) < 2:
        raise QueryError(f"grid must be three sizes >= 2, got {grid}")
    n_times = keyframe_count(artefact, times)
    height = check_height(height)
    n_maps = n_times * grid[0] * grid[1] * grid[2]
    size = n_maps * height * equirect_width(height) * 3 * 4
    if size > MAX_BAKED_BYTES:
        raise QueryError(
            f"bake of {n_maps} maps at height {height} needs {size / 2**20:.0f} MiB (> {MAX_BAKED_BYTES >> 20} MiB)"
        )

    b = artefact.bounds
    axes = [torch.linspace(lo, hi, n, dtype=torch.float64) for lo, hi, n in zip(b.lo, b.hi, grid)]
    xs = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3).to(torch.float32)
    key_times = (
        torch.linspace(b.t0, b.t1, n_times, dtype=torch.float64).to(torch.float32) if artefact.uses_time else None
    )
    maps = torch.empty(n_times, xs.shape[0], height, equirect_width(height), 3)
    for k in range(n_times):
        for p0 in range(0, xs.shape[0], probes_per_batch):
            chunk = xs[p0 : p0 + probes_per_batch]
            ts = None if key_times is None else key_times[k].expand(chunk.shape[0])
            maps[k, p0 : p0 + chunk.shape[0]] = artefact.envmaps(chunk, ts, height)[0].cpu()
    maps = maps.reshape(n_times, *grid, height, equirect_width(height), 3)
    return BakedField(maps, b, artefact.uses_time, artefact.weights_sha256)


def load_or_bake(
    artefact: LightFieldArtefact,
    grid: tuple[int, int, int] | None = None,
    times: int | None = None,
    height: int | None = None,
    save: bool = True,
) -> BakedField:
    """The stored bake when it is fresh and matches every spec given (None: any), else a new
    one with the given spec (defaults for the rest), saved next to the artefact when `save`."""
    try:
        baked = BakedField.load(artefact)
        if (
            (grid is None or baked.grid == tuple(grid))
            and (times is None or baked.times == keyframe_count(artefact, times))
            and (height is None or baked.height == height)
        ):
            return baked
    except ArtefactError as exc:
        if (artefact.path / BAKED_FILE).is_file():  # refused (corrupt, stale, old format): bake anew
            log.warning("%s: re-baking: %s", artefact.path, exc)
    baked = bake(artefact, grid or DEFAULT_GRID, DEFAULT_TIMES if times is None else times, height or DEFAULT_HEIGHT)
    if save:
        baked.save(artefact.path)
    return baked


def _maps_sha256(maps: torch.Tensor) -> str:
    return sha256_bytes(maps.detach().cpu().contiguous().numpy().tobytes())


def keyframe_count(artefact: LightFieldArtefact, times: int) -> int:
    """Time keyframes a bake needs: `times` (>= 2) for a field that varies over a time range, else 1."""
    if not (artefact.uses_time and artefact.bounds.has_duration):
        return 1
    if int(times) < 2:
        raise QueryError(f"times must be >= 2 for a field that varies over time, got {times}")
    return int(times)


def _safetensors_metadata(data: bytes) -> dict:
    """The string metadata of a safetensors blob (header = 8-byte length + JSON)."""
    n = int.from_bytes(data[:8], "little")
    return json.loads(data[8 : 8 + n]).get("__metadata__", {}) or {}
