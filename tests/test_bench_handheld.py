"""The handheld bench: its rolling shutter reads rows at different instants, its blur averages
instants, and the summary counts what the fallback took."""
import torch

from bench.handheld import VARIANTS, pose_at, render_frame, summarise
from bench.tracking import BUNDLED
from core.camera import Camera, Intrinsics
from core.sim.panorama_room import PanoramaRoom, load_panorama
from core.tracking.room import assumed_room


def test_a_global_shutter_is_one_instant_and_a_rolling_one_reads_rows_later():
    intr = Intrinsics.from_hfov(32, 24, 60.0)
    room = PanoramaRoom(load_panorama(BUNDLED, 64), assumed_room(), torch.zeros(3))
    sharp = render_frame(room, intr, 3, 10.0, 0.0, 0.0, 0.0)
    assert torch.equal(sharp, room.render(Camera(intr, pose_at(0.3, 10.0, 0.0)), 1)[0])
    rolling = render_frame(room, intr, 3, 10.0, 0.0, 0.0, 0.2)  # a slow readout: the bottom rows 0.2 s later
    later = room.render(Camera(intr, pose_at(0.3 + 0.2 * 23.5 / 24, 10.0, 0.0)), 1)[0]
    assert float((rolling[-1] - later[-1]).abs().mean()) < float((rolling[-1] - sharp[-1]).abs().mean())
    blurred = render_frame(room, intr, 3, 10.0, 0.0, 0.1, 0.0)
    assert float(blurred.std()) < float(sharp.std())  # the pan smears it


def test_summary_counts_the_fallback_and_the_errors():
    clip = {"method": "rotation", "frames_kept": 20, "rotation_fallback": False, "max_rotation_error_deg": 0.5}
    rows = [{"clips": {v: dict(clip) for v in VARIANTS}} for _ in range(3)]
    rows[1]["clips"]["rolling"].update(rotation_fallback=True, max_rotation_error_deg=1.5)
    rows[2]["clips"]["rolling"] = {"method": "failed:static-fallback", "frames_kept": 20, "rotation_fallback": False}
    s = summarise(rows)["rolling"]
    assert s["tracked"] == 2 and s["within_1_deg"] == 1 and s["by_the_rotation_fallback"] == 1
    assert s["within_1_deg_by_the_fallback"] == 0


def test_walk_summary_counts_the_walks_taken_for_a_pan():
    from bench.handheld import WALKS

    rows = [{"clips": {"walk-noisy": {"method": m, "frames_kept": 20, "max_rotation_error_deg": e}}}
            for m, e in (("rotation", 3.0), ("sfm:pycolmap", 1.0), ("sfm:pycolmap", 2.0))]
    rows.append({"clips": {"walk-noisy": {"method": "failed:static-fallback", "frames_kept": 20}}})
    s = summarise(rows, {"walk-noisy": WALKS["walk-noisy"]})["walk-noisy"]
    assert s["taken_as_a_pan"] == 1 and s["methods"] == {"failed:static-fallback": 1, "rotation": 1, "sfm:pycolmap": 2}
    assert s["max_rotation_error_deg_median"] == 2.0 and s["max_rotation_error_deg_worst"] == 3.0


def test_sfm_starts_summary_compares_the_first_start_the_kept_model_and_the_best():
    from bench.handheld import WALKS
    from bench.sfm_starts import summarise as summarise_starts

    def clip(kept, **starts):
        return {
            **{a: {"frames": f, "max_rotation_error_deg": e, "pooled_median_px": 0.3} for a, (f, e) in starts.items()},
            "kept": kept,
        }
    rows = [{"clips": {"walk-noisy": clip(8.0, **{"4.0": (20, 17.0), "8.0": (20, 6.0), "16.0": (20, 5.0)})}},
            # the first start falls short
            {"clips": {"walk-noisy": clip(16.0, **{"4.0": (5, 11.0), "16.0": (20, 3.0)})}},
            {"clips": {"walk-noisy": clip(4.0, **{"4.0": (20, 2.0), "8.0": (20, 1.0)})}},
            {"clips": {"walk-noisy": {}}}]  # no start registered half the frames: not counted
    s = summarise_starts(rows, {"walk-noisy": WALKS["walk-noisy"]}, (4.0, 8.0, 16.0))["walk-noisy"]
    assert s["clips"] == 3 and s["first_start_short_of_the_most_frames"] == 1
    assert s["first_start_alone"] == {"worst": 17.0, "median": 17.0, "over_5_deg": 1}
    assert s["kept"] == {"worst": 6.0, "median": 3.0, "over_5_deg": 1}
    assert s["best_start_oracle"] == {"worst": 5.0, "median": 3.0, "over_5_deg": 0}
