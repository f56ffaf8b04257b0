"""Ground truth at the probes: env maps per light source, rendered once, summed at any time.

Light transport is linear in the sources' strengths (geometry and materials do not change), so
the env map at probe x and time t is sum_k s_k(t) M_k(x), M_k the map with source k alone at its
full radiance (direct and indirect), s_k its schedule. Each M_k is a cube of six 90 deg Mitsuba
renders at the probe (bench.pbr.render.render_cube, no geometry at the probe point; a bulb's at
BULB_SPP_FACTOR x the samples), converted to the product's equirect layout by
core.cubemap.cubemap_to_equirect. The same maps give each source's share of a probe's irradiance
(the /sh main light is scored where one source gives >= MAIN_SHARE of it).
"""
from __future__ import annotations

import numpy as np
import torch

FACE_SIZE = 32
CUBE_SPP = 144
BULB_SPP_FACTOR = 4  # a small bright bulb lights nearby surfaces hard: its indirect light needs more samples
GT_HEIGHT = 64


def source_maps(scene: dict, probe, cache, face_size: int = FACE_SIZE, spp: int = CUBE_SPP,
                height: int = GT_HEIGHT) -> dict[str, torch.Tensor]:
    """{light name: [height, 2 height, 3] float32 equirect map with that light alone at scale 1}."""
    from bench.pbr.render import render_cube
    from core.cubemap import cubemap_to_equirect

    out = {}
    for name, light in scene["lights"].items():
        n = spp * (BULB_SPP_FACTOR if light["kind"] == "bulb" else 1)
        faces = render_cube(scene, {name: 1.0}, probe, face_size, n, cache)
        out[name] = cubemap_to_equirect(torch.from_numpy(np.ascontiguousarray(faces)), height).float()
    return out


def truth_map(maps: dict[str, torch.Tensor], scales: dict[str, float]) -> torch.Tensor:
    return sum(maps[name] * float(scales.get(name, 0.0)) for name in maps)


def fluence(env: torch.Tensor) -> float:
    """Luminance of the map's integral over the sphere (irradiance-like, bench.suite.evaluation)."""
    from bench.suite.evaluation import envmap_brightness

    return float(envmap_brightness(env[None])[0])


def shares(maps: dict[str, torch.Tensor], scales: dict[str, float]) -> dict[str, float]:
    """Each source's share of the probe's fluence at these scales."""
    parts = {name: fluence(maps[name]) * float(scales.get(name, 0.0)) for name in maps}
    total = sum(parts.values())
    return {name: (v / total if total > 0 else 0.0) for name, v in parts.items()}


def source_target(light: dict, probe) -> np.ndarray:
    """The point a source is seen at from the probe: a bulb's or a quad's centre; for a group of
    quads, the centre of the one subtending the largest solid angle (area x cosine / distance^2,
    only quads facing the probe)."""
    if light["kind"] in ("bulb", "quad"):
        return np.asarray(light["centre"], float)
    p = np.asarray(probe, float)
    best, best_w = None, -1.0
    for q in light["quads"]:
        c = np.asarray(q["centre"], float)
        d = p - c
        dist = float(np.linalg.norm(d))
        cos = float(np.dot(d / dist, np.asarray(q["normal"], float) / np.linalg.norm(q["normal"])))
        w = q["width"] * q["height"] * max(cos, 0.0) / dist**2
        if w > best_w:
            best, best_w = c, w
    return best


def unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def probe_truth(scene: dict, probe, cache, **kw) -> dict:
    """Per probe: the sources' maps, and per source the direction to it (unit, world, the
    direction light arrives from) and whether the probe sees it (line of sight)."""
    from bench.pbr.render import line_of_sight

    maps = source_maps(scene, probe, cache, **kw)
    info = {}
    for name, light in scene["lights"].items():
        target = source_target(light, probe)
        info[name] = {"direction": unit(target - np.asarray(probe, float)),
                      "line_of_sight": bool(line_of_sight(scene, probe, light, target)),
                      "kind": light["kind"]}
    return {"maps": maps, "sources": info}
