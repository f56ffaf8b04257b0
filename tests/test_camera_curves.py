"""Camera curves (core.sim.camera_curves): each curve a camera writes through, what its files
declare, the per-capture draw, and that the simulator's and the benches' files say what the
curve says (issue 60: no privileged curve in the benches)."""
from __future__ import annotations

import json
import typing

import numpy as np
import pytest
import torch

from core.sim import camera_curves as cc
from core.sim.camera_curves import CURVES, NAMES, REALISTIC, REFERENCE, STILL, VIDEO

X = torch.linspace(0.0, 1.0, 4097)


@pytest.mark.parametrize("name", NAMES)
def test_curve_is_monotone_from_zero_to_one_at_its_white_point(name):
    curve = CURVES[name]
    y = curve.apply(X * curve.clip)
    assert float(y[0]) == 0.0
    assert float(curve.apply(torch.tensor([curve.clip]))[0]) == pytest.approx(1.0, abs=1e-6)
    assert bool((y[1:] > y[:-1]).all()), "strictly increasing below the white point"
    assert float(curve.apply(torch.tensor([10.0 * curve.clip]))[0]) == pytest.approx(1.0, abs=1e-6)  # clips above


@pytest.mark.parametrize("name", NAMES)
def test_encode_quantises_to_the_bit_depth_and_decode_inverts_the_curve(name):
    curve = CURVES[name]
    codes = curve.encode(X * curve.clip)
    levels = codes * curve.levels
    torch.testing.assert_close(levels, levels.round(), atol=1e-3, rtol=0)
    assert len(torch.unique(codes)) > (200 if curve.bit_depth == 8 else 800)
    # decode is the exact inverse of the continuous curve (tone curve and HLG scale included)
    x = X[1:] * curve.clip
    torch.testing.assert_close(curve.decode(curve.apply(x)), x, atol=2e-5, rtol=2e-4)


def test_the_curves_are_the_standard_ones():
    x = torch.tensor([0.001, 0.01, 0.18, 0.5])
    torch.testing.assert_close(CURVES["srgb"].apply(x), torch.where(x <= 0.0031308, 12.92 * x,
                                                                     1.055 * x.pow(1 / 2.4) - 0.055))
    torch.testing.assert_close(CURVES["rec709"].apply(x), torch.where(x < 0.018, 4.5 * x, 1.099 * x.pow(0.45) - 0.099))
    torch.testing.assert_close(CURVES[REFERENCE].apply(x), x.pow(1 / 2.4))
    # HLG: reference white (exposed 1) at 75 % signal, 10 bits, headroom above it
    assert float(CURVES["hlg10"].apply(torch.tensor([1.0]))[0]) == pytest.approx(0.75, abs=1e-4)
    assert CURVES["hlg10"].bit_depth == 10 and CURVES["hlg10"].clip > 3.5
    # filmic: a toe (darker than sRGB in the deep shadows), mid-grey lifted, a shoulder
    film, srgb = CURVES["filmic"].apply(x), CURVES["srgb"].apply(x)
    assert float(film[0]) < float(srgb[0]) and float(film[2]) > float(srgb[2]) + 0.1


def test_what_each_camera_declares():
    declared = {n: (CURVES[n].declares(STILL), CURVES[n].declares(VIDEO)) for n in NAMES}
    assert declared == {"srgb": ("srgb", "srgb"), "rec709": (None, "rec709"), "filmic": ("srgb", "srgb"),
                        "hlg10": (None, "hlg"), REFERENCE: ("gamma:2.4", None)}
    assert CURVES["filmic"].oetf == "srgb"  # the tone curve is not stated
    # only the reference, whose video cannot state gamma 2.4, tells the job its curve
    assert [n for n in NAMES if CURVES[n].job_params(VIDEO)] == [REFERENCE]
    assert CURVES[REFERENCE].job_params(VIDEO) == {"transfer": "gamma:2.4"}
    assert all(not CURVES[n].job_params(STILL) for n in NAMES)
    assert CURVES[REFERENCE].label.startswith("gamma2.4 (reference")
    assert all("reference" not in CURVES[n].label for n in REALISTIC)


def test_loaded_is_what_a_loader_trusting_the_declaration_hands_the_engine():
    codes = CURVES["srgb"].encode(torch.tensor([0.18, 0.5]))
    torch.testing.assert_close(CURVES["srgb"].loaded(codes, STILL), CURVES["srgb"].decode(codes).pow(1 / 2.4))
    # a rec709 still states nothing: read as sRGB (the loader's default); its video states rec709
    rec = CURVES["rec709"].encode(torch.tensor([0.18]))
    torch.testing.assert_close(CURVES["rec709"].loaded(rec, STILL), CURVES["srgb"].decode(rec).pow(1 / 2.4))
    torch.testing.assert_close(CURVES["rec709"].loaded(rec, VIDEO), CURVES["rec709"].decode(rec).pow(1 / 2.4))
    # the reference is the engine's convention itself
    torch.testing.assert_close(CURVES[REFERENCE].loaded(rec, STILL), rec)


def test_the_draw_is_deterministic_and_covers_the_realistic_set():
    names = [f"room_{i:03d}.hdr" for i in range(200)]
    video = [cc.draw(n, VIDEO).name for n in names]
    assert video == [cc.draw(n, VIDEO).name for n in names]
    assert set(video) == set(REALISTIC)
    assert min(video.count(c) for c in REALISTIC) > 25  # roughly uniform
    still = {cc.draw(n, STILL).name for n in names}
    assert still == {"srgb", "rec709", "filmic"}  # HLG is video only
    assert REFERENCE not in set(video) | still
    # a fixed value, so a change of the draw is a deliberate one (bench rows name their curve)
    assert cc.draw("spatial", STILL).name == "filmic" and cc.draw("static", STILL).name == "srgb"


def test_resolve_and_run_choices():
    assert cc.resolve("rec709", "x", VIDEO).name == "rec709"
    assert cc.resolve("hlg10", "x", STILL).name == "srgb"  # a still falls back
    assert cc.resolve("hlg10", "x", VIDEO).name == "hlg10"
    assert cc.resolve("drawn", "x", VIDEO) == cc.draw("x", VIDEO)
    assert cc.run_choices("all", STILL) == ("srgb", "rec709", "filmic", REFERENCE)
    assert cc.run_choices("all", VIDEO) == (*REALISTIC, REFERENCE)
    assert cc.run_choices("drawn", VIDEO) == ("drawn",)
    with pytest.raises(ValueError, match="unknown camera curve"):
        cc.run_choices("log-c", VIDEO)


def test_group_by_curve_puts_the_reference_last_and_labelled():
    rows = [{"curve": REFERENCE, "v": 1}, {"curve": "srgb", "v": 2}, {"curve": "srgb", "v": 3}]
    out = cc.group_by_curve(rows, lambda rs: sum(r["v"] for r in rs))
    assert list(out) == ["srgb", CURVES[REFERENCE].label] and out["srgb"] == 5


def test_display_exposure_is_tonemap_hdrs_rule():
    from core.conventions import tonemap
    from core.exposure import display_tonemap

    hdr = torch.rand(24, 32, 3, generator=torch.Generator().manual_seed(1)).pow(3) * 40
    k = cc.display_exposure(hdr)
    torch.testing.assert_close(tonemap(hdr * k), display_tonemap(hdr, 99.0, 2.4, 0.9), atol=1e-5, rtol=0)


def test_the_spec_and_the_cli_name_the_registry_curves():
    from cli.bench import CURVE_CHOICES
    from core.sim.spec import CameraCurveName, SensorSpec

    assert set(typing.get_args(CameraCurveName)) == {"drawn", *NAMES}
    assert set(CURVE_CHOICES) == set(cc.CHOICES) - {"all"}
    assert SensorSpec().curve == "drawn"
    with pytest.raises(ValueError):
        SensorSpec(curve="log-c")


def test_mean_colour_linearised_with_the_cameras_curve_is_not_biased():
    """The constant baseline decodes with the capture's own curve: its mean is the exposed
    light's (to quantisation); the convention's inverse would bias it for a filmic camera."""
    from bench.real_panoramas import estimate_mean_colour
    from core.conventions import inverse_tonemap

    x = torch.rand(48, 64, 3, generator=torch.Generator().manual_seed(2)) * 0.9
    for name in NAMES:
        curve = CURVES[name]
        codes = curve.encode(x)
        mean = estimate_mean_colour(codes, curve)[0, 0]
        torch.testing.assert_close(mean, x.reshape(-1, 3).mean(0), atol=4e-3, rtol=0)
    film = CURVES["filmic"].encode(x)
    assert float((inverse_tonemap(film).mean() - x.mean()).abs()) > 0.05


def _stated(path):
    from core.io.images import decode_image

    return decode_image(path).stated_transfer


@pytest.mark.parametrize("name,expected", [("srgb", "srgb"), ("filmic", "srgb"), (REFERENCE, "gamma:2.4"),
                                           ("rec709", None)])
def test_a_photo_png_declares_what_the_camera_declares(tmp_path, name, expected):
    curve = CURVES[name]
    codes = curve.encode(torch.rand(8, 10, 3, generator=torch.Generator().manual_seed(0)))
    path = cc.write_png(tmp_path / "p.png", codes, curve)
    stated = _stated(path)
    assert (None if stated.transfer is None else str(stated.transfer)) == expected
    from core.io.images import read_image

    np.testing.assert_array_equal(np.round(read_image(path) * 255), np.round(codes.numpy() * 255))


@pytest.mark.parametrize("name,expected,bits", [("srgb", "srgb", 8), ("rec709", "rec709", 8), ("filmic", "srgb", 8),
                                                ("hlg10", "hlg", 10), (REFERENCE, None, 8)])
def test_a_video_declares_what_the_camera_declares(tmp_path, name, expected, bits):
    from core.io.video import read_video

    curve = CURVES[name]
    codes = curve.encode(torch.rand(3, 16, 16, 3, generator=torch.Generator().manual_seed(0)) * 0.8)
    path = cc.write_video(tmp_path / "v.mp4", codes, 5.0, curve)
    stated = read_video(path).stated_transfer
    assert (None if stated.transfer is None else str(stated.transfer)) == expected
    assert stated.bit_depth == bits


def _tiny(curve: str):
    from core.sim.suites import suite

    s = suite("static")
    return s.model_copy(update={
        "resolution": (24, 18), "frames": 2, "probes": [],
        "quality": s.quality.model_copy(update={"area_samples": 1, "indirect_samples": 1}),
        "sensor": s.sensor.model_copy(update={"curve": curve}),
    })


@pytest.mark.parametrize("name", ["rec709", "filmic", REFERENCE])
def test_the_simulators_capture_declares_its_curve(tmp_path, name):
    from core.io.images import read_image
    from core.io.video import read_video
    from core.sim.capture import write_capture
    from core.sim.render import render_frame

    scene = _tiny(name)
    write_capture(scene, tmp_path, envmap_height=4, video=True)
    doc = json.loads((tmp_path / "capture.json").read_text())
    curve = CURVES[name]
    assert doc["camera_curve"] == name and doc["transfer"] == curve.oetf
    # the ideal sensor (no `sensor` effect) writes the curve's codes
    frame = read_image(tmp_path / doc["frames"][0])
    expected = curve.encode(render_frame(scene, 0).hdr).numpy()
    np.testing.assert_allclose(frame, expected, atol=0.5 / 255)
    stated = _stated(tmp_path / doc["frames"][0])
    assert (None if stated.transfer is None else str(stated.transfer)) == curve.declares(STILL)
    video = read_video(tmp_path / doc["video"]).stated_transfer
    assert (None if video.transfer is None else str(video.transfer)) == curve.declares(VIDEO)
    # the loader decodes the frames with what capture.json states (the filmic tone curve stays in)
    from core.capture.prepare import load_prepared_capture
    from core.transfer import parse_transfer

    cap = load_prepared_capture(tmp_path)
    assert cap.metadata["transfer"]["curve"] == curve.oetf
    stated = parse_transfer(doc["transfer"]).to_convention(torch.from_numpy(frame))
    torch.testing.assert_close(cap.frames[0], stated, atol=1e-5, rtol=0)


def test_a_drawn_scene_records_the_drawn_curve_and_hlg_falls_back_for_png_frames(tmp_path):
    from core.sim.sensor import scene_curve

    assert scene_curve(_tiny("drawn")).name == cc.draw("static", STILL).name
    assert scene_curve(_tiny("hlg10")).name == "srgb"


def test_room_scan_constant_map_decodes_with_the_clips_curve():
    from core.sim.panorama_room import load_panorama
    from core.sim.room_scan import SAMPLE_PANORAMA, render_scan, scan_constant_map

    pano = load_panorama(SAMPLE_PANORAMA, 32)
    for name in ("filmic", "hlg10"):
        clip = render_scan(pano, yaw0=10.0, seed=1, size=(24, 18), path="pan", curve=CURVES[name])
        assert clip.curve.name == name
        levels = clip.ldr * clip.curve.levels
        torch.testing.assert_close(levels, levels.round(), atol=1e-3, rtol=0)
        const = scan_constant_map(clip, 4)
        torch.testing.assert_close(const[0, 0], CURVES[name].decode(clip.ldr).reshape(-1, 3).mean(0))
    plain = render_scan(pano, yaw0=10.0, seed=1, size=(24, 18), path="pan")
    assert plain.curve is None  # in memory: the engine's convention, 8 bits


def test_a_simulated_suites_constant_map_decodes_with_its_own_curve(tmp_path):
    """bench.suite.simulated.capture_linear (the accuracy probe's constant map): the frames
    linearised with the capture's own curve are the light (to quantisation); the engine's
    reading of a filmic file (declared sRGB) keeps the tone curve in."""
    from bench.suite.simulated import capture_linear
    from core.capture.prepare import load_prepared_capture
    from core.sim.capture import write_capture
    from core.sim.render import render_frame

    scene = _tiny("filmic")
    write_capture(scene, tmp_path, envmap_height=4, video=False)
    cap = load_prepared_capture(tmp_path)
    hdr = render_frame(scene, 0).hdr.clamp(0.0, 1.0)
    lit = hdr > 0.02  # where 8 bits resolve the light well
    linear = capture_linear(tmp_path, cap)
    assert float(((linear[0] - hdr).abs() / hdr.clamp_min(1e-3))[lit].median()) < 0.02
    assert float(((cap.linear()[0] - hdr).abs() / hdr.clamp_min(1e-3))[lit].median()) > 0.1


def test_a_bench_runs_each_curve_and_summarises_the_realistic_ones_apart_from_the_reference(tmp_path):
    """bench.real_panoramas.rows_over / curve_summaries, which the per-capture benches share:
    `--curve all` evaluates every capture once per curve; `summary` is over the realistic
    curves, `summary_per_curve` per curve with the reference last and labelled."""
    from bench.real_panoramas import curve_summaries, rows_over

    def evaluate(f, work, curve):
        return {"file": f.name, "curve": cc.resolve(curve, f"t:{f.name}", VIDEO).name, "v": 1}

    files = [tmp_path / "a.hdr", tmp_path / "b.hdr"]
    rows = rows_over(files, evaluate, tmp_path, cc.run_choices("all", VIDEO))
    assert [r["curve"] for r in rows] == [*cc.run_choices("all", VIDEO)] * 2
    out = curve_summaries(rows, len)
    assert out["summary"] == 8  # two captures x four realistic curves
    assert list(out["summary_per_curve"]) == [*REALISTIC, CURVES[REFERENCE].label]
    drawn = rows_over(files, evaluate, tmp_path, cc.run_choices("drawn", VIDEO))
    assert [r["curve"] for r in drawn] == [cc.draw(f"t:{f.name}", VIDEO).name for f in files]
    assert curve_summaries([{"curve": REFERENCE}], len)["summary"] == 1  # only the reference run: over it


def test_room_scan_table_rows_per_curve_with_the_reference_labelled():
    from bench.room_scans import markdown

    def room(curve):
        return {"file": "a.hdr", "split": "dev", "curve": curve, "span_stops": 4.0, "truth_seen_corr": 0.9,
                "scores": {m: {k: {"si_rmse": 1.0, "si_rmse_rel": 1.0, "angular_deg": 2.0}
                               for k in ("diffuse", "matte", "mirror")} for m in ("product", "mean-colour")},
                "modes": {"product": {"cpu_s": 50.0, "seen_corr": 0.9, "drift": 0.0, "uses_time": False,
                                      "tracking": {"method": "rotation", "max_rotation_error_deg": 0.1}}}}

    report = {"modes": ["product"], "curve": "all", "rooms": [room(c) for c in (*REALISTIC, REFERENCE)]}
    text = "\n".join(markdown(report))
    assert "| scan | product | 4 |" in text  # the summary row: the realistic curves only
    for c in REALISTIC:
        assert f"| scan, curve {c} | product | 1 |" in text
    assert f"| scan, curve {CURVES[REFERENCE].label} | product | 1 |" in text
    assert "| a.hdr | dev | hlg10 | product |" in text


def test_simulate_cli_forces_a_curve(tmp_path):
    import argparse

    from cli.main import main
    from cli.simulate import add_arguments

    p = argparse.ArgumentParser()
    add_arguments(p)
    choices = next(a.choices for a in p._actions if a.dest == "curve")
    assert set(choices) == set(cc.CHOICES) - {"all"}
    spec = _tiny("drawn")
    (tmp_path / "s.json").write_text(spec.model_dump_json())
    assert main(["simulate", str(tmp_path / "s.json"), "-o", str(tmp_path / "cap"), "--curve", "rec709",
                 "--no-video", "--height", "4"]) == 0
    assert json.loads((tmp_path / "cap" / "capture.json").read_text())["camera_curve"] == "rec709"
