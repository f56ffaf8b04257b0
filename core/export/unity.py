"""Unity hand-off: left-handed, +y up, camera +z. (x, y, z)_ours = (x, y, -z)_unity.

`SphericalHarmonicsL2` (indexed [channel, k], the same band order as ours: 1, y, z, x, xy, yz,
3z^2-1, xz, x^2-y^2) does not store raw coefficients: Unity keeps E_k C_k / pi, the irradiance
coefficient times the basis constant over pi, so that its shader (UnityCG.cginc `ShadeSH9`:
unity_SHA* = (k3, k1, k2, k0 - k6), unity_SHB* = (k4, k5, 3 k6, k7), unity_SHC = k8) returns
E(n) / pi, the outgoing radiance of a white Lambertian surface, directly. `AddAmbientLight(c)`
adds c to k0, consistent with this. The coefficients are of the map mirrored in z (Unity axes).
Unity is not installable here: `unity_shade_sh9` re-implements the shader formula and the test
checks it against our irradiance.
"""
from __future__ import annotations

import numpy as np

UNITY_FROM_OURS = np.diag([1.0, 1.0, -1.0])


def to_unity(v) -> np.ndarray:
    """Directions or positions [..., 3], ours -> Unity's."""
    return np.asarray(v, np.float64) @ UNITY_FROM_OURS


def unity_sh(env) -> list[list[float]]:
    """SphericalHarmonicsL2 values [3 channels][9] for an env map of ours [H, 2H, 3]."""
    import torch  # noqa: PLC0415 — torch is heavy: imported when used

    from core.sh import project_sh  # noqa: PLC0415 — core.sh pulls in torch: imported when used

    return unity_sh_from_coefficients(project_sh(torch.as_tensor(np.asarray(env, np.float64))))


def unity_sh_from_coefficients(radiance_sh) -> list[list[float]]:
    """Our radiance SH [9, 3] -> SphericalHarmonicsL2 values [3][9] (core.export.sh_layouts 'unity':
    the z mirror's signs and Unity's A_l C_k / pi scale)."""
    from core.export.sh_layouts import to_layout  # noqa: PLC0415 — core.export.sh_layouts pulls in torch: imported when used

    return to_layout(radiance_sh, "unity").T.tolist()


def unity_shade_sh9(sh: list[list[float]], normal_unity: np.ndarray) -> np.ndarray:
    """UnityCG.cginc's ShadeSH9 (SHEvalLinearL0L1 + L2) with unity_SH* built from `sh` -> [..., 3]."""
    k = np.asarray(sh, np.float64)  # [3, 9]
    n = np.asarray(normal_unity, np.float64)
    x, y, z = n[..., 0:1], n[..., 1:2], n[..., 2:3]
    sha = np.stack((k[:, 3], k[:, 1], k[:, 2], k[:, 0] - k[:, 6]), axis=-1)  # [3, 4]
    shb = np.stack((k[:, 4], k[:, 5], 3 * k[:, 6], k[:, 7]), axis=-1)
    shc = k[:, 8]
    n4 = np.concatenate((x, y, z, np.ones_like(x)), axis=-1)
    vb = np.concatenate((x * y, y * z, z * z, z * x), axis=-1)
    return n4 @ sha.T + vb @ shb.T + (x * x - y * y) * shc


def unity_probe_grid(evaluate, bounds, counts, t, artefact: str = "", lo=None, hi=None, grade=None):
    """The Unity probe grid product (core.export.schema.UnityProbeGrid), shared by the CLI and the API.

    `evaluate(x)` -> (env map [H, 2H, 3] of ours, {'x': bool, 't': bool} the field's own flags).
    Without lo/hi the probes sit at the cell centres of the region the captures cover
    (core.export.coverage); every probe outside that region (or the time range) is flagged. `grade`:
    the job's core.export.schema.AnswerGrade."""
    from core.export.coverage import cell_centre_grid, covered_region, inside  # noqa: PLC0415 — core.export.coverage pulls in pydantic, torch: imported when used
    from core.export.schema import Flags, Region, UnityProbe, UnityProbeGrid  # noqa: PLC0415 — core.export.schema pulls in pydantic, torch: imported when used

    c_lo, c_hi, source = covered_region(bounds)
    if lo is None and hi is None:
        positions = cell_centre_grid(c_lo, c_hi, counts)
    else:
        positions = probe_grid(c_lo if lo is None else lo, c_hi if hi is None else hi, counts)
    covered = inside(c_lo, c_hi, positions)
    probes = []
    for x, ok in zip(positions, covered):
        env, flags = evaluate(tuple(float(v) for v in x))
        probes.append(
            UnityProbe(
                position=tuple(float(v) for v in x),
                position_unity=tuple(float(v) for v in to_unity(x)),
                sh=unity_sh(np.asarray(env, np.float64)),
                extrapolated=Flags(x=bool(flags["x"] or not ok), t=bool(flags["t"])),
            )
        )
    return UnityProbeGrid(t=t, grid=tuple(int(n) for n in counts),
                          covered=Region(lo=tuple(c_lo.tolist()), hi=tuple(c_hi.tolist()), source=source),
                          extrapolated_probes=sum(p.extrapolated.x or p.extrapolated.t for p in probes),
                          probes=probes, artefact=artefact, grade=grade)


def probe_grid(lo, hi, counts) -> np.ndarray:
    """Probe positions (ours) on a regular grid inside [lo, hi], `counts` per axis -> [N, 3]."""
    axes = [np.linspace(a, b, int(n)) if int(n) > 1 else np.array([(a + b) / 2]) for a, b, n in zip(lo, hi, counts)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
