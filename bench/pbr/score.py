"""Scores of a session: the product's env maps at the probes and times against the truth.

* three spheres (bench.suite.evaluation.score_probe): si-RMSE, angular error, as ratios to the
  constant map of the capture's mean linearised colour (as bench.room_scans and
  bench.real_panoramas define it);
* lamp direction (`lamp_seen`): a map shows a lamp at direction u when some of its brightest
  pixels (those making up LAMP_TOP_FRACTION of the sphere's solid angle) lie within LAMP_CONE_DEG
  of u. Scored for every bulb at every probe that sees it (line of sight), at every scored time:
  while it is on (scale >= 0.5) the estimate should show it, while it is off (scale 0) it should
  not; a probe-time counts only where the truth itself passes the same test (shows the lamp
  while on, does not while off);
* switch ratio: the fluence (luminance of the map's integral) after / before each event (for a
  fade, its end / before), estimate against truth, as |log2 ratio error| in stops, the share of
  the truth's log change the estimate reproduces, and across the probes of one event the spread
  (std of the log ratios, estimate / truth: 1 = the change is where it is, 0 = the same change
  everywhere in the room);
* main light: the /sh route's dominant light (service.queries.sh_from_envmap of the map it
  evaluates: 128 rows at quality fast) against the direction to the source that gives >=
  MAIN_SHARE of the probe's fluence, where the probe sees that source;
* SH irradiance error: band-2 SH of each map (core.sh.project_sh), irradiance over FIB_NORMALS
  normals, estimate x one scale per session (the estimate's units are the capture's) against the
  truth: RMS error / RMS truth;
* drift: relative L1 between the estimate's maps at the two ends of the session's longest static
  stretch (the truth's is 0).
"""
from __future__ import annotations

import math

import numpy as np
import torch

LAMP_CONE_DEG = 15.0
LAMP_TOP_FRACTION = 0.005
ON_SCALE = 0.5
MAIN_SHARE = 0.3
FIB_NORMALS = 64


def constant_map(ldr: np.ndarray, height: int) -> torch.Tensor:
    """A constant map of the capture's mean colour: the decoded frames' codes linearised with the
    curve the session's camera encoded them with (bench.pbr.camera.sensor: sRGB; the engine's
    x^2.4 would bias the baseline), as the other benches' `mean-colour`."""
    from core.conventions import equirect_width
    from core.sim.camera_curves import CURVES

    mean = CURVES["srgb"].decode(torch.from_numpy(np.asarray(ldr, np.float32))).reshape(-1, 3).mean(0)
    return mean.expand(height, equirect_width(height), 3).clone()


def _lum(env: torch.Tensor) -> torch.Tensor:
    from core.exposure import luminance

    return luminance(env.double())


def lamp_seen(env: torch.Tensor, direction) -> bool:
    """Does the map show a source within LAMP_CONE_DEG of `direction` among its brightest pixels
    (those making up LAMP_TOP_FRACTION of the sphere)?"""
    from core.conventions import equirect_directions
    from core.envmap import solid_angles

    h = env.shape[0]
    y = _lum(env).reshape(-1)
    w = solid_angles(h, dtype=torch.float64).reshape(-1)
    order = torch.argsort(y, descending=True)
    cum = torch.cumsum(w[order], 0) / w.sum()
    top = order[: int(torch.searchsorted(cum, torch.tensor(LAMP_TOP_FRACTION, dtype=torch.float64))) + 1]
    d = equirect_directions(h, dtype=torch.float64).reshape(-1, 3)[top]
    u = torch.as_tensor(np.asarray(direction, float), dtype=torch.float64)
    return bool((d @ u >= math.cos(math.radians(LAMP_CONE_DEG))).any())


def fluence(env: torch.Tensor) -> float:
    from bench.pbr.truth import fluence as f

    return f(env)


def fib_normals(n: int = FIB_NORMALS) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    y = 1.0 - 2.0 * i / n
    r = torch.sqrt((1.0 - y * y).clamp_min(0.0))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack((r * torch.cos(phi), y, r * torch.sin(phi)), -1)


def sh_irradiance_luminance(env: torch.Tensor) -> torch.Tensor:
    """[FIB_NORMALS] luminance of the band-2 SH irradiance of a map."""
    from core.sh import project_sh, sh_irradiance

    e = sh_irradiance(project_sh(env.double()), fib_normals())
    return _lum(e)


def sh_errors(est: list[torch.Tensor], truth: list[torch.Tensor]) -> tuple[list[float], float]:
    """Per probe-time relative RMS error of the SH irradiance after one scale for the whole session
    (least squares), and that scale in stops (log2: what the estimate must be multiplied by)."""
    e = torch.stack([sh_irradiance_luminance(m) for m in est])
    g = torch.stack([sh_irradiance_luminance(m) for m in truth])
    scale = float((e * g).sum() / (e * e).sum().clamp_min(1e-30))
    errs = ((scale * e - g).pow(2).mean(-1).sqrt() / g.pow(2).mean(-1).sqrt().clamp_min(1e-30)).tolist()
    return errs, math.log2(max(scale, 1e-30))


def angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def relative_l1(a: torch.Tensor, b: torch.Tensor) -> float:
    from bench.room_scans import relative_l1 as rl1

    return rl1(a, b)


def main_light(env128: torch.Tensor) -> dict:
    """What GET /lightfield/<id>/sh answers for this map: its dominant light (direction, found,
    confidence)."""
    from service.queries import sh_from_envmap

    light, _ = sh_from_envmap(np.ascontiguousarray(env128.detach().cpu().numpy(), np.float32))
    return {"direction": [float(v) for v in light.direction], "found": bool(light.found),
            "confidence": float(light.confidence)}
