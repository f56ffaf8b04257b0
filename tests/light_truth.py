"""Ground truth for main-light checks on estimated fields: which source dominates the irradiance
at a probe. Simulated scenes: from their emitters (a lamp: radiance x its solid angle; a panel or
window: its radiance x cos / d^2 integrated over its area), independent of any env map."""
from __future__ import annotations

import math

import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722])


def emitter_irradiance(emitter, x, steps: int = 24) -> tuple[float, np.ndarray]:
    """(irradiance luminance a surface at x facing the emitter receives from it, unit direction to it)."""
    from core.sim.spec import Lamp

    x, c = np.asarray(x, float), np.asarray(emitter.center, float)
    radiance = float(LUMA @ np.asarray(emitter.radiance, float))
    if isinstance(emitter, Lamp):
        dist = float(np.linalg.norm(c - x))
        return radiance * 2 * math.pi * (1 - math.sqrt(max(0.0, 1 - (emitter.radius / dist) ** 2))), (c - x) / dist
    axis = "xyz".index(emitter.facing[-1])
    normal = np.zeros(3)
    normal[axis] = -1.0 if emitter.facing[0] == "-" else 1.0
    u, v = [i for i in range(3) if i != axis]
    total, towards = 0.0, np.zeros(3)
    for a in (np.arange(steps) + 0.5) / steps - 0.5:
        for b in (np.arange(steps) + 0.5) / steps - 0.5:
            p = c.copy()
            p[u] += a * emitter.size[0]
            p[v] += b * emitter.size[1]
            r = x - p
            dist = float(np.linalg.norm(r))
            cos_e = float(r @ normal) / dist
            if cos_e > 0:
                w = radiance * cos_e * emitter.size[0] * emitter.size[1] / steps ** 2 / dist ** 2
                total, towards = total + w, towards - w * r / dist
    return total, towards / max(float(np.linalg.norm(towards)), 1e-30)


def dominant_source(scene, x) -> tuple[str, np.ndarray, float]:
    """(name, unit direction from x, its irradiance over the next source's) of the strongest emitter."""
    ranked = sorted(((*emitter_irradiance(e, x), e.name) for e in scene.emitters), key=lambda r: -r[0])
    (e1, d1, name), runner_up = ranked[0], ranked[1][0] if len(ranked) > 1 else 0.0
    return name, d1, e1 / max(runner_up, 1e-30)


def angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return math.degrees(math.acos(float(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))
