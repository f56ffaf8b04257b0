"""The physically based AR-session bench end to end on a tiny room (bench/pbr, bench/pbr_sessions).

Mitsuba renders 8 frames of 64x48 at 16 spp and 16-px ground-truth cubes; the session is captured as
an AR app sends it (auto-exposure, noise, sRGB, 8 bits, H.264, poses, depth, frame_ev) and the
product's draft job runs on it. Skipped when mitsuba (the dev extra) is missing.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

mi = pytest.importorskip("mitsuba")

FRAME_SPP, FACE, CUBE_SPP = 16, 16, 16


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from bench.pbr.render import RenderCache
    from bench.pbr.scenes import get_scene

    return get_scene("tiny"), RenderCache(tmp_path_factory.mktemp("pbr-cache"))


def test_frame_and_ground_truth_agree_on_the_lamp(tiny):
    """The lamp is where the product's camera convention projects it, at its planar depth, and the
    ground-truth cube (converted to the product's equirect layout) shows it in the same direction."""
    from bench.pbr.render import render_frame
    from bench.pbr.scenes import camera_poses, intrinsics, scales_at
    from bench.pbr.truth import source_maps
    from core.conventions import equirect_directions

    scene, cache = tiny
    poses, k = camera_poses(scene), intrinsics(scene)
    lamp = np.asarray(scene["lights"]["lamp"]["centre"])
    i = 7  # after the switch
    frame = render_frame(scene, scales_at(scene, i / scene["camera"]["fps"]), poses[i], FRAME_SPP, cache)
    p = np.linalg.inv(poses[i]) @ np.r_[lamp, 1.0]
    u, v = k["fx"] * p[0] / -p[2] + k["cx"], -k["fy"] * p[1] / -p[2] + k["cy"]
    assert 4 < u < k["width"] - 4 and 4 < v < k["height"] - 4, "the lamp must be in view"
    y = frame[..., :3].mean(-1)
    rows, cols = np.nonzero(y > 0.5 * y.max())
    assert abs(cols.mean() + 0.5 - u) < 1.0 and abs(rows.mean() + 0.5 - v) < 1.0
    # planar depth at the lamp's centre pixel: the sphere's near side
    assert frame[int(v), int(u), 3] == pytest.approx(-p[2] - scene["lights"]["lamp"]["radius"], abs=0.03)
    before = render_frame(scene, scales_at(scene, 0.0), poses[i], FRAME_SPP, cache)
    assert before[..., :3].max() < 0.2 * frame[..., :3].max(), "before the switch the lamp is off"

    maps = source_maps(scene, poses[i][:3, 3], cache, face_size=FACE, spp=CUBE_SPP, height=32)
    lum = maps["lamp"].mean(-1).reshape(-1)
    d = equirect_directions(32, dtype=torch.float64).reshape(-1, 3)[int(torch.argmax(lum))].numpy()
    g = (lamp - poses[i][:3, 3]) / np.linalg.norm(lamp - poses[i][:3, 3])
    assert math.degrees(math.acos(float(np.clip(d @ g, -1, 1)))) < 8.0
    hits = cache.hits
    render_frame(scene, scales_at(scene, 0.7), poses[i], FRAME_SPP, cache)  # cached: no render
    assert cache.hits == hits + 1


@pytest.fixture(scope="module")
def session(tiny, tmp_path_factory):
    """The tiny room's session through the product: the full-AR upload's draft job, scored."""
    from bench.pbr_sessions import evaluate_session

    scene, cache = tiny
    return evaluate_session(scene, cache, tmp_path_factory.mktemp("pbr-work"), ("full-ar",), FRAME_SPP, FACE,
                            CUBE_SPP, sphere_size=16, log=lambda *_: None)


def test_session_through_the_product(tiny, session):
    """The draft job on the full-AR upload: the stored field answers finite positive maps at the
    probes and times, each scored against the truth and the constant map; the session's summary
    has the ratios and the job's cost."""
    from bench.pbr_sessions import summarise_variant

    scene, _ = tiny
    s = session
    assert s["jobs"]["full-ar"]["cpu_s"] > 0 and s["jobs"]["full-ar"]["exposure_source"] == "params"
    assert len(s["records"]) == len(scene["probes"]) * len(s["times"])
    for r in s["records"]:
        assert r["fluence"]["full-ar"] > 0 and math.isfinite(r["fluence"]["full-ar"])
        for method in ("full-ar", "mean-colour"):
            sc = r["spheres"][method]
            assert "non_finite" not in sc and math.isfinite(sc["diffuse"]["si_rmse"]) and sc["diffuse"]["si_rmse"] >= 0
        assert r["fluence"]["truth"] > 0
    (switch,) = s["switches"]
    near = next(p for p in switch["probes"] if scene["probes"][p["probe"]]["label"] == "near lamp")
    assert near["truth"] > 1.2  # the truth near the lamp brightens
    summary = summarise_variant([s], "full-ar")
    assert summary["diffuse_si_rmse_rel"]["ratio"] > 0 and summary["cpu_s"] > 0
    assert summary["lamp_seen_on"][1] + summary["lamp_seen_off"][1] > 0  # the lamp test had probe-times to score


def test_the_lamp_switching_on_brightens_the_estimate_near_it(tiny, session):
    """The lamp switches on while the auto-exposure follows it: the estimate near the lamp must
    brighten (it did not while core/capture/response.py took that exposure step for the camera's
    curve, 3a71154-b78ba12: every frame turned white and the job assumed static light)."""
    scene, _ = tiny
    (switch,) = session["switches"]
    near = next(p for p in switch["probes"] if scene["probes"][p["probe"]]["label"] == "near lamp")
    assert near["full-ar"] > 1.05, f"the estimate near the lamp did not brighten: {near}, job {session['jobs']}"
