"""What a subscriber to a live session receives each time a version lands: per probe point,
the lighting as WebXR's `XRLightProbe` / `XRLightEstimate` give it, so a page hands it to its
renderer as it would the browser's estimate (docs/api.md, "Live sessions"; docs/integrations.md).

    sphericalHarmonicsCoefficients  27 floats: 9 RGB coefficients interleaved in ARCore's layout
                                    (core.export.sh_layouts 'arcore'), or the subscription's
                                    `layout` ('threejs': what XREstimatedLight hands to three's
                                    LightProbe); the ambient part (the main light taken out)
    primaryLightDirection           {x, y, z, w: 0}: towards the light, world frame
    primaryLightIntensity           {x, y, z, w: 1}: its RGB intensity (relative units)
    reflectionCubeMap, environmentMap   URLs of the same point's maps (the latest version when fetched)

Positions and directions are in the project's world frame (docs/conventions.md), which the
client's XRReferenceSpace must match through the poses it sent with the frames.
"""
from __future__ import annotations

from urllib.parse import urlencode

from core.export.probe_queries import SH_ENVMAP_HEIGHT
from core.export.sh_layouts import LAYOUTS, pack
from service import queries
from service.context import AppContext
from service.errors import InvalidInput
from service.fieldcache import CachedField

CUBE_SIZE = 64
ENVMAP_HEIGHT = 64


def parse_probes(values: list, limit: int) -> list[tuple[float, float, float]]:
    """Probe points from 'X,Y,Z' strings or [x, y, z] lists (at most `limit`); 422 otherwise."""
    if not isinstance(values, list) or not values:
        raise InvalidInput("name at least one probe point (x=X,Y,Z)", code="invalid_query")
    if len(values) > limit:
        raise InvalidInput(f"at most {limit} probe points per subscription, got {len(values)}", code="too_many_probes")
    points = []
    for v in values:
        if isinstance(v, (list, tuple)) and len(v) == 3 and all(
                isinstance(c, (int, float)) and not isinstance(c, bool) for c in v):
            v = ",".join(repr(float(c)) for c in v)
        if not isinstance(v, str):
            raise InvalidInput(f"a probe point is 'X,Y,Z' or [x, y, z], got {str(v)[:60]!r}", code="invalid_query")
        points.append(queries.parse_x(v))
    return points


def default_time(cf: CachedField) -> float:
    """The newest moment the version knows: its last frame's time."""
    return float((cf.artefact.meta.get("time") or {}).get("t1") or 0.0)


def check_layout(layout) -> str:
    """An SH layout name (core.export.sh_layouts: arcore, threejs, ...); 422 otherwise."""
    if layout not in LAYOUTS:
        raise InvalidInput(f"layout must be one of {', '.join(LAYOUTS)}, got {str(layout)[:40]!r}",
                           code="invalid_query")
    return layout


async def version_event(ctx: AppContext, cf: CachedField, session_id: str, version: int, frames: int,
                        probes: list, t: float | None, layout: str = "arcore") -> dict:
    """The `version` event: one XRLightProbe-like entry per probe point, its SH in `layout`."""
    t = default_time(cf) if t is None else t
    entries = []
    for x in probes:
        answer = await queries.envmap_answer(ctx, cf, x, t, SH_ENVMAP_HEIGHT, "fast",
                                             finish=lambda hdr, _flags: queries.sh_from_envmap(hdr))
        light, _full_sh = answer.value
        query = urlencode({"x": ",".join(repr(float(c)) for c in x), "t": repr(float(t))})
        entries.append({
            "position": {"x": x[0], "y": x[1], "z": x[2], "w": 1.0},
            "sphericalHarmonicsCoefficients": pack(light.ambient_sh, layout),
            "primaryLightDirection": dict(zip("xyzw", [*(float(v) for v in light.direction), 0.0])),
            "primaryLightIntensity": dict(zip("xyzw", [*(float(v) for v in light.intensity_rgb), 1.0])),
            "primaryLightFound": bool(light.found),
            "reflectionCubeMap": f"/lightfield/{session_id}/cubemap?{query}&format=ktx2&size={CUBE_SIZE}"
                                 "&layout=threejs",
            "environmentMap": f"/lightfield/{session_id}/envmap?{query}&format=exr&height={ENVMAP_HEIGHT}",
            "extrapolated": {"x": answer.flags.x, "t": answer.flags.t},
        })
    return {"type": "version", "session": session_id, "version": version, "frames": frames, "t": t,
            "layout": layout, "probes": entries}
