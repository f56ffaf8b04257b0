"""Faults injected into a capture the engine otherwise reads right (issue 62): a failed track, a
track drifting to 135 deg off by its end, a wrong exposure course, depth 3x too far, and frames from
two rooms in one clip. Each must be detected (the job's quality block names the stage, or its
grade is not "explained"), and each must be answered no worse than the capture's constant map
(diffuse sphere si-RMSE and angle, core.metrics, at every frame's camera against the room's truth).

The capture is a short walk through the bundled panorama's room (core.sim.panorama_room: real
texture, exact depth and poses) written as a capture app's export (nerfstudio), so the engine
reads it without tracking; a fault is injected where its stage would have made it."""
from __future__ import annotations

import warnings
from dataclasses import replace

import pytest
import torch

from capture_fixtures import PANORAMA
from core.conventions import inverse_tonemap
from core.engine.job import run_job
from core.engine.params import JobParams
from core.engine.presets import preset
from core.engine.self_check import GRADES
from core.metrics import angular_error_deg, render_probe_spheres, si_rmse
from core.sim.faults import FPS, FRAMES, drifting, render_walk, walk_room, write_walk
from core.sim.panorama_room import load_panorama

MAP_HEIGHT = 16
CONFIG = preset("draft").with_overrides({"distill": {"iterations": 100, "work_height": 24, "warmup_steps": 4,
                                                     "checkpoint_every": 1000}})
# room scores are compared against the constant map's within this share (its own rounding)
SAME = 1.02
PANORAMA_ROWS = 64


def _panorama() -> torch.Tensor:
    return load_panorama(PANORAMA, PANORAMA_ROWS)


def _inject_after_load(monkeypatch, fault):
    """Run `fault(capture)` on the loaded capture, where the tracker would have run."""
    import core.capture.prepare as prepare

    real = prepare.track_capture
    monkeypatch.setattr(prepare, "track_capture", lambda capture, params=None: fault(real(capture, params)))


def _failed_track(capture):
    meta = {k: v for k, v in capture.metadata.items() if k != "poses_source"}
    meta["tracking"] = {"method": "failed:static-fallback", "camera_moves": True}
    return replace(capture, poses=capture.poses[:1].expand_as(capture.poses).clone(), metadata=meta)


def _rotated_track(capture):
    """The track drifts to 135 deg off by the last frame (the first frame anchors the world)."""
    return replace(capture, poses=torch.stack(drifting(list(capture.poses), 135.0)))


def _depth_off(capture):
    return replace(capture, depth=capture.depth * 3.0)


FAULTS = {
    "none": ({}, None, [False] * FRAMES),
    "failed track": ({}, _failed_track, [False] * FRAMES),
    "track rotated 135 deg": ({}, _rotated_track, [False] * FRAMES),
    # the frames share one exposure; the capture says it fell by a stop a frame
    "wrong exposure course": ({"frame_ev": [-1.0 * i for i in range(FRAMES)]}, None, [False] * FRAMES),
    "depth 3x too far": ({}, _depth_off, [False] * FRAMES),
    "two rooms in one clip": ({}, None, [False] * (FRAMES // 2) + [True] * (FRAMES // 2)),
}


def _diffuse_scores(pred: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    (p, g), mask = render_probe_spheres([pred, truth], "diffuse", 32)
    return si_rmse(p, g, mask), angular_error_deg(p, g, mask)


_RESULTS: dict[str, tuple[dict, torch.Tensor, torch.Tensor]] = {}


def _result(tmp_path_factory, name):
    """(quality block, the job's mean diffuse [si-RMSE, angle] over the frames' cameras, the
    constant map's), each fault's job run once for the module's tests."""
    if name not in _RESULTS:
        with pytest.MonkeyPatch.context() as monkeypatch:
            _RESULTS[name] = _run_fault(tmp_path_factory.mktemp("fault"), monkeypatch, name)
    return _RESULTS[name]


def _run_fault(tmp_path, monkeypatch, name):
    extra, fault, rooms = FAULTS[name]
    pano = _panorama()
    ldr, depth, intr, poses = render_walk(pano, rooms)
    root = write_walk(tmp_path / "scan", ldr, depth, intr, poses)
    if fault is not None:
        _inject_after_load(monkeypatch, fault)
    params = JobParams.model_validate({"fps": FPS, "transfer": "gamma:2.4", **extra})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        artefact = run_job(root, None, params, tmp_path / "field", config=CONFIG).artefact
    constant = inverse_tonemap(ldr).reshape(-1, 3).mean(0)
    job, const = [], []
    for i, pose in enumerate(poses):
        x = pose[:3, 3].float()
        truth = walk_room(pano, rooms[i]).envmap(x, MAP_HEIGHT)
        t = i / FPS if artefact.uses_time else None
        answer = artefact.envmap(x, t, MAP_HEIGHT)[0]
        job.append(_diffuse_scores(answer, truth))
        const.append(_diffuse_scores(constant.expand_as(truth).clone(), truth))
    return artefact.meta["quality"], torch.tensor(job).mean(0), torch.tensor(const).mean(0)


def test_a_capture_read_right_is_explained_and_kept(tmp_path_factory):
    quality, job, const = _result(tmp_path_factory, "none")
    assert quality["grade"] == GRADES[0] and quality["stage"] is None and quality["fallback"] is None, quality
    assert not quality["frame_agreement"]["pairs_disagreeing"]
    assert float(job[0]) < float(const[0]) and float(job[1]) < float(const[1])


# What neither the field's re-rendering nor the frames' agreement can tell (core.engine.frame_agreement):
# a wrong exposure course is a factor per frame, which an even change of light also is; depth 3x too
# far misplaces this walk's reprojections by a pixel or two at the check's 24 rows, which leaves more
# texture in the pairs' ratios (about 4x the clean walk's) but still less than the frames hold. Both
# answers stay better than the constant map (the test below); the check does not flag them.
UNTOLD = {"wrong exposure course": "a factor per frame: an exposure misstated reads as the light dimming evenly",
          "depth 3x too far": "the walk's parallax misplaced by a pixel or two at 24 rows: less than the texture"}


@pytest.mark.parametrize("name", [
    pytest.param(n, marks=pytest.mark.xfail(reason=UNTOLD[n], strict=True)) if n in UNTOLD else n
    for n in FAULTS if n != "none"])
def test_an_injected_fault_is_detected(tmp_path_factory, name):
    quality, _, _ = _result(tmp_path_factory, name)
    assert quality["grade"] != GRADES[0] and quality["stage"], quality


@pytest.mark.parametrize("name", [n for n in FAULTS if n != "none"])
def test_an_injected_fault_is_answered_no_worse_than_the_constant_map(tmp_path_factory, name):
    _, job, const = _result(tmp_path_factory, name)
    assert float(job[0]) <= SAME * float(const[0]), (job.tolist(), const.tolist())
    assert float(job[1]) <= SAME * float(const[1]), (job.tolist(), const.tolist())


@pytest.mark.parametrize("name", ["failed track", "track rotated 135 deg", "two rooms in one clip"])
def test_a_capture_no_reading_of_which_holds_most_frames_is_answered_by_its_constant_map(tmp_path_factory, name):
    quality, job, const = _result(tmp_path_factory, name)
    assert quality["fallback"] and "constant map" in quality["fallback"]["answer"], quality
    # the capture's constant map as the job read it (its exposures removed): within a few per cent of the test's
    assert torch.allclose(job, const, rtol=0.05), (job.tolist(), const.tolist())


def test_the_constant_field_answers_its_colour_everywhere_and_the_rule_keeps_a_majority():
    from core.engine.fallback import constant_field, fallback_reason
    from core.fields import FieldConfig, SceneBounds, build_field

    like = build_field(FieldConfig(kind="mlp", uses_time=True), SceneBounds.from_points(torch.randn(20, 3)))
    field = constant_field([0.2, 0.5, 3.0], like)
    maps = field.envmaps(torch.randn(3, 3), None, 8)
    assert not field.uses_time and torch.allclose(maps, torch.tensor([0.2, 0.5, 3.0]).expand_as(maps), rtol=1e-4)
    kept = {"grade": GRADES[1], "residual_ratio": 0.5, "field_residual": 0.05, "constant_residual": 0.1,
            "log_ratio_floor": 0.0039,
            "frame_agreement": {"pairs_disagreeing": [[3, 4]], "largest_agreeing_share": 0.6}}
    assert fallback_reason(kept) is None
    assert "worse than" in fallback_reason({**kept, "residual_ratio": 1.5, "field_residual": 0.15})
    # within one 8-bit step of the constant map's residual: a tie (a flat photo both explain), kept
    assert fallback_reason({**kept, "residual_ratio": 1.02, "field_residual": 0.102}) is None
    assert "disagree" in fallback_reason({**kept, "frame_agreement": {"pairs_disagreeing": [[3, 4]],
                                                                      "largest_agreeing_share": 0.5}})
