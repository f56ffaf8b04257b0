"""bench.room_scans: what each held-out room is scored with, and the scan's ground truth."""
from __future__ import annotations

import json

import torch

from capture_fixtures import bright_ceiling_room, write_manifest_rooms


def test_each_room_is_scored_with_a_profile_and_choices_made_without_it(tmp_path):
    """The elevation profile, clip rule and spill colour of the room's fold (fitted on the other indoor rooms)
    and the fill settings the photo CV chose in that fold; a control room gets the all-rooms
    choices."""
    from bench.panoramas import indoor_rooms
    from bench.real_panoramas import CLIP_KEY, GAIN_KEY, SPILL_KEY, cv_fits
    from bench.room_scans import cv_overrides

    write_manifest_rooms(tmp_path, bright_ceiling_room)
    refit = {"refit": {"fill_source_cap": {"chosen": {"a.hdr": 2.0, "b.hdr": 4.0, "c.hdr": 2.0}, "all_rooms": 8.0},
                       "a_removed_setting": {"chosen": {"a.hdr": 1.0}, "all_rooms": 1.0}}}
    (tmp_path / "refit.json").write_text(json.dumps(refit))
    overrides_for = cv_overrides(tmp_path, tmp_path / "refit.json")
    folds, _ = cv_fits(indoor_rooms(tmp_path))
    assert overrides_for("b.hdr") == {GAIN_KEY: folds["b.hdr"][GAIN_KEY], CLIP_KEY: folds["b.hdr"][CLIP_KEY],
                                      SPILL_KEY: folds["b.hdr"][SPILL_KEY], "priors.reprojection.fill_source_cap": 4.0}
    assert overrides_for("a.hdr")[GAIN_KEY] != overrides_for("b.hdr")[GAIN_KEY]
    assert overrides_for("d.hdr") == {"priors.reprojection.fill_source_cap": 8.0}


def test_the_truth_is_the_panorama_in_the_first_kept_cameras_axes():
    """scan_truth(d) = panorama(R_first d): the first kept camera's forward (-z) sees the
    panorama's colour in that camera's viewing direction."""
    from core.envmap import sample_envmap
    from core.sim.room_scan import render_scan, scan_truth

    h = 32
    coarse = torch.rand(1, 3, 4, 8, generator=torch.Generator().manual_seed(0)) + 0.1
    pano = torch.nn.functional.interpolate(coarse, size=(h, 2 * h), mode="bilinear")[0].permute(1, 2, 0)  # smooth
    clip = render_scan(pano, yaw0=40.0, seed=1, size=(32, 24))
    for first in (0, 5):
        truth = scan_truth(pano, clip, h, first)
        forward = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
        world = (clip.poses[first][:3, :3] @ forward.T).T
        a = sample_envmap(truth.double(), forward)
        b = sample_envmap(pano.double(), world)
        torch.testing.assert_close(a, b, rtol=0.05, atol=0.02)


def test_the_table_names_the_host_its_cpu_seconds_were_measured_on():
    """A report that records its machine says so under its summary; one that does not (before
    the bench recorded it) prints no host line rather than a guess."""
    from bench.room_scans import markdown

    room = {"file": "a.hdr", "split": "dev", "span_stops": 4.0, "truth_seen_corr": 0.9,
            "scores": {m: {k: {"si_rmse": 1.0, "si_rmse_rel": 1.0, "angular_deg": 2.0}
                           for k in ("diffuse", "matte", "mirror")}
                       for m in ("product", "mean-colour")},
            "modes": {"product": {"cpu_s": 50.0, "seen_corr": 0.9, "drift": 0.0, "uses_time": False,
                                  "tracking": {"method": "rotation", "max_rotation_error_deg": 0.1}}}}
    report = {"modes": ["product"], "rooms": [room]}
    assert not any(line.startswith("CPU seconds on") for line in markdown(report))
    report["machine"] = {"cpu_model": "Some CPU", "cores": 2, "git_commit": "abcdef0123",
                         "date_utc": "2026-12-07T07:00"}
    assert "CPU seconds on Some CPU, 2 cores, at abcdef0 (2026-12-07)." in markdown(report)
    row = [line for line in markdown(report) if line.startswith("| a.hdr")][0]
    assert "| 1.00 / 1.00 / 1.00 | – |" in row  # a row scored before the self-check: no grade
    room["modes"]["product"]["grade"] = "partly explained"
    assert "| 1.00 / 1.00 / 1.00 | partly explained |" in [ln for ln in markdown(report) if ln.startswith("| a.hdr")][0]
