"""Mitsuba 3 renders of the benchmark's rooms (bench.pbr.scenes), cached.

`scalar_rgb` variant (the `llvm_ad_*` variants crash with this machine's LLVM), path tracing with
MIS, a box pixel filter and a seeded multi-jitter sampler. Mitsuba is imported here, lazily
(`mitsuba()`): it is an optional dependency of the benches and tests, never of the service.

Conventions (checked by tests/test_pbr_sessions.py): Mitsuba's `look_at` with up = the camera's
+y puts world +x on the image's right for a camera looking along -z, which is the product's
camera (core/conventions.py), so a pose c2w renders with look_at(origin, origin - c2w[:3, 2],
c2w[:3, 1]); depth comes from a second pass with the `depth` integrator (4 spp; the `depth` AOV
of the `aov` integrator, the same distance, doubled a frame's cost), the distance along each ray,
turned into planar depth by the cosine to the optical axis. Cube faces are rendered by 90 deg
cameras looking along each axis and mirrored left-right into OpenGL's face table (core/cubemap.py:
the table is left-handed). Isolated fireflies (paths a few samples found) are removed from frames
and faces as they are read (`despeckle`), not in the cache.

Every render is cached under CACHE_DIR/<key[:2]>/<key>.npy, key = sha256 of the scene's geometry
and materials (`geometry_key`), the lights' scales at the render's time, the sensor, the samples
per pixel, the integrator and RENDER_VERSION; reruns cost nothing, and the seed is the key's.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path

import numpy as np

RENDER_VERSION = "pbr-1"
MAX_DEPTH = 6  # path length (5 bounces): enough for a room's interreflections
DEPTH_SPP = 4
DEFAULT_CACHE_DIR = Path(__file__).resolve().parents[1] / ".cache" / "pbr"


def mitsuba():
    """The mitsuba module in its scalar_rgb variant (imported on first use)."""
    import mitsuba as mi  # optional dependency (the dev extra), benches only

    if mi.variant() != "scalar_rgb":
        mi.set_variant("scalar_rgb")
    return mi


# ---------------------------------------------------------------------------------------
# Cache
# ---------------------------------------------------------------------------------------
def stable_hash(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


class RenderCache:
    """Arrays by key, one .npy per render (written to a temporary name, then renamed)."""

    def __init__(self, root: str | os.PathLike | None = None):
        self.root = Path(root) if root is not None else DEFAULT_CACHE_DIR
        self.hits = 0
        self.misses = 0

    def path(self, key: str) -> Path:
        return self.root / key[:2] / f"{key}.npy"

    def get(self, key: str) -> np.ndarray | None:
        p = self.path(key)
        if p.exists():
            try:
                out = np.load(p)
                self.hits += 1
                return out
            except (OSError, ValueError):
                p.unlink(missing_ok=True)
        return None

    def put(self, key: str, value: np.ndarray) -> None:
        p = self.path(key)
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as f:
            np.save(f, np.ascontiguousarray(value, np.float32))
        os.replace(tmp, p)

    def cached(self, key: str, compute):
        v = self.get(key)
        if v is None:
            self.misses += 1
            v = np.asarray(compute(), np.float32)
            self.put(key, v)
        return v


# ---------------------------------------------------------------------------------------
# Textures and geometry
# ---------------------------------------------------------------------------------------
def texture(spec: dict) -> np.ndarray:
    """A procedural reflectance texture [res, res, 3] float32 (linear), from its spec: checker,
    planks (boards along v with per-board tone and grain), stripes (along u) or noise (blocky
    value noise between two colours), `n` = tiles along (u, v), seeded."""
    res = int(spec.get("res", 128))
    nu, nv = spec.get("n", [8, 8])
    c0, c1 = np.asarray(spec["c0"], np.float32), np.asarray(spec["c1"], np.float32)
    rng = np.random.default_rng(int(spec.get("seed", 0)))
    u = (np.arange(res) + 0.5) / res
    uu, vv = np.meshgrid(u, u, indexing="xy")
    kind = spec["texture"]
    if kind == "checker":
        w = ((np.floor(uu * nu) + np.floor(vv * nv)) % 2).astype(np.float32)
    elif kind == "stripes":
        w = (np.floor(uu * nu) % 2).astype(np.float32)
        w = 0.15 + 0.7 * w
    elif kind == "planks":
        board = np.floor(vv * nv).astype(int)
        tone = rng.random(int(nv) + 1)[board]
        grain = 0.5 + 0.5 * np.sin(2 * np.pi * (uu * 3 + tone * 7) + 6 * np.sin(2 * np.pi * vv * nv))
        w = 0.6 * tone + 0.4 * grain
        w[(vv * nv) % 1.0 < 0.04] = 0.0  # the gaps
    elif kind == "noise":
        cells = rng.random((int(nv) + 1, int(nu) + 1))
        w = cells[np.floor(vv * nv).astype(int), np.floor(uu * nu).astype(int)]
        w = 0.7 * w + 0.3 * rng.random((res, res))
    else:
        raise ValueError(f"unknown texture {kind!r}")
    return (c0 + (c1 - c0) * w[..., None]).astype(np.float32)


def quad_basis(normal) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, n) of a rectangle facing `normal`: v = +y for vertical ones (u x v = n)."""
    n = np.asarray(normal, float)
    n /= np.linalg.norm(n)
    if abs(n[1]) < 0.9:
        u = np.cross([0.0, 1.0, 0.0], n)
        u /= np.linalg.norm(u)
    else:
        u = np.array([1.0, 0.0, 0.0])
    return u, np.cross(n, u), n


def _matrix(columns, centre) -> list[list[float]]:
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = columns
    m[:3, 3] = centre
    return m.tolist()


def _bsdf(mat: dict, mi) -> dict:
    def reflectance():
        if "texture" in mat:
            return {"type": "bitmap", "bitmap": mi.Bitmap(texture(mat)), "raw": True, "filter_type": "bilinear"}
        return {"type": "rgb", "value": mat["rgb"]}

    kind = mat["type"]
    if kind == "diffuse":
        return {"type": "diffuse", "reflectance": reflectance()}
    if kind == "twosided":
        return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": reflectance()}}
    if kind == "shade":  # a lampshade: its colour outside, dark-lined inside (its back faces, facing the bulb)
        return {"type": "twosided", "bsdf_outside": {"type": "diffuse", "reflectance": reflectance()},
                "bsdf_inside": {"type": "diffuse", "reflectance": {"type": "rgb", "value": mat["inside"]}}}
    if kind == "plastic":
        if mat.get("alpha", 0.0) <= 0.0:
            return {"type": "plastic", "diffuse_reflectance": reflectance()}
        return {"type": "roughplastic", "distribution": "ggx", "alpha": mat["alpha"],
                "diffuse_reflectance": reflectance()}
    if kind == "conductor":
        if mat.get("alpha", 0.0) <= 0.0:
            return {"type": "conductor", "material": mat["material"]}
        return {"type": "roughconductor", "material": mat["material"], "alpha": mat["alpha"], "distribution": "ggx"}
    raise ValueError(f"unknown material type {kind!r}")


def _rectangle(centre, normal, width, height, bsdf, mi, emitter=None) -> dict:
    u, v, n = quad_basis(normal)
    shape = {"type": "rectangle", "to_world": mi.ScalarTransform4f(_matrix((u * width / 2, v * height / 2, n), centre)),
             "bsdf": bsdf}
    if emitter is not None:
        shape["emitter"] = emitter
    return shape


def _cylinder(p0, p1, radius, bsdf, caps, mi) -> list[dict]:
    out = [{"type": "cylinder", "p0": list(p0), "p1": list(p1), "radius": radius, "bsdf": bsdf}]
    if caps:
        axis = np.asarray(p1, float) - np.asarray(p0, float)
        axis /= np.linalg.norm(axis)
        for p, n in ((p0, -axis), (p1, axis)):
            u, v, nn = quad_basis(n)
            out.append({"type": "disk", "to_world": mi.ScalarTransform4f(_matrix((u * radius, v * radius, nn), p)),
                        "bsdf": bsdf})
    return out


def _object(obj: dict, bsdfs: dict, mi) -> list[dict]:
    bsdf = bsdfs[obj["mat"]]
    kind = obj["type"]
    if kind == "box":
        yaw = math.radians(obj.get("yaw", 0.0))
        rot = np.array([[math.cos(yaw), 0, math.sin(yaw)], [0, 1, 0], [-math.sin(yaw), 0, math.cos(yaw)]])
        half = np.asarray(obj["size"], float) / 2
        return [{"type": "cube", "to_world": mi.ScalarTransform4f(_matrix(tuple((rot * half).T), obj["centre"])),
                 "bsdf": bsdf}]
    if kind == "sphere":
        return [{"type": "sphere", "center": obj["centre"], "radius": obj["radius"], "bsdf": bsdf}]
    if kind == "cylinder":
        return _cylinder(obj["p0"], obj["p1"], obj["radius"], bsdf, obj.get("caps", False), mi)
    if kind == "quad":
        return [_rectangle(obj["centre"], obj["normal"], obj["width"], obj["height"], bsdf, mi)]
    raise ValueError(f"unknown object type {kind!r}")


def _emitter(radiance, scale: float) -> dict | None:
    if scale <= 0.0:
        return None
    return {"type": "area", "radiance": {"type": "rgb", "value": [float(c) * scale for c in radiance]}}


def _light_shapes(light: dict, scale: float, bsdfs: dict, mi) -> list[dict]:
    emitter = _emitter(light["radiance"], scale)
    kind = light["kind"]
    if kind == "bulb":
        c, r = np.asarray(light["centre"], float), float(light["radius"])
        bulb = {"type": "sphere", "center": c.tolist(), "radius": r, "bsdf": bsdfs["bulb"]}
        if emitter is not None:
            bulb["emitter"] = emitter
        out = [bulb]
        top = c[1] + r
        shade = light.get("shade")
        if shade:
            sb = bsdfs[shade["mat"]]
            if shade["kind"] == "drum":
                y0, y1 = c[1] - shade["height"] / 2, c[1] + shade["height"] / 2
                out += _cylinder([c[0], y0, c[2]], [c[0], y1, c[2]], shade["radius"], sb, False, mi)
            else:  # cap: open below the bulb's centre, closed on top
                y0, y1 = c[1], c[1] + shade["height"]
                out += _cylinder([c[0], y0, c[2]], [c[0], y1, c[2]], shade["radius"], sb, False, mi)
                u, v, n = quad_basis([0, 1, 0])
                out.append({"type": "disk", "bsdf": sb, "to_world": mi.ScalarTransform4f(
                    _matrix((u * shade["radius"], v * shade["radius"], n), [c[0], y1, c[2]]))})
            top = y1
        pole = light.get("pole")
        if pole:
            to = np.asarray(pole["to"], float)
            start = np.array([c[0], top if to[1] > c[1] else c[1] - r, c[2]])
            out += _cylinder(to.tolist(), start.tolist(), 0.012, bsdfs[pole["mat"]], False, mi)
            if to[1] < c[1] and to[1] < 0.05:  # a floor lamp's base
                out += _cylinder([to[0], 0.0, to[2]], [to[0], 0.02, to[2]], 0.14, bsdfs[pole["mat"]], True, mi)
        return out
    quads = light["quads"] if kind == "quads" else [light]
    frame = bsdfs[light.get("frame_mat", "panel")]
    return [_rectangle(q["centre"], q["normal"], q["width"], q["height"], frame, mi, emitter) for q in quads]


def used_materials(scene: dict) -> set[str]:
    room = scene["room"]
    used = {room["floor"], room["ceiling"], *room["walls"], *(o["mat"] for o in scene["objects"])}
    for light in scene["lights"].values():
        if light["kind"] == "bulb":
            used.add("bulb")
            used.update(x["mat"] for x in (light.get("shade"), light.get("pole")) if x)
        else:
            used.add(light.get("frame_mat", "panel"))
    return used


def geometry_key(scene: dict) -> dict:
    """What a render depends on besides the lights' scales and the sensor: room, the materials it
    uses, objects and the lights without their schedules."""
    lights = {k: {kk: vv for kk, vv in v.items() if kk != "schedule"} for k, v in scene["lights"].items()}
    materials = {k: v for k, v in scene["materials"].items() if k in used_materials(scene)}
    return {"room": scene["room"], "materials": materials, "objects": scene["objects"], "lights": lights}


def scene_dict(scene: dict, scales: dict[str, float], integrator: str = "path") -> dict:
    """The Mitsuba scene dict of a room with each light at `scales[name]` x its radiance, with the
    path tracer ("path") or the depth integrator ("depth": distance along each ray)."""
    mi = mitsuba()
    bsdfs = {name: _bsdf(m, mi) for name, m in scene["materials"].items()}
    w, h, d = scene["room"]["size"]
    room = scene["room"]
    out: dict = {"type": "scene", "integrator": {"type": "path", "max_depth": MAX_DEPTH} if integrator == "path"
                 else {"type": "depth"}}
    walls = [((-w / 2, h / 2, 0.0), (1, 0, 0), d, h), ((w / 2, h / 2, 0.0), (-1, 0, 0), d, h),
             ((0.0, h / 2, -d / 2), (0, 0, 1), w, h), ((0.0, h / 2, d / 2), (0, 0, -1), w, h)]
    for k, ((c, n, a, b), mat) in enumerate(zip(walls, room["walls"])):
        out[f"wall{k}"] = _rectangle(c, n, a, b, bsdfs[mat], mi)
    out["floor"] = _rectangle((0.0, 0.0, 0.0), (0, 1, 0), w, d, bsdfs[room["floor"]], mi)
    out["ceiling"] = _rectangle((0.0, h, 0.0), (0, -1, 0), w, d, bsdfs[room["ceiling"]], mi)
    for i, obj in enumerate(scene["objects"]):
        for j, shape in enumerate(_object(obj, bsdfs, mi)):
            out[f"obj{i}_{j}"] = shape
    for name, light in scene["lights"].items():
        for j, shape in enumerate(_light_shapes(light, float(scales.get(name, 0.0)), bsdfs, mi)):
            out[f"light_{name}_{j}"] = shape
    return out


# ---------------------------------------------------------------------------------------
# Sensors and renders
# ---------------------------------------------------------------------------------------
def _sensor(origin, forward, up, fov_deg: float, width: int, height: int, spp: int, seed: int):
    mi = mitsuba()
    o = np.asarray(origin, float)
    return mi.load_dict({
        "type": "perspective", "fov": float(fov_deg), "fov_axis": "x",
        "to_world": mi.ScalarTransform4f().look_at(origin=o.tolist(), target=(o + np.asarray(forward)).tolist(),
                                                   up=list(up)),
        "sampler": {"type": "multijitter", "sample_count": int(spp), "seed": int(seed)},
        "film": {"type": "hdrfilm", "width": int(width), "height": int(height), "rfilter": {"type": "box"},
                 "pixel_format": "rgb"},
    })


class SceneCache:
    """Loaded Mitsuba scenes by (geometry, scales, aov): loading costs ~0.1-0.5 s."""

    def __init__(self):
        self._scenes: dict[str, object] = {}

    def get(self, scene: dict, scales: dict, integrator: str):
        key = stable_hash([geometry_key(scene), scales, integrator])
        if key not in self._scenes:
            if len(self._scenes) > 8:
                self._scenes.clear()
            self._scenes[key] = mitsuba().load_dict(scene_dict(scene, scales, integrator))
        return self._scenes[key]


_SCENES = SceneCache()


def _version() -> str:
    return mitsuba().__version__


def frame_key(scene: dict, scales: dict, c2w: np.ndarray, spp: int) -> str:
    cam = scene["camera"]
    return stable_hash({"v": RENDER_VERSION, "mitsuba": _version(), "kind": "frame", "geometry": geometry_key(scene),
                        "scales": scales, "c2w": np.round(np.asarray(c2w), 9).tolist(), "hfov": cam["hfov_deg"],
                        "size": cam["size"], "spp": spp, "max_depth": MAX_DEPTH, "depth_spp": DEPTH_SPP})


def planar_depth_factor(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """[H, W] cosine between each pixel's ray and the optical axis (distance x it = planar depth)."""
    u = (np.arange(width) + 0.5 - cx) / fx
    v = (np.arange(height) + 0.5 - cy) / fy
    uu, vv = np.meshgrid(u, v, indexing="xy")
    return 1.0 / np.sqrt(1.0 + uu * uu + vv * vv)


def render_frame(scene: dict, scales: dict, c2w: np.ndarray, spp: int, cache: RenderCache) -> np.ndarray:
    """[H, W, 4]: linear RGB radiance and planar depth (metres) of one frame (cached)."""
    from bench.pbr.scenes import intrinsics

    key = frame_key(scene, scales, c2w, spp)

    def compute():
        mi = mitsuba()
        k = intrinsics(scene)
        c2w_ = np.asarray(c2w, float)
        sensor = _sensor(c2w_[:3, 3], -c2w_[:3, 2], c2w_[:3, 1], scene["camera"]["hfov_deg"], k["width"],
                         k["height"], spp, int(key[:8], 16) % (2**31))
        rgb = np.array(mi.render(_SCENES.get(scene, scales, "path"), sensor=sensor), dtype=np.float32)[..., :3]
        # distance along each ray: a separate pass of the depth integrator (4 samples per pixel,
        # averaged over the pixel as a depth sensor does); the AOV integrator doubled the frame's cost
        sensor = _sensor(c2w_[:3, 3], -c2w_[:3, 2], c2w_[:3, 1], scene["camera"]["hfov_deg"], k["width"],
                         k["height"], DEPTH_SPP, int(key[8:16], 16) % (2**31))
        dist = np.array(mi.render(_SCENES.get(scene, scales, "depth"), sensor=sensor), dtype=np.float32)[..., 0]
        depth = dist * planar_depth_factor(k["width"], k["height"], k["fx"], k["fy"], k["cx"], k["cy"])
        depth[~(depth > 0)] = np.nan
        return np.concatenate([rgb, depth[..., None]], axis=-1)

    out = cache.cached(key, compute).copy()
    out[..., :3] = despeckle(out[..., :3])
    return out


def despeckle(img: np.ndarray, over_max: float = 1.5, over_median: float = 2.5) -> np.ndarray:
    """Remove path tracing's fireflies (caustic paths a few samples found): a pixel whose luminance
    is over `over_max` x the brightest of its 8 neighbours and `over_median` x their median gets
    their median. A lamp spans several pixels, so its pixels have bright neighbours and stay; a
    camera has no such outliers."""
    y = 0.2126 * img[..., 0] + 0.7152 * img[..., 1] + 0.0722 * img[..., 2]
    h, w = y.shape
    py = np.pad(y, 1, mode="edge")
    pimg = np.pad(img, ((1, 1), (1, 1), (0, 0)), mode="edge")
    shifts = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)]
    ny = np.stack([py[1 + dr:1 + dr + h, 1 + dc:1 + dc + w] for dr, dc in shifts])
    spikes = (y > over_max * ny.max(0) + 1e-6) & (y > over_median * np.median(ny, axis=0) + 1e-6)
    if not spikes.any():
        return img
    neighbours = np.stack([pimg[1 + dr:1 + dr + h, 1 + dc:1 + dc + w] for dr, dc in shifts])
    out = img.copy()
    out[spikes] = np.median(neighbours, axis=0)[spikes]
    return out


# GL face table (core/cubemap.py): the axis each face looks along and its image's down direction
FACE_AXES = (((1, 0, 0), (0, -1, 0)), ((-1, 0, 0), (0, -1, 0)), ((0, 1, 0), (0, 0, 1)), ((0, -1, 0), (0, 0, -1)),
             ((0, 0, 1), (0, -1, 0)), ((0, 0, -1), (0, -1, 0)))


def render_cube(scene: dict, scales: dict, probe, face_size: int, spp: int, cache: RenderCache) -> np.ndarray:
    """[6, S, S, 3] linear radiance arriving at `probe`, faces in core.cubemap's GL order (cached)."""
    key = stable_hash({"v": RENDER_VERSION, "mitsuba": _version(), "kind": "cube", "geometry": geometry_key(scene),
                       "scales": scales, "probe": [round(float(v), 6) for v in probe], "size": face_size, "spp": spp,
                       "max_depth": MAX_DEPTH})

    def compute():
        mi = mitsuba()
        ms = _SCENES.get(scene, scales, "path")
        faces = []
        for f, (axis, down) in enumerate(FACE_AXES):
            sensor = _sensor(probe, axis, [-c for c in down], 90.0, face_size, face_size, spp,
                             (int(key[:8], 16) + f) % (2**31))
            img = np.array(mi.render(ms, sensor=sensor), dtype=np.float32)[..., :3]
            faces.append(img[:, ::-1])  # a camera's view, mirrored into the GL table
        return np.stack(faces)

    return np.stack([despeckle(f) for f in cache.cached(key, compute)])


def line_of_sight(scene: dict, probe, light: dict, target=None) -> bool:
    """True when the ray from `probe` to the light (its centre, or `target`) meets nothing before
    the light's own surface (a bulb's sphere, a quad's plane)."""
    mi = mitsuba()
    ms = _SCENES.get(scene, {name: 1.0 for name in scene["lights"]}, "depth")
    o = np.asarray(probe, float)
    centre = np.asarray(target if target is not None else light["centre"], float)
    d = centre - o
    dist = float(np.linalg.norm(d))
    d /= dist
    si = ms.ray_intersect(mi.Ray3f(mi.ScalarPoint3f(o.tolist()), mi.ScalarVector3f(d.tolist())))
    if not si.is_valid():
        return True
    surface = dist - (float(light["radius"]) if light["kind"] == "bulb" else 0.0)
    return float(si.t) >= surface - 2e-3
