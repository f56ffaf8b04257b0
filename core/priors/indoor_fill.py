"""What an indoor room looks like where the camera did not look: the reprojection prior's
fill for unobserved directions (a small statistical prior, not a light source finder).

Pull-push (core.priors.reprojection.push_pull_fill) extrapolates the seen pixels smoothly,
which gives every unseen direction roughly the brightness and the colour of the walls the
photo happened to show. Four regularities of indoor light that a plain extrapolation
misses. Each value below is what a user gets: fitted or chosen on ALL 24 indoor panoramas
of MANIFEST.tsv (dev, test and extra). None of them is scored on the rooms it was fitted
on: `python -m bench.real_panoramas --cv` refits each of them per fold without the scored
room (the profile from the other 23 rooms' row means; SOURCE_CAP and LIGHT_COLOUR_KNEE chosen
on the other 23 by the same rules as here), and each rule's held-out effect is in docs/engine.md, "Accuracy
mechanisms under cross-validation" (bench/results/cv/).

1. Brightness depends on elevation: ELEVATION_GAIN[k] is the mean over the indoor panoramas
   of row-mean luminance / the panorama's mean luminance within +-HORIZON_BAND_DEG of the
   horizon, for GAIN_ROWS bands of 180/GAIN_ROWS degrees from up (+y, docs/conventions.md)
   to down, smoothed in log over rows (`python -m bench.calibration.indoor_fill`). The mean is
   arithmetic: the expected radiance of a band, lamps and windows included, which is what a
   diffuse or matte render integrates. Unseen pixels get the pull-push value x gain(row) /
   the mean gain over the seen pixels, so the seen rows set the level and the profile its
   shape. Under CV it is the largest gain of the three (diffuse si-RMSE).
2. Where nothing was seen, the colour is what was seen: unseen pixels keep the pull-push
   luminance with the seen region's mean chromaticity (of the capped radiance of rule 3: the
   walls', not a seen lamp's): the constant map's colour, the floor to beat. A rule that
   moved it towards grey ("light is whiter than the walls", UNSEEN_WHITENING = 0.5, chosen
   on dev) was removed: under leave-one-room-out it gained on the diffuse angle and lost on
   the matte and mirror angles, where it fell below the constant map (docs/engine.md).
3. Compact bright sources do not continue where the camera did not look: pull-push spreads
   every seen pixel's radiance into the holes around it, so a lamp or a window in view would
   become a glowing halo across the unseen sphere, brighter the brighter the source (its
   energy is already in the map where it was seen, and in the field's emitters). The
   extrapolation therefore starts from the seen radiance capped at SOURCE_CAP x the seen
   pixels' median luminance (`cap_sources`); the seen pixels themselves keep their value.
   SOURCE_CAP is chosen among 1, 2, 4, 8 and no cap by the prior's mean diffuse si-RMSE.
4. The light is not the walls' colour: a room's walls are its light times their albedo, and
   what lights a diffuse object is mostly the few bright directions (lamps, windows, lit
   ceilings), whose colour is the light's. So where the fill is brighter than its median it
   moves from the walls' colour (rule 2) towards the light's colour as the frames show it,
   estimated by grey-edge (the mean absolute difference between neighbouring pixels per
   channel: edges between surfaces of different albedo average to the light's colour; van de
   Weijer, Gevers and Gijsenij 2007): in log chromaticity, in proportion to log(L / median),
   all the way at (1 + LIGHT_COLOUR_KNEE) x the median. Dim fill keeps the walls' colour, so
   a mirror ball still shows walls of the right colour. LIGHT_COLOUR_KNEE is chosen like
   SOURCE_CAP, by the prior's mean diffuse angular error (none: the rule off).
Elevation is measured from the world's +y: right for single images and tracked videos (the
first camera is upright by assumption) and the simulator; a capture whose world up is not
+y (some nerfstudio exports) gets the profile tilted. Seen pixels are never changed.
"""
from __future__ import annotations

import math

import torch

from core.conventions import inverse_tonemap
from core.exposure import chromaticity, luminance

HORIZON_BAND_DEG = 25.0
GAIN_ROWS = 24
GAIN_SMOOTHING_ROWS = 2.0  # Gaussian sigma (rows of 7.5 deg) of the fitted log-gain profile
# Fitted by `python -m bench.calibration.indoor_fill` (arithmetic mean) on all 24 indoor panoramas of
# MANIFEST.tsv (dev, test and extra; row 0 = up): what a user gets. Scored only under
# leave-one-room-out, where each room's job gets the profile refitted on the other 23
# (`python -m bench.real_panoramas --cv`, bench/results/cv/).
ELEVATION_GAIN = (
    0.863, 0.892, 0.981, 1.128, 1.323, 1.534, 1.694, 1.736, 1.646, 1.467, 1.255, 1.042,
    0.85, 0.691, 0.572, 0.487, 0.429, 0.388, 0.361, 0.344, 0.335, 0.33, 0.327, 0.327,
)
# Chosen on all 24 indoor panoramas by bench.real_panoramas.CV_REFIT's rule (the prior's mean
# diffuse si-RMSE over the rooms; `refit` -> `all_rooms` in bench/results/cv/shortcut/shipped_refit.json).
SOURCE_CAP = 2.0  # x the seen median luminance: what pull-push may extrapolate
# Chosen the same way, by the prior's mean diffuse angular error (`refit` -> `all_rooms`).
LIGHT_COLOUR_KNEE = 0.5  # the unseen fill is the light's colour from (1 + this) x its median luminance


def elevation_gain(height: int, dtype=torch.float64, profile: tuple[float, ...] | None = None) -> torch.Tensor:
    """`profile` (None: ELEVATION_GAIN; rows from up to down) resampled to `height` rows
    (linear in log-gain over the polar angle)."""
    g = torch.log(torch.tensor(ELEVATION_GAIN if profile is None else profile, dtype=torch.float64))[None, None]
    if height != g.shape[-1]:
        g = torch.nn.functional.interpolate(g, size=height, mode="linear", align_corners=False)
    return g[0, 0].exp().to(dtype)


def grey_edge(frames: torch.Tensor) -> torch.Tensor:
    """The light's colour as LDR frames [T, H, W, 3] show it (rule 4): per frame [T, 3], the
    mean absolute difference between neighbouring pixels of the display-linear image, per
    channel (any scale; zero for a flat frame)."""
    lin = inverse_tonemap(frames.clamp(0, 1).double())
    dx = (lin[:, :, 1:] - lin[:, :, :-1]).abs().flatten(1, 2)
    dy = (lin[:, 1:] - lin[:, :-1]).abs().flatten(1, 2)
    return torch.cat([dx, dy], 1).mean(1)


def fill_unseen(filled: torch.Tensor, env: torch.Tensor, weight: torch.Tensor,
                gain_profile: tuple[float, ...] | None = None, light: torch.Tensor | None = None,
                light_knee: float | None = None) -> torch.Tensor:
    """filled: pull-push result [N, h, w, 3]; env, weight: its inputs (weight > 0 = seen; the
    reprojection prior passes env after cap_sources). Unseen pixels get the elevation gain
    (`gain_profile`, None: ELEVATION_GAIN) and the mean colour of env's seen pixels, moving
    towards `light`'s colour ([N, 3] or [3], any scale: `grey_edge`) where they are brighter
    than their median (rule 4; `light` or `light_knee` None: not); seen ones are kept."""
    n, h = filled.shape[:2]
    seen = weight.to(filled.dtype)  # [N, h, w]
    count = seen.sum((1, 2))
    if not bool((count > 0).any()):
        return filled
    gain = elevation_gain(h, filled.dtype, gain_profile)[None, :, None]  # [1, h, 1]
    seen_gain = (seen * gain).sum((1, 2)) / count.clamp_min(1e-12)  # [N]
    scaled = filled * (gain / seen_gain.clamp_min(1e-12)[:, None, None])[..., None]
    mean = (env * seen[..., None]).sum((1, 2)) / count.clamp_min(1e-12)[:, None]  # [N, 3]
    lum = luminance(scaled).clamp_min(0.0)
    colour = chromaticity(mean)[:, None, None, :].expand_as(scaled)
    if light is not None and light_knee is not None:
        light = light.to(filled.dtype).expand_as(mean)
        unseen = weight <= 0
        median = torch.nanmedian(torch.where(unseen, lum, torch.nan).flatten(1), dim=1).values.nan_to_num(0.0)
        t = torch.log(lum.clamp_min(1e-30) / median.clamp_min(1e-30)[:, None, None]) / math.log1p(light_knee)
        t = t.clamp(0.0, 1.0) * (luminance(light) > 0).to(t.dtype)[:, None, None]  # a flat frame shows no light
        log_walls = colour.clamp_min(1e-6).log()
        log_light = chromaticity(light).clamp_min(1e-6).log()[:, None, None, :]
        colour = chromaticity(torch.lerp(log_walls, log_light, t[..., None]).exp())
    recoloured = lum[..., None] * colour
    ok = (count > 0)[:, None, None, None] & (luminance(mean) > 0)[:, None, None, None]
    out = torch.where(ok, recoloured, filled)
    return torch.where(weight[..., None] > 0, filled, out)


def cap_sources(env: torch.Tensor, seen: torch.Tensor, cap: float | None = SOURCE_CAP) -> torch.Tensor:
    """The seen radiance pull-push extrapolates: env [N, h, w, 3] with each pixel's luminance
    capped at `cap` x the median luminance of its map's seen pixels (`seen` [N, h, w] bool),
    colour kept. A map with no seen pixel, or `cap` None, is returned as it is."""
    if cap is None:
        return env
    lum = luminance(env)
    nan = torch.full_like(lum, float("nan"))
    median = torch.nanmedian(torch.where(seen, lum, nan).flatten(1), dim=1).values  # [N], NaN: nothing seen
    limit = cap * median[:, None, None]
    factor = torch.where(torch.isfinite(limit) & (lum > limit), limit / lum.clamp_min(1e-30), torch.ones_like(lum))
    return env * factor[..., None]
