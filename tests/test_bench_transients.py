"""bench.transients' summary over per-panorama rows (no rendering): the counts it reports, and a
clip tracking took for a moving camera, which has no mask to score (the test run's summary step
failed on one)."""
from bench.transients import figure, summarise


def _row(iou=0.7, static=True, keep=True, pan_changes=False):
    walk = {"changing_light_remove": False, "changing_light_keep": keep, "static_camera": static,
            "painted_share": 0.08, "frames_with_transients": 10, "rank": 1}
    if static:
        walk.update(iou=iou, recall=0.95)
    other = {"changing_light_remove": True, "changing_light_keep": True, "static_camera": True,
             "painted_share": 0.0, "frames_with_transients": 0, "rank": 1}
    pan = {"static_camera": False, "method": "rotation", "frames_kept": 16, "max_rotation_error_deg": 0.5,
           "read_as_changing_light": pan_changes, "painted_share": 0.0}
    runs = {k: {"uses_time": k == "keep", "map_change_stops": 0.1 if k == "keep" else 0.0, "cpu_s": 1.0,
                "diffuse_si_rmse_rel": 0.3} for k in ("default", "keep", "clean")}
    return {"clips": {"walk": walk, "walk-halved": {**other, "iou": 0.6, "recall": 0.9}, "pool-off": other,
                      "clean": {**other, "changing_light_remove": False, "changing_light_keep": False}},
            "pans": {k: pan for k in ("pan", "pan-walk", "pan-ae", "pan-halved")}, "runs": runs,
            "mean_colour_diffuse_si_rmse_rel": 0.4}


def test_summary_counts_and_skips_unscored_clips():
    s = summarise([_row(0.7), _row(0.5, pan_changes=True), _row(static=False, keep=False)])
    walk = s["clips"]["walk"]
    assert walk["read_as_changing_light"] == {"remove": 0, "keep": 2}
    assert walk["scored"] == 2 and walk["iou_min"] == 0.5 and walk["iou_mean"] == 0.6
    assert walk["static_camera"] == 2
    assert s["pans"]["pan"]["read_as_changing_light"] == 1 and s["pans"]["pan"]["within_1deg"] == 3
    assert s["jobs_with_time_input"] == {"default": 0, "keep": 3, "clean": 0}
    assert s["map_change_stops_max"]["keep"] == 0.1


def test_the_figure_is_a_person_sized_silhouette():
    shape, coat = figure(120, 160, seed=1)
    assert shape.shape == (120, 160) and coat.shape == (120, 160, 3)
    rows = shape.any(1).nonzero().flatten()
    assert 85 <= int(rows.max() - rows.min()) + 1 <= 91  # 3/4 of the frame high
    assert int(shape.any(0).sum()) <= 160 // 6 + 1
    assert 0.0 < float(coat[shape].mean()) < 1.0
