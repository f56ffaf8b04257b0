"""LightField: the common shell of every field kind.

A field answers L(x, t, d) in world units: it owns its `SceneBounds` (mirrored as buffers so
a saved state dict is self-contained) and maps inputs to normalised coordinates before the
kind-specific network sees them. Subclasses implement `logits(xn, tn, d) -> z [B, 3]` and
the shell turns z into radiance with the bounded log-space activation of `FieldConfig`.

Hard inputs, by design:
* non-finite x / t are replaced by the box centre / capture start, and normalised positions
  and times are clamped to [-1, 1]: a query outside the box is answered as at the nearest
  point of the box (callers flag it via `SceneBounds.contains*`), so no input can produce an
  unbounded encoding;
* d is re-normalised; a zero or non-finite d becomes +y (any direction is as good);
* radiance = exp(lo + (hi - lo) sigmoid(z)) is always finite and positive.
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from typing import ClassVar

import torch
from pydantic import BaseModel
from torch import nn

from core.conventions import equirect_directions, equirect_width
from core.fields.components.emitters import Emitters
from core.fields.components.encodings import EquirectGridEncoding, TimeCodes, TimeGain
from core.fields.components.lattice import RoomLattice
from core.fields.components.normalization import SceneBounds
from core.fields.components.surfaces import ObservedSurfaces
from core.fields.kinds.config import FieldConfig
from core.fields.kinds.registry import field_class

# Rows per forward call in `envmaps`: bounds peak memory (the paper MLP keeps ~7 activations
# of width 256 per row: 2^16 rows ~ 0.5 GB in training mode, far less under inference_mode).
DEFAULT_CHUNK_ROWS = 1 << 16

# An untrained field answers about this radiance everywhere (small output weights), so the
# first renders are a plain grey room rather than random 12-decade noise.
INITIAL_RADIANCE = 1.0
OUTPUT_WEIGHT_SCALE = 0.1

# View-detail weights below this are 0 (beyond ~4.3 radii of every anchor), so probes away from
# the cameras skip the detail lookups, and every evaluation path agrees on which rows have it.
DETAIL_CUTOFF = 1e-4

# Emitter lobes in `envmaps` are at least this many pixels wide (sigma), so a lamp narrower than
# a pixel is area-averaged into the map rather than hit or missed by the pixel centres.
EMITTER_PIXEL_SIGMA = 0.6


class LightField(nn.Module):
    kind: ClassVar[str]  # set by @register_field
    Config: ClassVar[type[BaseModel]]  # the kind's settings section in FieldConfig

    def __init__(self, config: FieldConfig, bounds: SceneBounds):
        super().__init__()
        if config.kind != self.kind:
            raise ValueError(f"{type(self).__name__} is the {self.kind!r} field, the config asks for {config.kind!r}")
        self.config = config
        self.settings = config.section(self.kind)
        self.bounds = bounds
        self.register_buffer("bounds_lo", torch.tensor(bounds.lo, dtype=torch.float32))
        self.register_buffer("bounds_hi", torch.tensor(bounds.hi, dtype=torch.float32))
        self.register_buffer("time_range", torch.tensor([bounds.t0, bounds.t1], dtype=torch.float32))
        self.view_detail = None
        self.view_detail_time = None
        self.detail_time_rank = config.view_detail_time_rank if config.uses_time else 0
        if config.view_detail_heights:
            # static part first, then the time-varying maps (features 3 x (1 + rank)); a static
            # field's keys and shapes are those of the detail before it had a time part
            self.view_detail = EquirectGridEncoding(config.view_detail_heights, 3 * (1 + self.detail_time_rank))
            if self.detail_time_rank:
                self.view_detail_time = TimeCodes(config.view_detail_time_knots, self.detail_time_rank)
            anchors = torch.tensor(config.view_anchors, dtype=torch.float32).reshape(-1, 3)
            self.register_buffer("view_anchors", anchors, persistent=False)  # in the config, not the weights
        self.room_lattice = (
            RoomLattice(config.room_lattice, config.room_lattice_height) if config.room_lattice else None
        )
        self.time_gain = (
            TimeGain(config.time_gain_knots, config.time_gain_channels)
            if config.uses_time and config.time_gain_knots
            else None
        )
        self.emitters = (Emitters(config.emitter_count, config.emitter_knots, config.emitter_gate_resolution)
                         if config.emitter_count else None)
        self.surfaces = (ObservedSurfaces(config.surface_points, config.surface_knots, config.surface_height)
                         if config.surface_points else None)

    @property
    def uses_time(self) -> bool:
        return self.config.uses_time

    # ------------------------------------------------------------------ input handling
    def normalize_inputs(self, x: torch.Tensor, t: torch.Tensor | None, d: torch.Tensor):
        """World inputs -> (xn [B,3] in [-1,1], tn [B,1] in [-1,1] or None, unit d [B,3])."""
        xn = self._normalize_x(x)
        return xn, self._normalize_t(t, xn.shape[0]), unit_directions(d.to(xn.dtype))

    def _normalize_x(self, x: torch.Tensor) -> torch.Tensor:
        x = torch.as_tensor(x, dtype=self.bounds_lo.dtype, device=self.bounds_lo.device).reshape(-1, 3)
        centre = 0.5 * (self.bounds_lo + self.bounds_hi)
        x = torch.where(torch.isfinite(x), x, centre.expand_as(x))
        return (2.0 * (x - self.bounds_lo) / (self.bounds_hi - self.bounds_lo) - 1.0).clamp(-1.0, 1.0)

    def _normalize_t(self, t, n: int) -> torch.Tensor | None:
        """Seconds (scalar or [n]) -> [n, 1] in [-1, 1]; None when the field has no time input."""
        if not self.uses_time:
            return None
        if t is None:
            raise ValueError("t is required: this field has a time input (config.uses_time=True)")
        t = torch.as_tensor(t, dtype=self.bounds_lo.dtype, device=self.bounds_lo.device).reshape(-1)
        if t.numel() == 1 and n != 1:
            t = t.expand(n)
        if t.shape[0] != n:
            raise ValueError(f"t has {t.shape[0]} entries for {n} positions")
        t0, t1 = self.time_range[0], self.time_range[1]
        t = torch.where(torch.isfinite(t), t, t0)
        span = (t1 - t0).clamp_min(1e-12)
        return torch.where(t1 > t0, 2.0 * (t - t0) / span - 1.0, torch.zeros_like(t)).clamp(-1.0, 1.0)[:, None]

    def activate(self, z: torch.Tensor, tn: torch.Tensor | None = None) -> torch.Tensor:
        """z [B, 3] (or [P, N, 3] with tn [P, 1]) -> radiance exp(lo + (hi - lo) sigmoid(z)),
        times the time gain at tn where the field has one (its log kept within [lo, hi])."""
        lo, hi = self.config.log_radiance_min, self.config.log_radiance_max
        log_radiance = lo + (hi - lo) * torch.sigmoid(z)
        if self.time_gain is not None and tn is not None:
            gain = self.time_gain(tn)  # [B, channels] or [P, channels]
            log_radiance = (log_radiance + (gain if z.dim() == 2 else gain[:, None])).clamp(lo, hi)
        return torch.exp(log_radiance)

    def logit_for_radiance(self, radiance: float) -> float:
        """The z whose activation is `radiance` (for initialising output biases)."""
        lo, hi = self.config.log_radiance_min, self.config.log_radiance_max
        s = min(max((math.log(max(radiance, 1e-30)) - lo) / (hi - lo), 1e-6), 1 - 1e-6)
        return math.log(s / (1 - s))

    def _start_near_initial_radiance(self, output: nn.Linear) -> None:
        """Shrink the last layer's weights and set its bias to the logit of INITIAL_RADIANCE."""
        with torch.no_grad():
            output.weight.mul_(OUTPUT_WEIGHT_SCALE)
            output.bias.fill_(self.logit_for_radiance(INITIAL_RADIANCE))

    def time_variation(self) -> torch.Tensor | None:
        """The L1 total variation of the field's learned time codes, of its view detail's time
        coefficients, of its emitters' log intensities and of its time gain (None when it has none
        of them): the distillation penalises it so lighting changes only where the frames say so."""
        terms = [m.total_variation() for m in (getattr(self, "pe_t", None), self.view_detail_time, self.emitters,
                                               self.time_gain) if hasattr(m, "total_variation")]
        return sum(terms) if terms else None

    # ------------------------------------------------------------------ evaluation
    def logits(self, xn: torch.Tensor, tn: torch.Tensor | None, d: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    # ------------------------------------------------------------------ view detail
    def detail_weight(self, xn: torch.Tensor) -> torch.Tensor | None:
        """[B] weight of the view-detail residual at normalised positions (None: no detail)."""
        if self.view_detail is None or self.view_anchors.shape[0] == 0:
            return None
        x = self.bounds_lo + 0.5 * (xn + 1.0) * (self.bounds_hi - self.bounds_lo)
        # elementwise, not cdist (whose matmul path rounds with the batch size): a probe's answer
        # must not depend on what else is in the batch (see `envmaps`)
        r2 = (x.double()[:, None, :] - self.view_anchors.double()[None]).pow(2).sum(-1).amin(-1)
        w = torch.exp(-r2 / (2.0 * self.config.view_detail_radius ** 2)).to(xn.dtype)
        return torch.where(w >= DETAIL_CUTOFF, w, torch.zeros_like(w))

    def detail_parts(self, d: torch.Tensor) -> torch.Tensor:
        """[N, 1 + rank, 3] view-detail maps along unit directions d (the levels summed): the
        static part, then the time-varying ones (rank 0 without a time input)."""
        return self.view_detail(d).reshape(d.shape[0], -1, 1 + self.detail_time_rank, 3).sum(1)

    def combine_detail(self, parts: torch.Tensor, tn: torch.Tensor | None) -> torch.Tensor:
        """parts [N, 1 + rank, 3] at normalised times tn [N, 1] (or one [1, 1]) -> [N, 3]."""
        if self.view_detail_time is None:
            return parts[:, 0]
        coefficients = self.view_detail_time(tn)  # [N or 1, rank]
        return parts[:, 0] + (coefficients[..., None] * parts[:, 1:]).sum(1)

    def detail_logits(self, d: torch.Tensor, tn: torch.Tensor | None = None) -> torch.Tensor:
        """[N, 3] view-detail residual along unit directions d at normalised times tn [N, 1]."""
        return self.combine_detail(self.detail_parts(d), tn)

    def _with_detail(
        self, z: torch.Tensor, w: torch.Tensor | None, d: torch.Tensor, tn: torch.Tensor | None
    ) -> torch.Tensor:
        """z [B, 3] + w [B] x detail(d [B, 3], tn [B, 1]), the detail looked up only where w > 0."""
        if w is None:
            return z
        rows = torch.nonzero(w > 0).reshape(-1)
        if rows.numel() == 0:
            return z
        return z.index_add(0, rows, w[rows, None] * self.detail_logits(d[rows], None if tn is None else tn[rows]))

    def _with_lattice(self, z: torch.Tensor, xn: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """z [B, 3] + the room lattice's residual at xn [B, 3] along d [B, 3] (no lattice: z)."""
        return z if self.room_lattice is None else z + self.room_lattice(xn, d)

    # ------------------------------------------------------------------ emitters
    def _with_emitters(self, radiance: torch.Tensor, xn: torch.Tensor, tn: torch.Tensor | None, d: torch.Tensor,
                       sigma_floor: float) -> torch.Tensor:
        """radiance [B, 3] + the emitters' lobes at normalised xn [B or 1, 3], tn [B or 1, 1], unit
        d [B, 3], capped at the field's largest radiance (so the output stays finite)."""
        if self.emitters is None:
            return radiance
        x = self.bounds_lo + 0.5 * (xn + 1.0) * (self.bounds_hi - self.bounds_lo)
        added = self.emitters.radiance(x, xn, tn, d, sigma_floor)
        return (radiance + added).clamp(max=math.exp(self.config.log_radiance_max))

    # ------------------------------------------------------------------ observed surfaces
    def _has_surfaces(self) -> bool:
        return self.surfaces is not None and not self.surfaces.is_empty()

    def _surface_table(self, xn: torch.Tensor, tn: torch.Tensor | None) -> torch.Tensor | None:
        """The surfaces' look-up table of one probe at normalised xn [1, 3], tn [1, 1] or None."""
        x = self.bounds_lo + 0.5 * (xn + 1.0) * (self.bounds_hi - self.bounds_lo)
        return self.surfaces.splat(x, tn, math.exp(self.config.log_radiance_max))

    def _blend_surfaces(self, radiance: torch.Tensor, table: torch.Tensor | None, d: torch.Tensor,
                        keep: torch.Tensor | float) -> torch.Tensor:
        """radiance [N, 3] along unit d [N, 3] of one probe, moved towards its surfaces' table by
        coverage x keep (keep: 1 - the view-detail weight, a float or [N])."""
        if table is None:
            return radiance
        observed, coverage = self.surfaces.lookup(table, d)
        return self.surfaces.blend(radiance, observed, coverage * keep, math.exp(self.config.log_radiance_min))

    def _with_surfaces(self, radiance: torch.Tensor, xn: torch.Tensor, tn: torch.Tensor | None, index: torch.Tensor,
                       d: torch.Tensor, w_rows: torch.Tensor | None) -> torch.Tensor:
        """radiance [B, 3] of rows looking along d [B, 3] from probes xn[index] (tn[index]) with
        the observed surfaces blended in, one splat per probe (w_rows: the rows' detail weights)."""
        out = radiance.clone()
        for p in torch.unique(index).tolist():
            rows = torch.nonzero(index == p).reshape(-1)
            keep = 1.0 if w_rows is None else 1.0 - w_rows[rows]
            if w_rows is not None and not bool((keep > 0).any()):
                continue  # at a camera the photo fit answers: no splat (a blend by 0 is the identity)
            table = self._surface_table(xn[p:p + 1], None if tn is None else tn[p:p + 1])
            out[rows] = self._blend_surfaces(radiance[rows], table, d[rows], keep)
        return out

    def forward(self, x: torch.Tensor, t: torch.Tensor | None, d: torch.Tensor) -> torch.Tensor:
        """x [B,3] world metres, t [B] seconds (ignored when uses_time=False), d [B,3] -> [B,3] > 0.
        With observed surfaces, each distinct (x, t) among the rows costs one splat of the layer."""
        xn, tn, d = self.normalize_inputs(x, t, d)
        w = self.detail_weight(xn)
        out = self.activate(self._with_detail(self._with_lattice(self.logits(xn, tn, d), xn, d), w, d, tn), tn)
        if self._has_surfaces():
            keys = xn if tn is None else torch.cat((xn, tn), -1)
            probes, index = torch.unique(keys, dim=0, return_inverse=True)  # one splat per distinct probe
            out = self._with_surfaces(out, probes[:, :3], None if tn is None else probes[:, 3:], index, d, w)
        return self._with_emitters(out, xn, tn, d, self.config.emitter_sigma_floor)

    def envmaps(
        self, xs: torch.Tensor, ts: torch.Tensor | None, height: int, chunk_rows: int = DEFAULT_CHUNK_ROWS
    ) -> torch.Tensor:
        """Env maps [P, H, 2H, 3] seen from probes xs [P,3] at times ts [P] (see conventions).

        Generic path: evaluates every (probe, direction) pair in chunks of `chunk_rows`.
        Kinds with shared per-probe work override `_envmap_logits`.

        Probes are evaluated one at a time, so a probe's map is bit-identical whatever else is
        in the batch: CPU matrix products round differently with the number of rows (a 1-row
        product takes another kernel), and the service batches unrelated clients' queries.
        """
        xn = self._normalize_x(xs)
        tn = self._normalize_t(ts, xn.shape[0])
        height = int(height)
        dirs = equirect_directions(height, device=xn.device).reshape(-1, 3)
        z = torch.cat([self._envmap_logits(xn[p:p + 1], None if tn is None else tn[p:p + 1], dirs, chunk_rows)
                       for p in range(xn.shape[0])]) if xn.shape[0] else xn.new_empty(0, dirs.shape[0], 3)  # [P, N, 3]
        if self.room_lattice is not None and xn.shape[0]:
            blended = self.room_lattice.blended(xn)  # per probe, elementwise: batch-independent
            for dl in direction_blocks(dirs.shape[0], chunk_rows):
                z[:, dl] = z[:, dl] + self.room_lattice.sample(blended, dirs[dl])
        w = self.detail_weight(xn)
        if w is not None and bool((w > 0).any()):
            near = torch.nonzero(w > 0).reshape(-1).tolist()
            for dl in direction_blocks(dirs.shape[0], chunk_rows):  # a block at a time: a 2K map has 2 M directions
                parts = self.detail_parts(dirs[dl])  # looked up once; each probe weighs them at its own time
                for p in near:
                    z[p, dl] = z[p, dl] + w[p] * self.combine_detail(parts, None if tn is None else tn[p:p + 1])
        out = self.activate(z, tn)
        if self._has_surfaces():
            for p in range(xn.shape[0]):
                keep = 1.0 - (0.0 if w is None else float(w[p]))
                if keep <= 0.0:
                    continue  # at a camera the photo fit answers: no splat (a blend by 0 is the identity)
                table = self._surface_table(xn[p:p + 1], None if tn is None else tn[p:p + 1])
                for dl in direction_blocks(dirs.shape[0], chunk_rows):
                    out[p, dl] = self._blend_surfaces(out[p, dl], table, dirs[dl], keep)
        if self.emitters is not None:
            floor = EMITTER_PIXEL_SIGMA * math.pi / height
            for p in range(xn.shape[0]):
                for dl in direction_blocks(dirs.shape[0], chunk_rows):  # the probe's row broadcasts over the block
                    out[p, dl] = self._with_emitters(out[p, dl], xn[p:p + 1], None if tn is None else tn[p:p + 1],
                                                     dirs[dl], floor)
        return out.reshape(xn.shape[0], height, equirect_width(height), 3)

    def probe_radiance(self, xs: torch.Tensor, ts, probe_index: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Radiance [B,3] of rows that share a few probe positions (differentiable).

        Row b looks along d[b] from xs[probe_index[b]] at ts[probe_index[b]] (ts: [P], a scalar
        or None). Equals forward(xs[probe_index], ts[probe_index], d), but kinds with per-probe
        work (trunk, MLP encoding layers) do it once per probe: the distillation's ball
        rendering path, where thousands of rows share 9 probes.
        """
        xn = self._normalize_x(xs)
        tn = self._normalize_t(ts, xn.shape[0])
        index = torch.as_tensor(probe_index, dtype=torch.long, device=xn.device).reshape(-1)
        d = unit_directions(d.to(xn.dtype))
        w = self.detail_weight(xn)
        tn_rows = None if tn is None else tn[index]
        z = self._probe_logits(xn, tn, index, d)
        if self.room_lattice is not None:  # blended once per probe, then looked up per row
            z = z + self.room_lattice.rows(self.room_lattice.blended(xn), index, d)
        out = self.activate(self._with_detail(z, None if w is None else w[index], d, tn_rows), tn_rows)
        if self._has_surfaces():
            out = self._with_surfaces(out, xn, tn, index, d, None if w is None else w[index])
        return self._with_emitters(out, xn[index], tn_rows, d, self.config.emitter_sigma_floor)

    def _probe_logits(self, xn, tn, index, d) -> torch.Tensor:
        return self.logits(xn[index], None if tn is None else tn[index], d)

    def _envmap_logits(self, xn, tn, dirs, chunk_rows: int) -> torch.Tensor:
        n_probes, n_dirs = xn.shape[0], dirs.shape[0]
        out = xn.new_empty(n_probes, n_dirs, 3)
        probes_per_chunk = max(1, chunk_rows // n_dirs)
        dirs_per_chunk = min(n_dirs, chunk_rows)
        for p0 in range(0, n_probes, probes_per_chunk):
            p1 = min(n_probes, p0 + probes_per_chunk)
            for k0 in range(0, n_dirs, dirs_per_chunk):
                k1 = min(n_dirs, k0 + dirs_per_chunk)
                n_p, n_k = p1 - p0, k1 - k0
                x_rows = xn[p0:p1, None].expand(n_p, n_k, 3).reshape(-1, 3)
                t_rows = None if tn is None else tn[p0:p1, None].expand(n_p, n_k, 1).reshape(-1, 1)
                d_rows = dirs[None, k0:k1].expand(n_p, n_k, 3).reshape(-1, 3)
                out[p0:p1, k0:k1] = self.logits(x_rows, t_rows, d_rows).reshape(n_p, n_k, 3)
        return out


def build_field(config: FieldConfig, bounds: SceneBounds) -> LightField:
    """A freshly initialised field of `config.kind` normalised to `bounds` (float32, CPU)."""
    return field_class(config.kind)(config, bounds)


def probe_chunks(n_probes: int, n_dirs: int, chunk_rows: int) -> Iterator[slice]:
    """Slices of whole probes whose (probe, direction) rows fit in `chunk_rows` (>= 1 probe each):
    the chunking of the kinds that evaluate all directions of a probe at once."""
    step = max(1, chunk_rows // n_dirs)
    return (slice(p0, p0 + step) for p0 in range(0, n_probes, step))


def direction_blocks(n_dirs: int, chunk_rows: int) -> Iterator[slice]:
    """Slices of at most `chunk_rows` directions: a 1024-row map is 2 M directions, and its
    per-direction terms alone would take gigabytes if computed at once."""
    step = max(1, chunk_rows)
    return (slice(k0, min(k0 + step, n_dirs)) for k0 in range(0, n_dirs, step))


def unit_directions(d: torch.Tensor) -> torch.Tensor:
    """Normalise d [B,3]; zero-length rows and rows with a non-finite component become +y."""
    finite = torch.isfinite(d).all(dim=-1, keepdim=True)
    d = torch.where(finite, d, torch.zeros_like(d))
    n = d.norm(dim=-1, keepdim=True)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=d.dtype, device=d.device).expand_as(d)
    return torch.where(n > 1e-30, d / n.clamp_min(1e-30), up)
