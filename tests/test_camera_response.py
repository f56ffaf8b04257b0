"""The camera's response recovered from frames at different exposures (core.capture.response),
and the transfer functions it starts from (core.transfer): synthetic auto-exposure captures
encoded with curves the product does not assume, read as a file that declares sRGB is read."""
from __future__ import annotations

import math

import pytest
import torch

from core.camera import Intrinsics
from core.capture.load import capture_from_arrays
from core.capture.params import CaptureParams
from core.capture.response import fit_response, with_estimated_response
from core.transfer import SRGB, parse_transfer, transfer_from_h273

EVS = torch.tensor([0.0, -1.0, -2.0, 1.0, 0.5, -1.5, 2.0, -0.5])


def filmic(x: torch.Tensor) -> torch.Tensor:
    """A phone-like tone curve (toe and shoulder) reaching 1 at 11.2x the exposure's white."""
    def f(v):
        return v * (2.51 * v + 0.03) / (v * (2.43 * v + 0.59) + 0.14)
    return (f(x) / f(torch.tensor(11.2))).clamp(0.0, 1.0)


def wall_radiance(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """A textured wall over ~2.5 decades: smooth gradients and flat patches."""
    patches = 1.0 + 3.0 * (((x * 3).floor() + (y * 2).floor()) % 3)
    rgb = torch.stack((0.02 + 0.5 * (x % 1) * (y % 1), 0.03 + 0.4 * (x % 1), 0.05 + 0.3 * (y % 1)), -1)
    return rgb * patches[..., None]


def encoded(linear: torch.Tensor, camera, seed: int) -> torch.Tensor:
    """What a camera writes (noise before its curve, 8 bits), read back as a file declaring sRGB is."""
    g = torch.Generator().manual_seed(seed)
    noisy = (linear + torch.randn(linear.shape, generator=g) * 0.002 * linear.sqrt()).clamp_min(0.0)
    return SRGB.to_convention(torch.round(camera(noisy) * 255.0) / 255.0)


def static_capture(camera, evs=EVS):
    H, W = 72, 96
    y, x = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    scene = wall_radiance(x, y)
    frames = torch.stack([encoded(scene * 2.0 ** float(e), camera, i) for i, e in enumerate(evs)])
    return capture_from_arrays(frames, frame_ev=evs), scene


def moving_capture(camera):
    """A camera sliding 0.6 m along a wall 2 m away, auto-exposing, with poses and depth."""
    H, W = 72, 96
    k = Intrinsics.from_hfov(W, H, 60.0)
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    frames, poses = [], []
    for i, e in enumerate(EVS):
        tx = 0.6 * i / (len(EVS) - 1)
        X = tx + (u - k.cx) / k.fx * 2.0
        Y = -(v - k.cy) / k.fy * 2.0
        frames.append(encoded(wall_radiance(X * 0.8, Y * 0.8 + 1.0) * 2.0 ** float(e), camera, i))
        pose = torch.eye(4, dtype=torch.float64)
        pose[0, 3] = tx
        poses.append(pose)
    depth = torch.full((len(EVS), H, W), 2.0)
    return capture_from_arrays(torch.stack(frames), depth, intrinsics=k, poses=torch.stack(poses), frame_ev=EVS)


def log_error(frames_convention: torch.Tensor, scene: torch.Tensor) -> float:
    """Mean |log linear error| over the well-exposed pixels of frame 0, up to one scale."""
    ok = (frames_convention > 0.06) & (frames_convention < 0.95)
    e = (frames_convention.clamp_min(1e-6).pow(2.4).log() - scene.clamp(0, 1).clamp_min(1e-6).log())[ok]
    return float((e - e.median()).abs().mean())


def test_transfers_round_trip_and_name_their_h273_codes():
    x = torch.logspace(-6, 0, 200)
    for name in ("srgb", "rec709", "linear", "hlg", "gamma:2.2"):
        t = parse_transfer(name)
        assert torch.allclose(t.to_linear(t.from_linear(x)), x, rtol=1e-3, atol=1e-7), name
    assert str(transfer_from_h273(18)) == "hlg" and str(transfer_from_h273(16)) == "pq"
    assert str(transfer_from_h273(13)) == "srgb" and transfer_from_h273(2) is None
    with pytest.raises(ValueError, match="gamma:G"):
        parse_transfer("gamma2.4")
    with pytest.raises(ValueError):
        CaptureParams(transfer="gamma:9")


def test_hlg_keeps_highlights_far_above_reference_white_unclipped():
    hlg = parse_transfer("hlg")
    white = torch.tensor(0.265)  # HLG reference white (75 % signal) in scene light
    assert abs(float(hlg.from_linear(white)) - 0.75) < 0.01
    lamp = white * 3.5  # a lamp 3.5x reference white: still under HLG's top code
    assert float(hlg.from_linear(lamp)) < 0.99
    assert float(SRGB.from_linear(lamp / white)) > 0.999  # an SDR camera puts white at its top code: clipped


def test_a_filmic_camera_read_as_srgb_is_corrected_from_its_exposures():
    capture, scene = static_capture(lambda v: SRGB.from_linear(filmic(v)))
    fit = fit_response(capture)
    assert fit is not None and fit.better
    assert fit.fitted_error < 0.2 * fit.declared_error
    corrected, _ = with_estimated_response(capture)
    assert corrected.metadata["response"]["used"]
    before, after = log_error(capture.frames[0], scene), log_error(corrected.frames[0], scene)
    assert after < 0.25 * before, (before, after)
    # the curve keeps white white and black black, and stays monotone
    assert float(corrected.frames.max()) <= 1.0 and float(corrected.frames.min()) >= 0.0
    assert (fit.log_g.diff() >= 0).all()


def test_a_correctly_declared_camera_keeps_its_curve_within_noise():
    capture, scene = static_capture(SRGB.from_linear)
    corrected, fit = with_estimated_response(capture)
    assert fit is not None
    assert log_error(corrected.frames[0], scene) < log_error(capture.frames[0], scene) + 0.005


def test_rec709_read_as_srgb_is_recovered_through_a_moving_cameras_poses():
    capture = moving_capture(parse_transfer("rec709").from_linear)
    fit = fit_response(capture)
    assert fit is not None and fit.better and fit.fitted_error < 0.5 * fit.declared_error


def test_a_locked_exposure_or_one_frame_cannot_tell_a_curve():
    capture, _ = static_capture(SRGB.from_linear, evs=torch.zeros(4))
    kept, fit = with_estimated_response(capture)
    assert fit is None and not kept.metadata["response"]["used"]
    assert torch.equal(kept.frames, capture.frames)
    single, _ = static_capture(SRGB.from_linear, evs=torch.zeros(1))
    assert fit_response(single) is None


def test_a_global_fade_the_auto_exposure_follows_is_not_taken_for_a_curve():
    """Daylight fades 3 stops while the camera's auto-exposure follows it and states its exposures:
    the codes barely move while the stated exposures do. A light changing for the whole room is a
    per-frame factor, not a curve (the ratio does not vary with the code level): the declared curve
    is kept, or the fit stays within noise of it."""
    H, W = 72, 96
    y, x = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    scene = wall_radiance(x, y)
    fade = torch.linspace(0.0, -3.0, 8)  # the light, in stops
    ae = -fade  # the exposure follows it
    frames = torch.stack([encoded(scene * 2.0 ** float(f + e), SRGB.from_linear, i)
                          for i, (f, e) in enumerate(zip(fade, ae))])
    capture = capture_from_arrays(frames, frame_ev=ae)
    kept, fit = with_estimated_response(capture)
    assert fit is not None
    grey = torch.linspace(0.1, 0.9, 9)
    assert (fit.apply(grey) - grey).abs().max() < 0.03 or not fit.better, fit.as_dict()
    assert (kept.frames - capture.frames).abs().max() < 0.03



def test_readings_a_few_codes_apart_do_not_decide_a_curve():
    """An auto-exposure creeping 0.03 stop a frame: every pair the fit compares is exposed under
    a quarter stop apart, its readings a few codes apart, which noise and a highlight's shift
    swamp (a flat curve called a glossy room's such pairs one light). Without the rule the same
    capture is fitted; with it, it cannot tell a curve and keeps the declared one."""
    from dataclasses import replace

    from core.capture.response import DEFAULT

    capture, _ = static_capture(SRGB.from_linear, evs=torch.arange(24) * 0.03)  # 0.69 stop in all
    assert fit_response(capture, replace(DEFAULT, min_pair_stops=0.0)) is not None
    kept, fit = with_estimated_response(capture)
    assert fit is None and not kept.metadata["response"]["used"]
    assert torch.equal(kept.frames, capture.frames)


# ---------------------------------------------------------------------------------------
# Files read through their own curve (core.capture.load.decode_transfer)
# ---------------------------------------------------------------------------------------
def _hdr_room(T=4, H=48, W=64):
    """Linear scene light (HLG's scale: the sensor clips at 1): a wall at 0.1 and a lamp at 0.9,
    3.4x reference white, which an SDR camera exposed for the wall clips."""
    scene = torch.full((H, W, 3), 0.1)
    scene[16:32, 24:40] = 0.9
    return scene[None].expand(T, H, W, 3).clone()


def test_an_hlg_10_bit_clip_is_read_to_linear_light_with_its_lamp_unclipped(tmp_path):
    from core.capture.load import load_capture
    from core.io import write_video

    hlg = parse_transfer("hlg")
    scene = _hdr_room()
    for codec in ("libx265", "libx264"):
        path = write_video(tmp_path / f"hlg-{codec}.mp4", hlg.from_linear(scene).numpy(), fps=10.0,
                           transfer="hlg", bit_depth=10, primaries="bt2020", codec=codec)
        cap = load_capture(path, params=CaptureParams(tracking="off"))
        meta = cap.metadata["transfer"]
        assert meta["curve"] == "hlg" and meta["bit_depth"] == 10 and meta["primaries"] == "bt2020", meta
        linear = cap.linear()[0]
        wall, lamp = float(linear[4:12, 4:12].mean()), float(linear[20:28, 28:36].mean())
        assert lamp / wall == pytest.approx(9.0, rel=0.05), (codec, lamp, wall)  # the 8-bit twin clips it
        assert float(cap.frames.max()) < 0.99  # nothing reads as clipped
    sdr = write_video(tmp_path / "sdr.mp4", SRGB.from_linear(scene / 0.3).numpy(), fps=10.0, transfer="srgb")
    cap = load_capture(sdr, params=CaptureParams(tracking="off"))
    assert float(cap.frames[0, 20:28, 28:36].min()) > 0.99  # the SDR twin: the lamp clipped


def test_png_chunks_decide_the_curve_and_params_override_them(tmp_path):
    from core.capture.load import load_capture
    from core.io import write_png

    linear = torch.linspace(0.01, 1.0, 64).reshape(1, 64, 1).expand(48, 64, 3).contiguous()
    for transfer in ("srgb", "gamma:2.2", None):
        code = (SRGB if transfer == "srgb" else parse_transfer(transfer or "gamma:2.4")).from_linear(linear)
        path = write_png(tmp_path / f"{transfer}.png", code.numpy(), transfer=transfer)
        cap = load_capture(path)
        assert cap.metadata["transfer"]["curve"] == (transfer or "gamma:2.4")
        assert torch.allclose(cap.linear()[0], linear, atol=0.01, rtol=0.03), transfer
    cap = load_capture(tmp_path / "srgb.png", params=CaptureParams(transfer="linear"))
    assert cap.metadata["transfer"] == {"curve": "linear", "source": "params", "bit_depth": 8, "primaries": "bt709"}
    from PIL import Image

    Image.fromarray((SRGB.from_linear(linear).numpy() * 255).round().astype("uint8")).save(tmp_path / "plain.png")
    cap = load_capture(tmp_path / "plain.png")  # a file that says nothing: sRGB
    assert cap.metadata["transfer"]["curve"] == "srgb" and "default" in cap.metadata["transfer"]["source"]
    assert torch.allclose(cap.linear()[0], linear, atol=0.01, rtol=0.03)


@pytest.mark.slow
def test_an_hlg_clip_end_to_end_keeps_the_lamp_its_8_bit_twin_clips(tmp_path):
    """The same static room (a wall and a lamp 9x brighter) as a 10-bit HLG HEVC clip and as its
    8-bit sRGB twin exposed for the wall: both jobs succeed, the HLG job records its curve, and its
    env map holds the lamp's level over the wall (9x) closer than the twin's, whose clipped frames
    leave the level to the clip rule's guess."""
    from core.engine import run_job
    from core.engine.params import JobParams
    from core.fields.stored.artefact import LightFieldArtefact
    from core.io import write_video

    scene = _hdr_room(T=3)
    hlg_path = write_video(tmp_path / "hlg.mp4", parse_transfer("hlg").from_linear(scene).numpy(), fps=5.0,
                           transfer="hlg", bit_depth=10, codec="libx265")
    sdr_path = write_video(tmp_path / "sdr.mp4", SRGB.from_linear(scene / 0.3).numpy(), fps=5.0, transfer="srgb")
    ratios = {}
    for name, path in (("hlg", hlg_path), ("sdr", sdr_path)):
        params = JobParams.model_validate({"intrinsics": {"hfov_deg": 60.0}, "tracking": "off"})
        run_job(path, None, params, tmp_path / name, overrides={"distill.iterations": 60})
        art = LightFieldArtefact.load(tmp_path / name)
        assert art.meta["capture"]["metadata"]["transfer"]["curve"] == ("hlg" if name == "hlg" else "srgb")
        assert art.meta["quality"]["grade"] is not None
        d = torch.tensor([[0.0, 0.0, -1.0], [-0.5, 0.35, -0.79]])  # the lamp (view centre), the wall
        rad = art.radiance(torch.zeros(2, 3), None, d / d.norm(dim=-1, keepdim=True)).mean(-1)
        assert torch.isfinite(rad).all() and (rad > 0).all()
        ratios[name] = float(rad[0] / rad[1])
    error = {name: abs(math.log(r / 9.0)) for name, r in ratios.items()}
    assert error["hlg"] < math.log(1.5) and error["hlg"] < error["sdr"], ratios
