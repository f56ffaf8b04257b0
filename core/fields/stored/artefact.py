"""The stored light field: a directory with `field.safetensors` + `lightfield.json`.

Writing is atomic: everything goes into a temporary sibling directory (files fsynced), which
is then renamed onto the final name, so a reader never sees a half-written artefact under
that name; an existing artefact is moved aside first and removed only after the rename
(restored if the rename fails). Crashed writers leave only hidden `.NAME.tmp-*` siblings.

Loading never unpickles: the JSON is parsed and validated (its own SHA-256, schema and conventions
versions, field config, bounds, SHA-256 of the weights), then the safetensors bytes are
checked tensor by tensor against the state dict the config implies. Any mismatch raises
`ArtefactError` naming the file and the field at fault.
"""
from __future__ import annotations

import hashlib
import json
import math
import numbers
import os
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Any

import torch
from pydantic import ValidationError
from safetensors import SafetensorError
from safetensors.torch import load as load_safetensors_bytes, save_file

from core.conventions import CONVENTIONS_SUMMARY, CONVENTIONS_VERSION
from core.fields import BoundsError, FieldConfig, LightField, SceneBounds, build_field
from core.integrity import DOCUMENT_HASH_KEY, IntegrityError, seal_document, verify_document

SCHEMA_VERSION = 1
WEIGHTS_FILE = "field.safetensors"
META_FILE = "lightfield.json"
MAX_ENVMAP_HEIGHT = 4096  # a 4096 x 8192 map is 400 MB of float32; refuse beyond that
RESERVED_KEYS = (
    "schema_version",
    "conventions_version",
    "conventions",
    "field",
    "bounds",
    "weights",
    DOCUMENT_HASH_KEY,
)


class ArtefactError(ValueError):
    """An artefact cannot be written or is missing, corrupt or incompatible."""


class QueryError(ValueError):
    """A query (position, time, height, directions) is malformed."""


# ---------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------
def save_artefact(out_dir, field: LightField, meta: dict | None = None) -> "LightFieldArtefact":
    """Write `field` and `meta` as an artefact directory at `out_dir` (atomically) and return
    it in memory, exactly as `LightFieldArtefact.load(out_dir)` would (the written weights in a
    fresh field on CPU, the written lightfield.json), so nobody needs to read it back.

    `meta` (capture summary, prior, temporal decision, training stats, ...) is stored at the
    top level of lightfield.json next to the reserved keys, which it may not override.
    Non-finite floats in meta become null (JSON has no NaN).
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ArtefactError(f"artefact path {out_dir} exists and is not a directory")
    meta = dict(meta or {})
    document = _document(field, meta)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.tmp-", dir=out_dir.parent))
    try:
        weights = tmp / WEIGHTS_FILE
        state = {k: v.detach().to("cpu", torch.float32).contiguous().clone() for k, v in field.state_dict().items()}
        save_file(state, str(weights), metadata={"schema_version": str(SCHEMA_VERSION)})
        _fsync_file(weights)
        document["weights"] = {
            "file": WEIGHTS_FILE,
            "sha256": _sha256(weights.read_bytes()),
            "bytes": weights.stat().st_size,
        }
        document = seal_document(document)
        _write_json(tmp / META_FILE, document)
        _fsync_dir(tmp)
        _replace_dir(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    saved = build_field(field.config, field.bounds)
    saved.load_state_dict(state)
    return LightFieldArtefact(out_dir, saved.eval().requires_grad_(False), document)


def _document(field: LightField, meta: dict) -> dict:
    document: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION,
        "conventions_version": CONVENTIONS_VERSION,
        "conventions": CONVENTIONS_SUMMARY,
        "field": field.config.model_dump(mode="json"),
        "bounds": field.bounds.to_dict(),
    }
    for key, value in meta.items():
        if key in RESERVED_KEYS and (key not in document or _jsonable(value) != document[key]):
            raise ArtefactError(f"meta key {key!r} is reserved for the artefact writer")
        document.setdefault(key, _jsonable(value))
    return document


def _jsonable(value):
    """Plain JSON types: numpy/torch scalars and arrays to lists, Paths to str, NaN/inf to None."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, torch.Tensor):
        return _jsonable(value.detach().cpu().tolist())
    if hasattr(value, "model_dump"):  # pydantic
        return _jsonable(value.model_dump(mode="json"))
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):  # numpy
        return _jsonable(value.tolist())
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, bool) or value is None or isinstance(value, (str, int)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    raise ArtefactError(f"meta value of type {type(value).__name__} is not JSON-serialisable: {value!r:.80}")


def _write_json(path: Path, document: dict) -> None:
    with open(path, "w", encoding="utf-8") as f:
        json.dump(document, f, indent=1, allow_nan=False)
        f.flush()
        os.fsync(f.fileno())


def _fsync_file(path: Path) -> None:
    with open(path, "rb+") as f:
        os.fsync(f.fileno())


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # some platforms cannot open directories; durability is best effort there
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _replace_dir(tmp: Path, out_dir: Path) -> None:
    """Rename tmp onto out_dir; an existing out_dir is moved aside, then deleted."""
    old = None
    if out_dir.exists():
        old = out_dir.with_name(f".{out_dir.name}.old-{uuid.uuid4().hex[:8]}")
        os.replace(out_dir, old)
    try:
        os.replace(tmp, out_dir)
    except BaseException:
        if old is not None and not out_dir.exists():
            os.replace(old, out_dir)
        raise
    _fsync_dir(out_dir.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# ---------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------
class LightFieldArtefact:
    """A loaded, validated artefact and its query API (all queries under inference_mode).

    Positions are world metres, times seconds from the first frame, directions follow
    core.conventions. Queries outside the box / time range are answered (as at the nearest
    point of the box / range) and flagged.
    """

    def __init__(self, path: Path, field: LightField, meta: dict):
        self.path = Path(path)
        self.field = field
        self.meta = meta  # the whole lightfield.json

    # ------------------------------------------------------------------ properties
    @property
    def config(self) -> FieldConfig:
        return self.field.config

    @property
    def bounds(self) -> SceneBounds:
        return self.field.bounds

    @property
    def uses_time(self) -> bool:
        return self.field.uses_time

    @property
    def weights_sha256(self) -> str:
        return self.meta["weights"]["sha256"]

    @property
    def device(self) -> torch.device:
        return self.field.bounds_lo.device

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, path, device: str | torch.device = "cpu") -> "LightFieldArtefact":
        path = Path(path)
        if not path.is_dir():
            raise ArtefactError(f"artefact directory {path} does not exist")
        meta = _read_meta(path)
        try:
            config = FieldConfig.model_validate(meta["field"])
        except ValidationError as exc:
            raise ArtefactError(f"{META_FILE}: 'field' is not a valid field config: {exc}") from exc
        try:
            bounds = SceneBounds.from_dict(meta["bounds"])
        except BoundsError as exc:
            raise ArtefactError(f"{META_FILE}: 'bounds' is invalid: {exc}") from exc
        with torch.device("meta"):  # shapes only: a crafted config cannot make us allocate
            expected = build_field(config, bounds).state_dict()
        tensors = _read_weights(path, meta, expected, bounds)
        field = build_field(config, bounds)
        field.load_state_dict(tensors)
        field = field.to(device).eval().requires_grad_(False)
        return cls(path, field, meta)

    # ------------------------------------------------------------------ queries
    def radiance(self, x, t, d) -> torch.Tensor:
        """Radiance [B, 3] (float32) for positions x [B, 3], times t [B] (or None), directions d [B, 3]."""
        x = self._positions(x, "x")
        d = _as_tensor(d, "d", self.device)
        if d.shape[-1:] != (3,) or d.reshape(-1, 3).shape != x.shape:
            raise QueryError(f"d must have shape [{x.shape[0]}, 3] to match x, got {tuple(d.shape)}")
        d = d.reshape(-1, 3)
        if not torch.isfinite(d).all() or (d.norm(dim=-1) == 0).any():
            raise QueryError("d must be finite, non-zero directions")
        t = self._times(t, x.shape[0])
        with torch.inference_mode():
            return self.field(x, t, d)

    def envmap(self, x, t=None, height: int = 64) -> tuple[torch.Tensor, dict]:
        """Env map hdr [H, 2H, 3] (float32, CPU/device tensor) at x [3], t and its flags
        {'extrapolated_x': bool, 'extrapolated_t': bool}."""
        x = self._positions(x, "x")
        if x.shape[0] != 1:
            raise QueryError(f"x must be one position [3], got {x.shape[0]}")
        hdr, flags = self.envmaps(x, None if t is None else [t], height)
        return hdr[0], flags[0]

    def envmaps(self, xs, ts, height: int = 64) -> tuple[torch.Tensor, list[dict]]:
        """Env maps [P, H, 2H, 3] at positions xs [P, 3] and times ts [P] (or a scalar, or None)."""
        xs = self._positions(xs, "xs")
        ts = self._times(ts, xs.shape[0])
        height = check_height(height)
        with torch.inference_mode():
            hdr = self.field.envmaps(xs, ts, height)
        return hdr, self.flags(xs, ts)

    def flags(self, xs: torch.Tensor, ts: torch.Tensor | None) -> list[dict]:
        return extrapolation_flags(self.bounds, xs, ts)

    # ------------------------------------------------------------------ validation
    def _positions(self, x, name: str) -> torch.Tensor:
        return query_positions(x, name, self.device)

    def _times(self, t, n: int) -> torch.Tensor | None:
        return query_times(t, n, self.bounds, self.uses_time, self.device)


def query_positions(x, name: str, device="cpu") -> torch.Tensor:
    """A position query as finite [N, 3] metres (N >= 1); QueryError naming `name` otherwise."""
    x = _as_tensor(x, name, device)
    if x.ndim == 0 or x.shape[-1] != 3:
        raise QueryError(f"{name} must have shape [3] or [N, 3], got {tuple(x.shape)}")
    x = x.reshape(-1, 3)
    if x.shape[0] == 0:
        raise QueryError(f"{name} is empty")
    if not torch.isfinite(x).all():
        raise QueryError(f"{name} must be finite (metres), got {x[~torch.isfinite(x).all(-1)][0].tolist()}")
    return x


def query_times(t, n: int, bounds: SceneBounds, uses_time: bool, device="cpu") -> torch.Tensor | None:
    """t as [n] finite seconds (a scalar is broadcast), or None. Required when `uses_time`."""
    if t is None:
        if uses_time:
            raise QueryError(f"t is required: this light field varies over time [{bounds.t0:g}, {bounds.t1:g}] s")
        return None
    t = _as_tensor(t, "t", device).reshape(-1)
    if t.numel() == 1:
        t = t.expand(n)
    if t.shape[0] != n:
        raise QueryError(f"t has {t.shape[0]} values for {n} positions")
    if not torch.isfinite(t).all():
        raise QueryError("t must be finite (seconds from the first frame)")
    return t


def extrapolation_flags(bounds: SceneBounds, xs: torch.Tensor, ts: torch.Tensor | None) -> list[dict]:
    """Per query: is x outside the box, is t outside the capture's time range (None: never)."""
    inside_x = bounds.contains(xs.to(torch.float64)).tolist()
    inside_t = [True] * xs.shape[0] if ts is None else bounds.contains_t(ts.to(torch.float64)).tolist()
    return [{"extrapolated_x": not a, "extrapolated_t": not b} for a, b in zip(inside_x, inside_t)]


def check_height(height) -> int:
    if isinstance(height, bool) or not isinstance(height, numbers.Integral):
        raise QueryError(f"height must be an integer, got {height!r}")
    if not 1 <= int(height) <= MAX_ENVMAP_HEIGHT:
        raise QueryError(f"height must be in [1, {MAX_ENVMAP_HEIGHT}], got {height}")
    return int(height)


def _as_tensor(v, name: str, device) -> torch.Tensor:
    try:
        return torch.as_tensor(v, dtype=torch.float32, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise QueryError(f"{name} must be numbers, got {v!r:.80}") from exc


def _read_meta(path: Path) -> dict:
    meta_path = path / META_FILE
    if not meta_path.is_file():
        raise ArtefactError(f"artefact {path} is missing {META_FILE}")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ArtefactError(f"{meta_path} is not valid JSON: {exc}") from exc
    if not isinstance(meta, dict):
        raise ArtefactError(f"{meta_path} must hold a JSON object, got {type(meta).__name__}")
    try:  # artefacts written before the document checksum existed have none
        verify_document(meta, META_FILE, required=False)
    except IntegrityError as exc:
        raise ArtefactError(str(exc)) from None
    if meta.get("schema_version") != SCHEMA_VERSION:
        raise ArtefactError(
            f"{META_FILE}: unsupported schema_version {meta.get('schema_version')!r} (this build reads "
            f"{SCHEMA_VERSION})"
        )
    conv = meta.get("conventions_version")
    if not isinstance(conv, str) or conv.split(".")[0] != CONVENTIONS_VERSION.split(".")[0]:
        raise ArtefactError(
            f"{META_FILE}: conventions_version {conv!r} is incompatible with this build's {CONVENTIONS_VERSION}"
        )
    for key in ("field", "bounds", "weights"):
        if key not in meta:
            raise ArtefactError(f"{META_FILE} is missing {key!r}")
    weights = meta["weights"]
    if (
        not isinstance(weights, dict)
        or weights.get("file") != WEIGHTS_FILE
        or not isinstance(weights.get("sha256"), str)
    ):
        raise ArtefactError(f"{META_FILE}: 'weights' must name {WEIGHTS_FILE!r} with a sha256, got {weights!r:.120}")
    return meta


def _read_weights(
    path: Path, meta: dict, expected: dict[str, torch.Tensor], bounds: SceneBounds
) -> dict[str, torch.Tensor]:
    """The weights, checked against the checksum in meta and the expected names / shapes."""
    weights_path = path / WEIGHTS_FILE
    if not weights_path.is_file():
        raise ArtefactError(f"artefact {path} is missing {WEIGHTS_FILE}")
    data = weights_path.read_bytes()
    if _sha256(data) != meta["weights"]["sha256"]:
        raise ArtefactError(
            f"{WEIGHTS_FILE}: checksum mismatch ({len(data)} bytes on disk; the file is truncated, corrupt or replaced)"
        )
    try:
        tensors = load_safetensors_bytes(data)
    except (SafetensorError, ValueError, RuntimeError) as exc:
        raise ArtefactError(f"{WEIGHTS_FILE} cannot be parsed as safetensors: {exc}") from exc
    missing, unexpected = sorted(set(expected) - set(tensors)), sorted(set(tensors) - set(expected))
    if missing or unexpected:
        raise ArtefactError(
            f"{WEIGHTS_FILE} does not match the field config: missing {missing}, unexpected {unexpected}"
        )
    for name, ref in expected.items():
        got = tensors[name]
        if tuple(got.shape) != tuple(ref.shape):
            raise ArtefactError(
                f"{WEIGHTS_FILE}: tensor {name!r} has shape {tuple(got.shape)}, config implies {tuple(ref.shape)}"
            )
        if got.dtype != torch.float32:
            raise ArtefactError(f"{WEIGHTS_FILE}: tensor {name!r} has dtype {got.dtype}, expected float32")
        if not torch.isfinite(got).all():
            raise ArtefactError(f"{WEIGHTS_FILE}: tensor {name!r} contains non-finite values")
    from_json = {
        "bounds_lo": torch.tensor(bounds.lo, dtype=torch.float32),
        "bounds_hi": torch.tensor(bounds.hi, dtype=torch.float32),
        "time_range": torch.tensor([bounds.t0, bounds.t1], dtype=torch.float32),
    }
    for name, ref in from_json.items():
        if not torch.allclose(tensors[name], ref, rtol=1e-6, atol=1e-6):
            raise ArtefactError(f"{WEIGHTS_FILE}: {name} {tensors[name].tolist()} disagrees with {META_FILE} 'bounds'")
    return tensors
