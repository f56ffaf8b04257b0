"""The real-panorama protocol's geometry: crops and ground truth agree on directions."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from bench.panoramas import camera_rotation, perspective_crop
from bench.real_panoramas import PITCH_DEG, estimate_mean_colour, view_for
from core.conventions import equirect_directions, inverse_tonemap
from core.envmap import rotate_envmap, sample_envmap


def _direction_coded_pano(h=64):
    """Radiance encodes the direction (shifted positive), so lookups can be checked exactly."""
    return equirect_directions(h) + 1.5


@given(st.floats(-180, 180), st.floats(-15, 15))
@settings(max_examples=25, deadline=None)
def test_camera_rotation_is_a_rotation(yaw, pitch):
    R = camera_rotation(yaw, pitch)
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.det(R) > 0


def test_crop_centre_sees_the_camera_forward_direction():
    pano = _direction_coded_pano()
    R = camera_rotation(40.0, 10.0)
    crop, intr = perspective_crop(pano, R)
    forward = R @ torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    centre = crop[intr.height // 2 - 1 : intr.height // 2 + 1, intr.width // 2 - 1 : intr.width // 2 + 1].mean((0, 1))
    assert torch.allclose(centre.double() - 1.5, forward, atol=0.03)


def test_ground_truth_in_camera_frame_matches_the_world_panorama():
    pano = _direction_coded_pano()
    R = camera_rotation(-120.0, -7.0)
    gt = rotate_envmap(pano, R.T)
    d_cam = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    assert torch.allclose(sample_envmap(gt, d_cam), sample_envmap(pano, d_cam @ R.T), atol=0.06)


def test_views_are_fixed_per_file_and_differ_between_files():
    assert view_for("a.hdr") == view_for("a.hdr")
    assert view_for("a.hdr") != view_for("b.hdr")


@pytest.mark.parametrize("name", ["srgb", "rec709", "filmic", "gamma2.4"])
def test_mean_colour_baseline_is_the_mean_linearised_with_the_photos_curve(name):
    from core.sim.camera_curves import CURVES

    curve = CURVES[name]
    ldr = torch.zeros(4, 4, 3)
    ldr[:2] = 0.5
    env = estimate_mean_colour(ldr, curve)
    assert torch.allclose(env, torch.full_like(env, float(curve.decode(torch.tensor(0.5))) / 2))
    if name == "gamma2.4":  # the reference camera's inverse is the convention's
        assert torch.allclose(env, torch.full_like(env, float(inverse_tonemap(torch.tensor(0.5))) / 2))


@pytest.mark.parametrize("name", ["srgb", "rec709", "filmic", "gamma2.4"])
def test_photo_round_trips_through_the_png_the_job_reads(tmp_path, name):
    """The product path reads the photo from a PNG file: the capture the job sees is the
    8-bit photo decoded with what its file declares (sRGB where it declares nothing), with
    the stated FOV."""
    from bench.panoramas import CROP_HFOV_DEG
    from bench.real_panoramas import job_params, ldr_photo, photo_curve, write_photo
    from core.capture.load import load_capture
    from core.sim.camera_curves import STILL

    pano = _direction_coded_pano()
    crop, intr = perspective_crop(pano, camera_rotation(10.0, 0.0))
    curve = photo_curve("p.hdr", 0, name)
    ldr = ldr_photo(crop, curve)
    levels = ldr * 255
    assert torch.allclose(levels, levels.round(), atol=1e-3)
    cap = load_capture(write_photo(ldr, tmp_path / "p.png", curve), None, job_params(curve))
    assert torch.allclose(cap.frames[0], curve.loaded(ldr, STILL), atol=1e-5)
    assert abs(cap.intrinsics.fx - intr.fx) < 1e-6 * intr.fx
    assert job_params().intrinsics.hfov_deg == CROP_HFOV_DEG and job_params().preset == "draft"


def test_section_runs_the_product_end_to_end_on_a_tiny_manifest(tmp_path):
    """run_panoramas on a one-panorama `dev` manifest, with a 3-step job: every method is
    scored, ratios and correlations are finite, the truth correlates well with its photo."""
    import math

    from bench.real_panoramas import CONSTANT, FIELD, PRIOR, run_panoramas
    from core.io.hdr import write_hdr

    h = 64
    d = equirect_directions(h)
    pano = 0.2 + 0.1 * (d + 1.0)  # a smooth colour gradient
    pano[h // 4 : h // 4 + 2, 10:12] = 40.0  # a lamp
    write_hdr(tmp_path / "room.hdr", pano.numpy())
    (tmp_path / "MANIFEST.tsv").write_text("filename\tsplit\nroom.hdr\tdev\n")
    out = run_panoramas(tmp_path, None, 16, workdir=tmp_path / "work", overrides={"distill.iterations": 3})
    assert "VARIANT" in out["protocol"]
    methods = out["splits"]["dev"]["methods"]
    for name in (FIELD, PRIOR, CONSTANT):
        assert all(math.isfinite(v) for v in methods[name]["vs_constant"].values()), name
    assert methods[CONSTANT]["observed_corr"] == 0.0
    assert methods["truth"]["observed_corr"] > 0.9
    assert methods[PRIOR]["observed_corr"] > 0.5
    # the photo's camera curve is drawn by its name, recorded, and summarised per curve
    from bench.real_panoramas import photo_curve

    image = out["splits"]["dev"]["images"][0]
    assert out["curve"] == "drawn" and image["curve"] == photo_curve("room.hdr").name
    assert list(out["splits"]["dev"]["per_curve"]) == [image["curve"]]


def test_views_turn_the_first_photo_evenly_around_the_room():
    """View 0 is the protocol's single photo; the others turn its yaw by multiples of 360/views."""
    yaw0, pitch0 = view_for("room.hdr")
    assert view_for("room.hdr", 0, 4) == (yaw0, pitch0)
    for k in range(1, 4):
        yaw, pitch = view_for("room.hdr", k, 4)
        assert -180.0 <= yaw < 180.0 and abs(pitch) <= PITCH_DEG
        assert abs((yaw - yaw0 - 90.0 * k + 180.0) % 360.0 - 180.0) < 1e-9
    assert view_for("room.hdr", 1, 4) == view_for("room.hdr", 1, 4)


def test_intervals_resample_panoramas_and_rescore_reproduces_the_summary():
    """The ratio's 90 % interval brackets the ratio of means and treats a panorama's photos as one
    draw (two identical photos of a room do not narrow it); `rescore` rebuilds the summary from
    the per-photo results alone."""
    from bench.real_panoramas import CONSTANT, FIELD, rescore, summarise

    def photo(file, field, const):
        scores = {
            m: {
                mat: {"si_rmse_rel": v, "angular_deg": v, "si_rmse": v, "nrmse": v}
                for mat in ("diffuse", "matte", "mirror")
            }
            for m, v in ((FIELD, field), (CONSTANT, const))
        }
        return {"file": file, "scores": scores, "seconds": {FIELD: 1.0, CONSTANT: 0.0},
                "observed_corr": {FIELD: 0.9, CONSTANT: 0.0, "truth": 0.95}}

    rooms = [("a", 0.5, 1.0), ("b", 0.9, 1.0), ("c", 0.7, 1.0), ("d", 1.1, 1.0)]
    once = [photo(*r) for r in rooms]
    twice = once + [photo(*r) for r in rooms[:1]]  # room a photographed twice, the same photo
    s1 = summarise(once, (FIELD, CONSTANT))
    lo, hi = s1[FIELD]["interval_90"]["diffuse_si_rmse_rel"]
    assert s1[FIELD]["vs_constant"]["diffuse_si_rmse_rel"] == pytest.approx(0.8)
    assert lo < 0.8 < hi
    assert summarise(twice, (FIELD, CONSTANT))[FIELD]["interval_90"] == s1[FIELD]["interval_90"]
    assert CONSTANT not in {k for k, v in s1.items() if "interval_90" in v}
    assert s1[FIELD]["photos_beating_constant"]["diffuse_si_rmse_rel"] == [3, 4]  # room d loses
    report = {"splits": {"dev": {"images": once, "methods": {FIELD: {}, CONSTANT: {}, "truth": {}}}}}
    assert rescore(report)["splits"]["dev"]["methods"] == s1


def test_compare_counts_photos_that_moved_each_way_not_the_mean():
    """A mean can improve on one photo while most get a little worse: the comparison counts them."""
    from bench.real_panoramas import compare_reports

    def report(diffuse):
        images = [{"file": f"p{i}.hdr", "view": 0,
                   "scores": {"field": {"diffuse": {"si_rmse_rel": d, "angular_deg": 5.0},
                                        "matte": {"si_rmse_rel": 0.9, "angular_deg": 5.0}}}}
                  for i, d in enumerate(diffuse)]
        return {"splits": {"dev": {"images": images}}}

    before, after = report([0.9, 0.5, 0.5, 0.5]), report([0.3, 0.52, 0.52, 0.5])
    rows = compare_reports(before, after)
    diffuse = next(r for r in rows if "diffuse si_rmse_rel" in r)
    # one better (0.9 -> 0.3), two worse by 0.02, one unchanged; median ratio of 0.33, 1.04, 1.04, 1.0
    assert diffuse == "| dev | diffuse si_rmse_rel | 4 | 1 | 2 | 1.020 |"
    assert next(r for r in rows if "matte si_rmse_rel" in r) == "| dev | matte si_rmse_rel | 4 | 0 | 0 | 1.000 |"


# ----------------------------------------------------------------- leave-one-room-out (--cv)
def _cv_photo(file, field, const, angle=None):
    from bench.real_panoramas import CONSTANT, FIELD

    def mats(v, a):
        return {
            mat: {"si_rmse_rel": v, "angular_deg": a, "si_rmse": v, "nrmse": v}
            for mat in ("diffuse", "matte", "mirror")
        }

    return {"file": file, "split": "dev", "scores": {FIELD: mats(field, angle if angle is not None else field),
                                                    CONSTANT: mats(const, const)},
            "seconds": {FIELD: 1.0, CONSTANT: 0.0}, "observed_corr": {FIELD: 0.9, CONSTANT: 0.0, "truth": 0.95}}


def test_cv_summary_ratios_95_interval_and_rooms_failing_on_angle():
    from bench.real_panoramas import CONSTANT, FIELD, cv_markdown, cv_summary
    from bench.suite.evaluation import ratio_interval

    images = [
        _cv_photo("a", 0.5, 1.0),
        _cv_photo("b", 0.9, 1.0),
        _cv_photo("c", 0.7, 1.0),
        _cv_photo("d", 1.1, 1.0, angle=1.6),
    ]
    s = cv_summary(images, (FIELD, CONSTANT))
    f = s[FIELD]
    assert f["vs_constant"]["diffuse_si_rmse_rel"] == pytest.approx(0.8)
    lo, hi = f["interval_95"]["diffuse_si_rmse_rel"]
    assert lo < 0.8 < hi
    lo90, hi90 = ratio_interval([0.5, 0.9, 0.7, 1.1], [1.0] * 4)
    assert lo <= lo90 and hi >= hi90  # 95 % is at least as wide as 90 %
    assert f["rooms_diffuse_angle_over_1.5x_constant"] == {"count": 1, "of": 4, "rooms": ["d"]}
    assert f["rooms_beating_constant"]["diffuse_si_rmse_rel"] == [3, 4]
    assert "vs_constant" not in s[CONSTANT]
    # the oracle bound takes each room's better of the two: d's 1.1 counts as its constant's 1.0
    assert f["oracle_floor_at_constant"]["diffuse_si_rmse_rel"] == pytest.approx((0.5 + 0.9 + 0.7 + 1.0) / 4)
    assert f["oracle_floor_at_constant"]["diffuse_angular_deg"] == pytest.approx((0.5 + 0.9 + 0.7 + 1.0) / 4)
    report = {"protocol": "p", "splits": {"indoor (leave-one-room-out)": {"methods": s, "images": images}}}
    text = "\n".join(cv_markdown(report))
    assert "1 / 4" in text and "| d | dev |" in text
    assert "| job's grade |" in text and "| 1.10 / 1.60 | – |" in text  # rows scored before the self-check
    images[3]["grade"] = "worse than a constant map -> constant map"
    assert "| 1.10 / 1.60 | worse than a constant map -> constant map |" in "\n".join(cv_markdown(report))
    assert "Oracle bound, indoor (leave-one-room-out), field" in text and "diffuse angle 0.775" in text


def test_a_saved_cv_report_is_rendered_again_with_its_summaries_remade(tmp_path):
    from bench.real_panoramas import CONSTANT, FIELD, main

    images = [_cv_photo("a", 0.5, 1.0), _cv_photo("d", 1.1, 1.0, angle=1.6)]
    saved = {"protocol": "p", "methods": [FIELD, CONSTANT],
             "splits": {"indoor (leave-one-room-out)": {"methods": {}, "images": images}}}
    (tmp_path / "cv.json").write_text(json.dumps(saved))
    assert main(["--cv-report", str(tmp_path / "cv.json"), "--md", str(tmp_path / "cv.md")]) == 0
    text = (tmp_path / "cv.md").read_text()
    assert "0.800 [" in text and "1 / 2" in text and "diffuse si-RMSE 0.750" in text


def test_cv_refits_the_elevation_profile_without_the_scored_room(tmp_path):
    from bench.calibration.indoor_fill import gain_from_profiles, panorama_profiles
    from bench.panoramas import indoor_rooms
    from bench.real_panoramas import cv_gains
    from capture_fixtures import bright_ceiling_room, write_manifest_rooms

    write_manifest_rooms(tmp_path, bright_ceiling_room)  # a different bright ceiling per room
    rooms = indoor_rooms(tmp_path)
    assert [p.name for p in rooms] == ["a.hdr", "b.hdr", "c.hdr"]  # control is not an indoor room
    folds, everything = cv_gains(rooms)
    profiles = panorama_profiles(rooms)
    assert folds["a.hdr"] == gain_from_profiles(profiles[1:])
    assert folds["b.hdr"] == gain_from_profiles(profiles[[0, 2]])
    assert everything == gain_from_profiles(profiles)
    assert len({tuple(g) for g in folds.values()}) == 3


def test_cv_refits_the_clip_rule_without_the_scored_room(monkeypatch, tmp_path):
    """Each room's coefficients are the least-squares fit on the OTHER rooms' blobs; the shipped
    ones are the fit on all of them; a fold with no blob keeps the shipped coefficients."""
    import bench.calibration.clip_rule as cr
    from core.capture.highlights import RULE_COEFFICIENTS

    rng = torch.Generator().manual_seed(0)

    def blobs(slope):
        feats = torch.cat([torch.ones(12, 1), torch.rand(12, 4, generator=rng) * 4 - 2], 1).double()
        return [{"features": f.tolist(), "true_stops": float(1.0 + slope * f[2]), "energy": 1.0} for f in feats]

    samples = {"a.hdr": blobs(0.5), "b.hdr": blobs(-0.5), "c.hdr": blobs(0.0), "d.hdr": []}
    monkeypatch.setattr(cr, "blob_samples", lambda path: samples[path.name])
    folds, everything = cr.cv_coefficients([tmp_path / n for n in samples])
    assert folds["a.hdr"] == cr.fit(samples["b.hdr"] + samples["c.hdr"])
    assert folds["c.hdr"] == cr.fit(samples["a.hdr"] + samples["b.hdr"])
    assert folds["a.hdr"] != folds["b.hdr"]
    assert everything == cr.fit(samples["a.hdr"] + samples["b.hdr"] + samples["c.hdr"])
    assert cr.cv_coefficients([tmp_path / "d.hdr"])[1] == list(RULE_COEFFICIENTS)


def test_the_spill_colour_settings_are_chosen_without_the_scored_room():
    """bench.calibration.clip_rule.colour_cv: each room's white-hot blobs are recoloured with the setting
    the OTHER rooms' blobs favour. Two rooms' warm lamps spill their own warm light; a third,
    heavier room's white lamps sit on a warm wall. Over all rooms leaving the pixels white wins
    (the heavy room decides); the heavy room's own fold recolours, the others' folds do not."""
    import bench.calibration.clip_rule as cr

    warm, white, background = (1.0, 0.7, 0.5), (1.0, 1.0, 1.0), np.array([0.1, 0.1, 0.1])

    def blob(room, truth, energy):
        halo_rgb = [list(background + 0.5 * np.array(warm) * (1.0 - r / 8)) for r in range(6)] + [list(background)] * 2
        return {"file": room, "area_px": 20, "halo": [float(np.mean(c)) for c in halo_rgb], "ring_pixels": [30] * 8,
                "white_fraction": 1.0, "halo_rgb": halo_rgb, "hot_true_rgb": list(truth), "hot_energy": energy}

    samples = [blob("a", warm, 1.0), blob("b", warm, 1.0), blob("c", white, 10.0)]
    report = cr.colour_cv(samples)
    assert report["chosen_on_all_rooms"] == [None, None]
    assert report["chosen_per_room"]["a"] == [None, None] and report["chosen_per_room"]["b"] == [None, None]
    assert report["chosen_per_room"]["c"] != [None, None]
    assert report["held_out"]["mean_deg"] > report["left_white"]["mean_deg"]  # every fold chose wrong
    # the same choices as the jobs' `spill_colour` setting: "left white" as an excess no spill reaches
    by_room = {room: [x for x in samples if x["file"] == room] for room in "abc"}
    folds, everything = cr.cv_spill_colour(by_room)
    assert everything == folds["a"] == folds["b"] == [cr.LEFT_WHITE_EXCESS, 1.0]
    assert folds["c"] == [float(v) for v in report["chosen_per_room"]["c"]]


def test_cv_select_never_lets_the_scored_room_vote(monkeypatch, tmp_path):
    """Per fold, the grid value with the lowest score summed over the OTHER rooms: a room whose
    own score would flip the choice does not flip its own."""
    import bench.real_panoramas as rp

    monkeypatch.setattr(rp, "CV_REFIT", {"fill_source_cap": ((1.0, 2.0), "diffuse", "si_rmse_rel")})
    table = {"a": (1.0, 2.0), "b": (1.0, 2.0), "c": (9.0, 1.0)}  # a, b prefer 1.0; c strongly prefers 2.0

    def fake(path, sphere_size, workdir, methods, overrides, curve="drawn"):
        v = table[path.name][(1.0, 2.0).index(overrides["priors.reprojection.fill_source_cap"])]
        return {"scores": {rp.PRIOR: {"diffuse": {"si_rmse_rel": v}}}}

    monkeypatch.setattr(rp, "evaluate_panorama", fake)
    rooms = [tmp_path / n for n in table]
    sel = rp.cv_select(rooms, {n: {rp.GAIN_KEY: [1.0, 1.0]} for n in table}, {}, 16, tmp_path)["fill_source_cap"]
    # all rooms: 11 vs 5 -> 2.0; without a: 10 vs 3 -> 2.0; without c: 2 vs 4 -> 1.0
    assert sel["all_rooms"] == 2.0
    assert sel["chosen"] == {"a": 2.0, "b": 2.0, "c": 1.0}
    # an ablation that fixes the setting is not refitted
    assert rp.cv_select(rooms, {}, {"priors.reprojection.fill_source_cap": None}, 16, tmp_path) == {}


def test_cv_runs_the_prior_and_the_constant_map_on_a_tiny_manifest(tmp_path):
    """run_cv on three indoor rooms (one per split) and a control: the folds' profiles and
    choices reach the jobs, control is summarised apart, every ratio is finite."""
    import math

    from bench.real_panoramas import CONSTANT, PRIOR, run_cv
    from capture_fixtures import write_manifest_rooms

    d = equirect_directions(32)

    def room(k):
        pano = 0.2 + 0.1 * (d + 1.0) * (1 + k)
        pano[2 + k : 4 + k, 10:14] = 30.0
        return pano

    write_manifest_rooms(tmp_path, room)
    out = run_cv(tmp_path, 16, (PRIOR, CONSTANT), workdir=tmp_path / "work")
    indoor, control = out["splits"]["indoor (leave-one-room-out)"], out["splits"]["control (not indoor)"]
    assert indoor["files"] == ["a.hdr", "b.hdr", "c.hdr"] and control["files"] == ["d.hdr"]
    for im in indoor["images"]:
        ov = im["fold_overrides"]
        assert ov["priors.reprojection.fill_source_cap"] == out["refit"]["fill_source_cap"]["chosen"][im["file"]]
        assert len(ov["priors.reprojection.elevation_gain"]) == 24
        assert len(ov["priors.reprojection.clip_coefficients"]) == 5
    control_ov = control["images"][0]["fold_overrides"]
    assert control_ov["priors.reprojection.elevation_gain"] == out["all_rooms_elevation_gain"]
    assert control_ov["priors.reprojection.clip_coefficients"] == out["all_rooms_clip_coefficients"]
    m = indoor["methods"][PRIOR]
    assert all(math.isfinite(v) for v in m["vs_constant"].values())
    assert m["rooms_diffuse_angle_over_1.5x_constant"]["of"] == 3
