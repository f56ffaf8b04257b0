"""The auto-exposure benches: the simulated phone auto-exposure meters each frame, the pans of
real panoramas carry it, and the summaries count what they claim."""
import pytest
import torch

from bench.accuracy_probe import level_table, scale_stops, without_frame_ev
from bench.auto_exposure_pans import FRAMES, ae_clip, map_change_stops, summarise
from bench.tracking import BUNDLED
from core.sim.panorama_room import load_panorama
from core.sim.sensor import AE_MID_GREY, metered_evs


def test_metering_darkens_a_brighter_frame_and_moves_part_way():
    dim, bright = torch.full((4, 4, 3), 0.09), torch.full((4, 4, 3), 0.72)
    assert metered_evs([dim], speed=1.0) == pytest.approx([1.0])  # 0.09 * 2 = mid-grey
    evs = metered_evs([dim, bright, bright], speed=0.5)
    assert evs[1] == pytest.approx(1.0 + 0.5 * (-2.0 - 1.0)) and evs[2] < evs[1] and evs[2] > -2.0
    lamp = torch.full((32, 32, 3), AE_MID_GREY)
    lamp[0, 0] = 1e6  # one tiny lamp must not set the exposure
    assert metered_evs([lamp])[0] > -0.1  # uncapped it would meter 12 stops down (clamped at -4)


def test_a_pan_of_the_bundled_panorama_changes_its_exposure():
    ldr, evs, poses = ae_clip(load_panorama(BUNDLED, 64), 0.0, 0.0)
    assert ldr.shape[0] == len(evs) == len(poses) == FRAMES and 0.0 <= float(ldr.min()) and float(ldr.max()) <= 1.0
    assert max(evs) - min(evs) > 0.2
    dimmed, flat, _ = ae_clip(load_panorama(BUNDLED, 64), 0.0, 0.0, dimming=0.5)
    assert flat == [0.0] * FRAMES and float(dimmed[-1].mean()) < float(dimmed[0].mean())


def test_summary_counts_decisions_and_errors():
    row = {
        "file": "a.hdr",
        "tracked": True,
        "ae_range_stops": 1.0,
        "decision": {"auto": False, "locked": True, "estimate": False},
        "auto_detected": True,
        "estimate_error_stops": 0.1,
        "mean_colour_diffuse_si_rmse_rel": 0.6,
        "locked_dimming": {"auto_detected": True, "read_as_changing_light": True},
        "runs": {
            k: {"drift_stops": d, "map_change_stops": d, "diffuse_si_rmse_rel": 0.5}
            for k, d in (("auto", 0.0), ("locked", 0.4), ("estimate", 0.0), ("stated", 0.0))
        },
    }
    s = summarise(
        [row, {**row, "auto_detected": False, "decision": {"auto": True, "locked": False, "estimate": False}}]
    )
    assert s["read_as_changing_light"] == {"auto": 1, "locked": 1, "estimate": 0} and s["auto_exposure_detected"] == 1
    assert s["drift_stops_mean"]["locked"] == 0.4 and s["estimate_error_stops"]["max"] == 0.1
    assert s["locked_dimming"] == {"auto_detected": 2, "read_as_changing_light": 2}
    s = summarise([row, {**row, "file": "b.hdr", "tracked": False, "estimate_error_stops": 6.0}])
    assert s["tracking_failed"] == ["b.hdr"] and s["panoramas_tracked"] == 1 and s["estimate_error_stops"]["max"] == 0.1


def test_level_in_stops_and_a_capture_copy_without_exposures(tmp_path):
    import json

    gt = torch.ones(2, 8, 16, 3)
    pred = gt * torch.tensor([2.0, 0.5])[:, None, None, None]
    s = scale_stops(pred, gt)
    assert s["mean"] == pytest.approx(0.0) and s["sd"] == pytest.approx(2 ** 0.5, rel=1e-3)
    src = tmp_path / "cap"
    (src / "frames").mkdir(parents=True)
    (src / "capture.json").write_text(json.dumps({"format": "lightfield-capture", "frame_ev": [0.0, -1.0]}))
    copy = without_frame_ev(src, tmp_path / "copy")
    assert "frame_ev" not in json.loads((copy / "capture.json").read_text()) and (copy / "frames").is_dir()
    assert "frame_ev" in json.loads((src / "capture.json").read_text())  # the original is untouched
    report = {"withhold_frame_ev": True, "frame_ev": "estimate", "temporal": "auto", "suites": {"s": {
        "ratios": {"field": {"vs_constant": {"diffuse.si_rmse": 0.9, "matte.si_rmse": 0.5}}},
        "scale_stops": {"field": {"mean": 0.2, "sd": 0.3}}, "uses_time": {"field": False}}}}
    (tmp_path / "r.json").write_text(json.dumps(report))
    assert "| r | s | withheld, estimate | auto | False | 0.90 | 0.50 | +0.20 (0.30) | - |" in level_table(
        [str(tmp_path / "r.json")]
    )


def test_map_change_is_zero_for_the_same_map_and_one_stop_for_twice_as_bright():
    env = torch.rand(8, 16, 3) + 0.1
    assert map_change_stops(env, env) == 0.0
    assert map_change_stops(env, 2 * env) == pytest.approx(1.0, rel=1e-5)
