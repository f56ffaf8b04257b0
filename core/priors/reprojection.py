"""ReprojectionPrior: the embedded, weights-free default prior (a CLASSICAL BASELINE).

It answers "what would a chrome ball at c show?" from the frame itself:

1. Linearise the frame with the inverse tone map (at ev 0, the capture's exposure), at the
   capture's FULL resolution (Capture.full_resolution: area-averaging LDR values first would
   hide which pixels clipped and average in gamma space), then area-resize the radiance to
   the working resolution. A clipped pixel (any channel >= CLIP_LDR) only says "at least
   white"; light sources are what clips, so clip_rule "estimate" (default) estimates each
   clipped blob's radiance from exposure changes across frames and from its size and halo
   (core.capture.highlights; rule and measured error in docs/highlights.md); "fixed"
   multiplies by clip_boost (the old behaviour, CLIP_BOOST = 8).
2. Unproject the frame with its depth into a coloured point cloud. The geometry is computed
   once per distinct (pose, depth) — once in total for a static camera with static depth;
   colours come from the requested frame, so lighting changes over time are followed. When
   the engine has decided the lighting is static, a moving camera's request also splats the
   other viewpoints (all of them unless `merge_views` is configured; points thinned to a
   budget, OTHER_VIEWS_POINTS), so a probe sees what any frame saw; each frame's radiance is
   first merged with the other frames' readings of the same surfaces (core.capture.hdr_merge:
   what one frame clipped or left dark another exposed well).
3. For each probe centre, splat the points into an equirect env map (ENV height from the
   config) with a depth test: per env pixel only points within Z_TOLERANCE of the nearest
   distance contribute (a z-buffer by distance from the probe), averaged. back_faces "dark"
   gives radiance 0 (still occluding) to points whose surface faces away from the probe (the
   probe is behind the side the frame saw: under a table whose top the camera sees), since
   their back was never observed; "front" (default) reuses their observed side's radiance.
   "dark" makes this prior better, but the field distilled from it is not (docs/engine.md,
   "Back faces").
4. Fill directions the frame never observed by pull-push (push_pull_fill): weight-average the
   observed pixels down a pyramid to one pixel, then blend each level with the upsampled
   coarser one by its weight (columns wrap at the seam). With unseen_fill "indoor" (default)
   the unseen directions then get an elevation gain fitted on the indoor panoramas (scored
   leave-one-room-out) and the seen mean colour, moving towards the light's colour (grey-edge
   of the frames) where the fill is bright (core.priors.indoor_fill). This is a smooth
   extrapolation of what was seen (e.g. the room behind the camera gets the average colour
   of the nearby walls, floor and ceiling). No light source is invented.
5. Render the balls under those env maps (core.chrome_ball, probe-centre lookup) and tone
   map at request.ev; pixels outside the balls are request.image.

Limitations (by design): it cannot know lights outside the view, the true brightness of
clipped sources, or view-dependent effects; it is the CPU-fast default and a baseline for
the diffusion prior, not a replacement for it.
"""
from __future__ import annotations

import functools
import math
from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import Field, NonNegativeFloat, PositiveFloat

from core.capture.depth import surface_normals
from core.capture.hdr_merge import capture_reading_weights, merge_frames
from core.capture.highlights import CLIP_LDR, RULE_COEFFICIENTS, SPILL_COLOUR, linearise_highlights
from core.conventions import expose, inverse_tonemap
from core.envmap import SPLAT_Z_TOLERANCE, resize_envmap, splat_points, voxel_merge
from core.priors.base import Prior, PriorCapabilities, PriorConfig, PriorError, PriorRequest
from core.priors.indoor_fill import LIGHT_COLOUR_KNEE, SOURCE_CAP, cap_sources, fill_unseen, grey_edge
from core.priors.known import ball_target
from core.priors.registry import prior_settings, register_prior

CLIP_BOOST = 8.0  # clip_rule "fixed" only
Z_TOLERANCE = SPLAT_Z_TOLERANCE  # the z-buffer of core.envmap.splat_points
OTHER_VIEW_STRIDE = 3  # merged viewpoints contribute at most a third of their points (cost) ...
OTHER_VIEWS_POINTS = 16384  # ... and this many points in all
STATIC_CLOUD_POINTS = 12288  # still light, moving camera: one cloud of every frame's points, voxel-merged


def linear_frames(capture, clip_rule: str = "estimate", clip_boost: float = CLIP_BOOST,
                  lighting_changes: bool = True, clip_coefficients: tuple[float, ...] | None = None,
                  spill_colour: tuple[float, float] | None = None) -> torch.Tensor:
    """Linear radiance [T, H, W, 3] (ev 0; each frame's stated exposure removed) of a capture
    at its own resolution, linearised at the resolution it was resized from (see the module
    docstring, step 1). Exposure changes between frames are used only for a static camera
    under static lighting (a lamp switching off must not read as an exposure change).
    `clip_coefficients`: the blob rule's (None: core.capture.highlights.RULE_COEFFICIENTS);
    `spill_colour`: its white-hot pixels' (min excess, min ratio) (None: highlights.SPILL_COLOUR)."""
    src = capture.full_resolution or capture
    if clip_rule == "fixed":
        lin = linearise(src.frames, clip_boost)
    else:
        ev = src.stated_ev
        known = None if ev is None else torch.pow(2.0, ev.double() - float(ev[0]))  # frame t's exposure / frame 0's
        lin = linearise_highlights(src.frames, src.intrinsics, src.static_camera and not lighting_changes,
                                   coefficients=clip_coefficients or RULE_COEFFICIENTS,
                                   static_camera=src.static_camera, known_ratios=known,
                                   spill=spill_colour or SPILL_COLOUR)
    if src.stated_ev is not None:  # each frame's own units -> one scale (ev 0)
        lin = expose(lin, -src.frame_ev.to(lin.dtype)[:, None, None, None])
    if src is not capture and (src.height, src.width) != (capture.height, capture.width):
        lin = F.interpolate(lin.permute(0, 3, 1, 2), size=(capture.height, capture.width), mode="area").permute(
            0, 2, 3, 1
        )
    return lin.contiguous()


def linearise(frames: torch.Tensor, clip_boost: float = CLIP_BOOST) -> torch.Tensor:
    """LDR [..., 3] -> linear radiance (ev 0) with clipped pixels boosted by `clip_boost`."""
    lin = inverse_tonemap(frames.clamp(0, 1))
    clipped = frames.amax(dim=-1, keepdim=True) >= CLIP_LDR
    return torch.where(clipped, lin * clip_boost, lin)


@functools.lru_cache(maxsize=64)
def _upsample_matrix(n_fine: int, n_coarse: int, wrap: bool) -> torch.Tensor:
    """[n_fine, n_coarse] linear interpolation from coarse to fine pixel centres, where coarse
    pixel j is the average of fine pixels 2j and 2j+1 (its centre: their mean index; the last
    one of an odd size has one child). `wrap`: the axis is periodic (equirect columns).
    Cached (the same few sizes every call): callers must not modify the result."""
    centres = torch.tensor([(2 * j + min(2 * j + 1, n_fine - 1)) / 2 for j in range(n_coarse)], dtype=torch.float64)
    A = torch.zeros(n_fine, n_coarse, dtype=torch.float64)
    if n_coarse == 1:
        return A + 1.0
    for i in range(n_fine):
        if wrap:  # nearest centres below and above i on the circle of length n_fine
            below = max(range(n_coarse), key=lambda j: -((i - centres[j]) % n_fine))
            above = (below + 1) % n_coarse
            gap = float((centres[above] - centres[below]) % n_fine) or float(n_fine)
            t = float((i - centres[below]) % n_fine) / gap
        else:
            above = int(torch.searchsorted(centres, torch.tensor(float(i), dtype=torch.float64)).clamp(1, n_coarse - 1))
            below = above - 1
            t = float(((i - centres[below]) / (centres[above] - centres[below])).clamp(0.0, 1.0))
        A[i, below] += 1.0 - t
        A[i, above] += t
    return A


def push_pull_fill(env: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Fill pixels with weight 0 in equirect env maps [N, h, w, 3] by pull-push (Gortler et al.
    1996, the Lumigraph's hole filling).

    Pull: each coarser level is the weight-averaged 2x2 downsample (value = sum w x / sum w,
    weight = min(1, sum w)), down to ONE pixel, so every hole has an observed ancestor.
    Push: from the top, fine = w x + (1 - w) upsample(coarse), the upsample linear between
    pixel centres, columns wrapping around the phi = +-pi seam. Observed pixels (weight 1)
    keep their values; holes get a smooth extrapolation of what was seen. With no observed
    pixel at all the result is 0. `weight` may be fractional (in [0, 1])."""
    x = env.permute(0, 3, 1, 2).to(torch.float64)  # [N, 3, h, w]
    w = weight[:, None].to(torch.float64).clamp(0.0, 1.0)
    levels = [(x, w)]
    while x.shape[-2] > 1 or x.shape[-1] > 1:
        kh = 2 if x.shape[-2] > 1 else 1
        kw = 2 if x.shape[-1] > 1 else 1
        num, den = _sum_pool(x * w, kh, kw), _sum_pool(w, kh, kw)
        x = num / den.clamp_min(1e-12)
        w = den.clamp(max=1.0)
        levels.append((x, w))
    filled = levels[-1][0]
    for (x, w), (coarse, _) in zip(reversed(levels[:-1]), reversed(levels[1:])):
        rows = _upsample_matrix(x.shape[-2], coarse.shape[-2], wrap=False)
        cols = _upsample_matrix(x.shape[-1], coarse.shape[-1], wrap=True)
        up = torch.einsum("ij,ncjk,lk->ncil", rows, filled, cols)
        filled = w * x + (1.0 - w) * up
    return filled.permute(0, 2, 3, 1).to(env.dtype).contiguous()


def _sum_pool(x: torch.Tensor, kh: int, kw: int) -> torch.Tensor:
    """Sum over (kh, kw) blocks; an odd edge's last block has fewer pixels (zero padding)."""
    H, W = x.shape[-2:]
    x = F.pad(x, (0, (-W) % kw, 0, (-H) % kh))
    n, c, H2, W2 = x.shape
    return x.reshape(n, c, H2 // kh, kh, W2 // kw, kw).sum((3, 5))


class ReprojectionSettings(PriorConfig):
    env_height: int = Field(32, ge=4, description="splat resolution: env maps of env_height x 2 env_height")
    clip_rule: Literal["estimate", "fixed"] = Field(
        "estimate",
        description=(
            "clipped pixels: 'estimate' their radiance per blob (core.capture.highlights) or multiply by clip_boost "
            "('fixed')"
        ),
    )
    clip_boost: float = Field(
        CLIP_BOOST, gt=0, description="radiance factor of clipped (>= CLIP_LDR) pixels with clip_rule 'fixed'"
    )
    clip_coefficients: tuple[float, float, float, float, float] | None = Field(None, description=(
        "with clip_rule 'estimate': the blob rule's coefficients (core.capture.highlights.Blob.features); null: "
        "RULE_COEFFICIENTS (benches pass coefficients refitted without the scored room)"))
    spill_colour: tuple[NonNegativeFloat, PositiveFloat] | None = Field(None, description=(
        "with clip_rule 'estimate': the white-hot pixels' spill colour settings (min excess over the halo's "
        "background, min channel ratio: core.capture.highlights.Blob.spill_colour); null: SPILL_COLOUR_MIN_EXCESS "
        "and SPILL_COLOUR_MIN_RATIO (benches pass the settings chosen without the scored room)"))
    unseen_fill: Literal["indoor", "push-pull"] = Field(
        "indoor",
        description=(
            "unobserved directions: pull-push with the indoor elevation gain and the seen mean colour "
            "(core.priors.indoor_fill), "
            "or plain pull-push"
        ),
    )
    fill_source_cap: float | None = Field(SOURCE_CAP, gt=0, description=(
        "with unseen_fill 'indoor': seen radiance above this multiple of the seen median luminance is capped "
        "before it is extrapolated into unseen directions (core.priors.indoor_fill.cap_sources); null: not capped"))
    light_colour_knee: float | None = Field(LIGHT_COLOUR_KNEE, gt=0, description=(
        "with unseen_fill 'indoor': unseen directions brighter than the fill's median move from the walls' colour "
        "towards the light's (grey-edge of the frames), all the way at (1 + this) x the median "
        "(core.priors.indoor_fill, rule 4); null: the walls' colour everywhere"))
    elevation_gain: tuple[PositiveFloat, ...] | None = Field(
        None,
        min_length=2,
        description=(
            "with unseen_fill 'indoor': the unseen directions' brightness profile from up to down (any number of rows, "
            "each > 0); null: core.priors.indoor_fill.ELEVATION_GAIN (benches pass a profile refitted without the "
            "scored room)"
        ),
    )
    back_faces: Literal["dark", "front"] = Field("front", description=(
        "points whose observed side faces away from the probe: occluders of radiance 0 ('dark') or with the "
        "radiance of their observed side ('front')"))
    merge_views: int | None = Field(None, ge=1, description=(
        "viewpoints a request splats (its own + evenly spaced others); only valid when the lighting is static. "
        "None: every frame when bind() is told the lighting is static and the camera moves, else 1"))


@register_prior("reprojection", for_jobs=True)
class ReprojectionPrior(Prior):
    Config = ReprojectionSettings
    capabilities = PriorCapabilities(frame_geometry=True, envmaps=True, envmaps_anywhere=True, view_radiance=True)

    def __init__(self, **settings):
        """Settings: see ReprojectionSettings (PriorError when one is out of range)."""
        s = prior_settings(self.name, settings)
        self.env_height = int(s.env_height)
        self.clip_boost = float(s.clip_boost)
        self.clip_rule = s.clip_rule
        self.clip_coefficients = None if s.clip_coefficients is None else tuple(float(c) for c in s.clip_coefficients)
        self.spill_colour = None if s.spill_colour is None else (float(s.spill_colour[0]), float(s.spill_colour[1]))
        self.unseen_fill = s.unseen_fill
        self.fill_source_cap = s.fill_source_cap
        self.light_colour_knee = s.light_colour_knee
        self.elevation_gain = None if s.elevation_gain is None else tuple(float(g) for g in s.elevation_gain)
        self.back_faces = s.back_faces
        self.configured_merge_views = s.merge_views
        self.merge_views = s.merge_views or 1
        self._capture = None
        self._colors: torch.Tensor | None = None
        self._light: torch.Tensor | None = None  # [T, 3]: each frame's grey-edge light colour
        self._points: dict[int, torch.Tensor] = {}
        self._normals: dict[int, torch.Tensor] = {}
        self._camera_maps: dict[int, torch.Tensor] = {}  # frame -> its map at its own camera centre
        self._geometry_key: list[int] = []
        self._static_cloud: tuple[torch.Tensor, torch.Tensor] | None = None
        self.point_cloud_builds = 0  # how many times geometry was unprojected (reported)

    # ------------------------------------------------------------------ per capture
    def bind(self, capture, *, lighting_changes: bool = True) -> None:
        """Linearise all frames once and work out which frames share geometry."""
        self._capture = capture
        static_lighting_moving_camera = not lighting_changes and not capture.static_camera
        self.merge_views = self.configured_merge_views or (capture.num_frames if static_lighting_moving_camera else 1)
        self._colors = linear_frames(capture, self.clip_rule, self.clip_boost, lighting_changes, self.clip_coefficients,
                                     self.spill_colour)
        self._light = grey_edge(capture.frames)
        self._static_cloud = None
        if static_lighting_moving_camera:  # what one frame clipped or lost in the black, another saw
            self._colors = merge_frames(capture, self._colors, capture_reading_weights(capture))
        self._points = {}
        self._normals = {}
        self._camera_maps = {}
        self.point_cloud_builds = 0
        # frames with the same pose and the same depth share one point cloud
        key: list[int] = []
        for i in range(capture.num_frames):
            owner = i
            for j in sorted(set(key)):
                if torch.equal(capture.poses[i], capture.poses[j]) and torch.equal(
                    torch.nan_to_num(capture.depth[i], nan=-1.0), torch.nan_to_num(capture.depth[j], nan=-1.0)
                ):
                    owner = j
                    break
            key.append(owner)
        self._geometry_key = key
        if static_lighting_moving_camera and self.configured_merge_views is None and self.back_faces == "front":
            self._static_cloud = self._merged_cloud()

    def _merged_cloud(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Every frame's points with their (merged) radiance, voxel-merged to STATIC_CLOUD_POINTS:
        under still light a surface looks the same from every frame, so one cloud answers every
        request, whatever frame it comes from."""
        owners = sorted(set(self._geometry_key))
        pts = torch.cat([self.points(v) for v in owners])
        col = torch.cat([self._colors[v].reshape(-1, 3) for v in owners])
        ok = torch.isfinite(pts).all(-1) & torch.isfinite(col).all(-1)
        pts, col = voxel_merge(pts[ok].double(), col[ok].double(), STATIC_CLOUD_POINTS)
        return pts.float(), col.float()

    def prepare_frame(self, frame_index: int) -> None:
        self.points(frame_index)

    def points(self, frame_index: int) -> torch.Tensor:
        """World points [H*W, 3] of a frame (NaN rows where depth is invalid), cached."""
        owner = self._geometry_key[frame_index]
        if owner not in self._points:
            self._points[owner] = (
                self._capture.camera(owner).unproject(self._capture.depth[owner].float()).reshape(-1, 3)
            )
            self.point_cloud_builds += 1
        return self._points[owner]

    def normals(self, frame_index: int) -> torch.Tensor:
        """Unit normals [H*W, 3] of `points(frame_index)`, facing the camera that saw them, cached."""
        owner = self._geometry_key[frame_index]
        if owner not in self._normals:
            cap = self._capture
            pts = self.points(owner).reshape(cap.height, cap.width, 3)
            self._normals[owner] = surface_normals(pts, cap.poses[owner, :3, 3]).reshape(-1, 3)
        return self._normals[owner]

    def views_for(self, frame_index: int) -> list[tuple[int, int]]:
        """(frame, stride) whose point clouds a request for `frame_index` splats (see merge_views):
        its own in full, the others every stride-th point, within OTHER_VIEWS_POINTS in all."""
        own = self._geometry_key[frame_index]
        if self.merge_views == 1:
            return [(frame_index, 1)]
        owners = sorted(set(self._geometry_key) - {own})
        k = min(self.merge_views - 1, len(owners))
        picked = sorted({owners[round(j * (len(owners) - 1) / max(k - 1, 1))] for j in range(k)}) if k else []
        per_frame = self._capture.height * self._capture.width
        stride = max(OTHER_VIEW_STRIDE, math.ceil(len(picked) * per_frame / OTHER_VIEWS_POINTS))
        return [(frame_index, 1)] + [(v, stride) for v in picked]

    # ------------------------------------------------------------------ per request
    def frame_at(self, time: float) -> int:
        """The index of the frame nearest to `time` (seconds): the frame a request at `time` splats."""
        if self._capture is None:
            raise PriorError("ReprojectionPrior.bind(capture) must be called before use")
        return int(self._capture.nearest_frames(torch.tensor([float(time)]))[0])

    def envmaps(self, centers: torch.Tensor, time: float, height: int) -> torch.Tensor:
        """HDR env maps [N, height, 2 height, 3] seen from `centers` [N, 3] in the frame nearest
        to `time`, splatted at env_height and resized (area-correct down, bilinear up)."""
        frame = self.frame_at(time)
        with torch.no_grad():
            env = self.envmaps_at_frame(torch.as_tensor(centers, dtype=torch.float32), frame)
        return env if height == self.env_height else torch.stack([resize_envmap(m, height) for m in env])

    def observed_envmaps(self, centers: torch.Tensor, time: float) -> tuple[torch.Tensor, torch.Tensor]:
        """What `envmaps` splats before any fill: radiance [N, h, 2h, 3] (0 where unseen) and the
        seen mask [N, h, 2h] at env_height, from `centers` [N, 3] in the frame nearest to `time`
        (with its merged viewpoints). Where seen, `envmaps` at env_height answers the same."""
        frame = self.frame_at(time)
        with torch.no_grad():
            return self._splat_seen(torch.as_tensor(centers, dtype=torch.float32), frame)

    def envmaps_at_frame(self, centers: torch.Tensor, frame_index: int) -> torch.Tensor:
        """HDR env maps [N, h, 2h, 3] (h = env_height) seen from `centers` [N, 3] in frame `frame_index`.
        The map at the frame's own camera centre (asked every radiance step) is splatted once."""
        if self._capture is None:
            raise PriorError("ReprojectionPrior.bind(capture) must be called before use")
        at_camera = (centers == self._capture.poses[frame_index, :3, 3].to(centers.dtype)).all(-1)
        if not bool(at_camera.any()):
            return self._splat(centers, frame_index)
        if frame_index not in self._camera_maps:
            self._camera_maps[frame_index] = self._splat(centers[at_camera][:1], frame_index)[0]
        out = self._camera_maps[frame_index].expand(centers.shape[0], -1, -1, -1).clone()
        if bool((~at_camera).any()):
            out[~at_camera] = self._splat(centers[~at_camera], frame_index)
        return out

    def _splat(self, centers: torch.Tensor, frame_index: int) -> torch.Tensor:
        env, seen = self._splat_seen(centers, frame_index)
        if self.unseen_fill != "indoor":
            return push_pull_fill(env, seen)
        # the walls, not the lamps, set the fill's level and colour
        source = cap_sources(env, seen, self.fill_source_cap)
        extrapolated = push_pull_fill(source, seen)
        # the light's colour from the frames this request splats (all of them for one merged cloud)
        frames = [v for v, _ in self.views_for(frame_index)] if self._static_cloud is None else slice(None)
        return fill_unseen(torch.where(seen[..., None], env, extrapolated), source, seen, self.elevation_gain,
                           self._light[frames].mean(0), self.light_colour_knee)

    def _splat_seen(self, centers: torch.Tensor, frame_index: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Splatted radiance [N, h, w, 3] and its seen mask [N, h, w] (no fill)."""
        if self._static_cloud is not None:
            return splat_points(*self._static_cloud, centers, self.env_height)
        views, stride = zip(*self.views_for(frame_index))
        pts = torch.cat([self.points(v)[::k] for v, k in zip(views, stride)])
        col = torch.cat([self._colors[v].reshape(-1, 3)[::k] for v, k in zip(views, stride)])
        ok = torch.isfinite(pts).all(-1)
        pts, col = pts[ok], col[ok]
        if self.back_faces == "dark":  # the probe sees the unobserved back of the surface (NaN normal: front)
            nrm = torch.cat([self.normals(v)[::k] for v, k in zip(views, stride)])[ok]
            rel = pts[None, :, :] - centers[:, None, :].to(pts.dtype)  # [N, P, 3]
            col = torch.where(
                ((rel * nrm[None]).sum(-1) > 0)[..., None], 0.0, col[None].expand(centers.shape[0], -1, 3)
            )
        return splat_points(pts, col, centers, self.env_height)

    def view_radiance(self, frame_index: int) -> torch.Tensor:
        """The frame's linearised pixels (clip rule applied): what its env maps splat."""
        if self._colors is None:
            raise PriorError("ReprojectionPrior.bind(capture) must be called before use")
        return self._colors[frame_index]

    def __call__(self, request: PriorRequest) -> torch.Tensor:
        p = request.probes
        with torch.no_grad():
            env = self.envmaps_at_frame(torch.as_tensor(p.centers, dtype=torch.float32), int(p.frame_index))
        return ball_target(request, env)

    def describe(self) -> dict:
        return {
            "name": self.name,
            "kind": "classical reprojection baseline (no weights; cannot invent out-of-view lights)",
            "env_height": self.env_height,
            "clip_ldr": CLIP_LDR,
            "clip_rule": self.clip_rule,
            "clip_boost": self.clip_boost if self.clip_rule == "fixed" else None,
            "clip_coefficients": list(self.clip_coefficients or RULE_COEFFICIENTS) if self.clip_rule == "estimate"
            else None,
            "spill_colour": list(self.spill_colour or SPILL_COLOUR)
            if self.clip_rule == "estimate" else None,
            "z_tolerance": Z_TOLERANCE,
            "hole_fill": "pull-push pyramid in the equirect domain" + (
                " + indoor elevation gain, the seen mean colour and the light's"
                if self.unseen_fill == "indoor" else ""),
            "fill_source_cap": self.fill_source_cap if self.unseen_fill == "indoor" else None,
            "light_colour_knee": self.light_colour_knee if self.unseen_fill == "indoor" else None,
            "back_faces": self.back_faces,
            "merge_views": self.merge_views,
            "merged_cloud_points": None if self._static_cloud is None else int(self._static_cloud[0].shape[0]),
            "point_cloud_builds": self.point_cloud_builds,
        }
