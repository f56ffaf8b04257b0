"""Per-frame exposure metadata (`frame_ev`): an auto-exposure video's frames share one radiance
scale, read as static light, recover clipped sources from darker frames, and every consumer
(prior, ball loop, preview, checkpoints) sees the frame as the camera took it."""
import json
import shutil
import warnings

import numpy as np
import pytest
import torch

from core.capture.autoexposure import with_estimated_exposure
from core.capture.base import CaptureError
from core.capture.load import capture_from_arrays
from core.capture.params import CaptureParams
from core.capture.prepare import load_prepared_capture
from core.capture.temporal import AUTO_EXPOSURE_HINT, decide_temporal
from core.conventions import tonemap
from core.engine.checkpoints import fingerprint
from core.engine.distill import distill
from core.engine.presets import preset
from core.exposure import luminance
from core.priors.known import KnownRadiancePrior
from core.priors.reprojection import linear_frames

H, W = 36, 48
EVS = [0.0, 0.6, -1.0, -3.0]  # an auto-exposure's course, the last frame 3 stops darker


def room_hdr() -> torch.Tensor:
    """[H, W, 3] a smooth room in linear units with a lamp 6x brighter than white at ev 0."""
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    base = 0.05 + 0.25 * xx[..., None] * torch.tensor([1.0, 0.9, 0.8]) + 0.1 * yy[..., None]
    lamp = ((yy - 0.3) ** 2 + (xx - 0.7) ** 2 < 0.004)[..., None] * torch.tensor([6.0, 5.4, 4.5])
    return base + lamp


def exposed_clip(evs=EVS) -> torch.Tensor:
    """The same room taken at each ev: 8-bit LDR frames [T, H, W, 3]."""
    hdr = room_hdr()
    return torch.stack([torch.round(tonemap(hdr, ev) * 255) / 255 for ev in evs])


def test_stated_exposures_put_the_frames_on_one_radiance_scale():
    frames = exposed_clip()
    cap = capture_from_arrays(frames, frame_ev=EVS)
    lin = cap.linear()
    truth = room_hdr()
    unclipped = (frames.amax(-1) < 0.98).all(0)
    rel = (luminance(lin) / luminance(truth).clamp_min(1e-6))[:, unclipped]
    assert float((rel - 1).abs().median()) < 0.02  # every frame reads the room's own radiance
    unstated = capture_from_arrays(frames).linear()
    ratio = float(luminance(unstated[3])[unclipped].median() / luminance(unstated[0])[unclipped].median())
    assert ratio == pytest.approx(2.0**-3, rel=0.05)  # without them the last frame reads 8x darker


def test_the_lamp_clipped_in_the_bright_frame_is_read_from_the_dark_one():
    frames = exposed_clip()
    lamp = room_hdr()[..., 0] > 3.0
    assert bool((frames[0][lamp] >= 0.99).all()) and bool((frames[3][lamp] < 0.99).all())
    cap = capture_from_arrays(frames, frame_ev=EVS)
    lin = linear_frames(cap, lighting_changes=False)  # a static camera under static light
    got = float(luminance(lin[0])[lamp].mean())
    want = float(luminance(room_hdr())[lamp].mean())
    assert got == pytest.approx(want, rel=0.05)  # not the clip rule's guess: the darker frame's reading
    for t in range(len(EVS)):  # and every frame reads the lamp at the same radiance
        assert float(luminance(lin[t])[lamp].mean()) == pytest.approx(want, rel=0.05)


def test_auto_exposure_reads_as_static_light_only_when_stated():
    evs = [0.0] * 5 + [-0.2, -0.5, -0.8, -1.0, -1.0]  # the exposure settles a stop lower
    frames = exposed_clip(evs)
    assert decide_temporal(capture_from_arrays(frames)).uses_time  # indistinguishable from a dimmer
    decision = decide_temporal(capture_from_arrays(frames, frame_ev=evs))
    assert not decision.uses_time and decision.statistic < 0.3 * decision.threshold


@pytest.mark.parametrize(
    "bad, message", [([0.0, 1.0], "2 exposures for 4 frames"), ([0.0, 0.0, float("nan"), 0.0], "finite")]
)
def test_bad_exposures_name_their_input(bad, message):
    with pytest.raises(CaptureError, match=message) as info:
        capture_from_arrays(exposed_clip(), frame_ev=bad)
    assert info.value.field == "frame_ev"


def test_the_schema_refuses_exposures_out_of_range():
    with pytest.raises(ValueError, match="frame_ev"):
        CaptureParams(frame_ev=[30.0])
    with pytest.raises(ValueError, match="frame_ev"):
        CaptureParams(frame_ev=[])


def test_the_ball_loop_shows_the_prior_each_frame_as_the_camera_took_it():
    frames = exposed_clip()
    cap = capture_from_arrays(frames, frame_ev=EVS)
    seen = []

    class Recording(KnownRadiancePrior):
        def __call__(self, request):
            seen.append((request.probes.frame_index, request.ev, request.sweep_ev, request.image.clone(),
                         request.ball_masks.sum(0).clone()))
            return super().__call__(request)

    prior = Recording(lambda x, t, d: torch.full((x.shape[0], 3), 0.3))
    cfg = preset("draft").with_overrides({"distill": {"work_height": H, "iterations": 6, "warmup_steps": 2,
                                                      "supervision": "balls", "ev_min": 0.0, "checkpoint_every": 1000}})
    distill(cap, prior, cfg, uses_time=False, seed=0)
    assert len({ev for _, ev, *_ in seen}) >= 2  # frames of different exposures were composited
    for i, ev, sweep, image, cover in seen:
        assert ev == pytest.approx(EVS[i]) and sweep == pytest.approx(0.0)
        outside = cover < 1e-6
        assert torch.allclose(image.permute(1, 2, 0)[outside], frames[i][outside], atol=2e-3)  # the frame itself


def test_checkpoints_of_other_stated_exposures_do_not_resume():
    frames = exposed_clip()
    cfg = preset("draft")
    prior = KnownRadiancePrior(lambda x, t, d: torch.ones(x.shape[0], 3))
    a = fingerprint(capture_from_arrays(frames), cfg.distill, cfg.field, 0, prior)
    b = fingerprint(capture_from_arrays(frames, frame_ev=EVS), cfg.distill, cfg.field, 0, prior)
    assert a != b


def test_the_preview_keeps_each_frames_exposure(tmp_path):
    from jobs.capture_preview import preview_from_capture, save_preview
    from service.stored_preview import load_preview

    cap = capture_from_arrays(exposed_clip(), torch.full((4, H, W), 2.0), frame_ev=EVS)
    preview = preview_from_capture(cap, max_frames=2)  # frames 0 and 3
    save_preview(preview, tmp_path)
    stored = load_preview(tmp_path)
    assert [stored.frame_ev(i) for i in range(stored.num_frames)] == pytest.approx([EVS[0], EVS[3]])
    save_preview(preview_from_capture(capture_from_arrays(exposed_clip())), tmp_path / "plain")
    assert load_preview(tmp_path / "plain").frame_ev(1) == 0.0


def test_a_simulated_auto_exposure_pan_states_its_exposures(tmp_path):
    from core.sim.capture import write_capture
    from core.sim.suites import suite

    scene = suite("auto-exposure").model_copy(update={"resolution": (96, 72), "probes": []})
    write_capture(scene, tmp_path / "stated", video=False)
    doc = json.loads((tmp_path / "stated" / "capture.json").read_text())
    assert doc["frame_ev"] == doc["sensor_frame_ev"] and max(doc["frame_ev"]) - min(doc["frame_ev"]) > 0.8
    shutil.copytree(tmp_path / "stated", tmp_path / "plain")
    doc.pop("frame_ev")
    (tmp_path / "plain" / "capture.json").write_text(json.dumps(doc))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        stated = load_prepared_capture(tmp_path / "stated")
        plain = load_prepared_capture(tmp_path / "plain", params=CaptureParams(frame_ev="locked"))
        given = load_prepared_capture(tmp_path / "plain", params=CaptureParams(frame_ev=doc["sensor_frame_ev"]))
        detected = load_prepared_capture(tmp_path / "plain")  # frame_ev unset: a moving camera is taken to auto-expose
    assert stated.metadata["exposure_source"] == "capture.json" and given.metadata["exposure_source"] == "params"
    assert np.allclose(stated.frame_ev.numpy(), given.frame_ev.numpy())
    assert not decide_temporal(stated).uses_time  # a pan under static light
    assert decide_temporal(plain).uses_time  # said to be locked, the exposure reads as light
    assert AUTO_EXPOSURE_HINT in decide_temporal(plain).reason  # and the artefact says what to send
    assert detected.metadata["exposure_estimate"]["applied"]
    assert not decide_temporal(detected).uses_time
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        estimated = load_prepared_capture(tmp_path / "plain", params=CaptureParams(frame_ev="estimate"))
    truth = np.array(doc["sensor_frame_ev"]) - doc["sensor_frame_ev"][0]
    assert np.abs(estimated.frame_ev.numpy() - truth).max() < 0.05  # chained through the pan's poses
    assert estimated.metadata["exposure_source"].startswith("estimated")
    assert not decide_temporal(estimated).uses_time


def test_an_estimated_exposure_follows_a_static_cameras_auto_exposure():
    evs = [0.0, 0.0, 0.3, 0.5, -0.4, -1.0, -1.0, -1.2]
    cap = with_estimated_exposure(capture_from_arrays(exposed_clip(evs)), CaptureParams(frame_ev="estimate"))
    assert np.abs(cap.frame_ev.numpy() - np.array(evs)).max() < 0.05
    assert not decide_temporal(cap).uses_time
    assert with_estimated_exposure(
        capture_from_arrays(exposed_clip([0.0])), CaptureParams(frame_ev="estimate")
    ).frame_ev.tolist() == [0.0]
    static = with_estimated_exposure(capture_from_arrays(exposed_clip(evs)), CaptureParams())
    assert static.stated_ev is None  # unset: a static camera's exposure moves only with the light, left alone


def test_a_light_switching_off_in_part_of_the_view_is_not_taken_for_exposure():
    evs = [0.0] * 4 + [-0.5] * 4
    frames = exposed_clip(evs)
    frames[6:, :, : W // 6] *= 0.4  # a lamp-lit corner goes dark in the last frames
    cap = with_estimated_exposure(capture_from_arrays(frames), CaptureParams(frame_ev="estimate"))
    assert np.abs(cap.frame_ev.numpy() - np.array(evs)).max() < 0.05
    assert decide_temporal(cap).uses_time  # the switch is still a change of light


def test_a_moving_cameras_exposure_is_estimated_unless_said_to_be_locked():
    """Unset, a moving camera's whole-view brightness course is its exposure: an auto-exposure
    under steady light is recovered (a fast one and a lagging one that meters the frame
    before). The same whole-view change under a locked exposure (the room dimmed to half
    mid-pan) cannot be told from it by the frames alone: "locked" keeps it a change of light."""
    from core.sim.panorama_room import ldr_clip
    from core.sim.sensor import metered_evs

    hdr, depth, k, poses = _bundled_pan()
    for speed, delay in ((1.0, 0), (0.25, 0), (0.5, 1)):
        metered = metered_evs(list(hdr), speed=speed)
        evs = [metered[max(i - delay, 0)] for i in range(len(metered))]
        auto = torch.stack([torch.round(tonemap(h, ev) * 255) / 255 for h, ev in zip(hdr, evs)])
        found = with_estimated_exposure(
            capture_from_arrays(auto, depth, intrinsics=k, poses=poses, fps=10), CaptureParams()
        )
        assert found.metadata["exposure_estimate"]["applied"], (speed, delay)
        assert np.abs(found.frame_ev.numpy() - (np.array(evs) - evs[0])).max() < 0.1, (speed, delay)
        assert not decide_temporal(found).uses_time
        assert with_estimated_exposure(capture_from_arrays(auto, depth, intrinsics=k, poses=poses, fps=10),
                                       CaptureParams(frame_ev="locked")).stated_ev is None
    dimmed = hdr * torch.tensor([1.0] * 10 + [0.5] * 10)[:, None, None, None]
    plain = capture_from_arrays(ldr_clip(dimmed), depth, intrinsics=k, poses=poses, fps=10)
    locked = with_estimated_exposure(plain, CaptureParams(frame_ev="locked"))
    assert locked.stated_ev is None and decide_temporal(locked).uses_time
    assert with_estimated_exposure(plain, CaptureParams()).metadata["exposure_estimate"]["applied"]


def test_a_steady_pan_needs_no_exposure():
    """A course under the temporal decision's floor is left alone (nothing to correct)."""
    from core.sim.panorama_room import ldr_clip

    hdr, depth, k, poses = _bundled_pan()
    steady = with_estimated_exposure(capture_from_arrays(ldr_clip(hdr), depth, intrinsics=k, poses=poses, fps=10),
                                     CaptureParams())
    assert steady.stated_ev is None and not steady.metadata["exposure_estimate"]["applied"]


def _bundled_pan(frames: int = 20):
    from pathlib import Path

    from core.camera import Camera, Intrinsics
    from core.sim.panorama_room import PanoramaRoom, load_panorama, render_clip
    from core.sim.state import pose_from_yaw_pitch
    from core.tracking.room import assumed_room

    pano = load_panorama(Path(__file__).resolve().parents[1] / "assets" / "sample_panorama.hdr", 128)
    k = Intrinsics.from_hfov(96, 72, 60.0)
    poses = torch.stack([pose_from_yaw_pitch((0, 0, 0), 60 * i / (frames - 1), 0) for i in range(frames)])
    _, depth, hdr = render_clip(
        PanoramaRoom(pano, assumed_room(), torch.zeros(3)), [Camera(k, p) for p in poses], supersample=1
    )
    return hdr * (0.18 / float(luminance(hdr).mean())), depth, k, poses


def _photo_with_exposure(path, ldr: np.ndarray, seconds: float | None, iso: float | None, f_number: float | None):
    """A PNG whose EXIF states how it was exposed (the tags a phone writes in auto mode)."""
    from fractions import Fraction

    from PIL import ExifTags, Image
    from PIL.TiffImagePlugin import IFDRational

    def rational(x: float) -> IFDRational:
        f = Fraction(x).limit_denominator(100000)
        return IFDRational(f.numerator, f.denominator)

    exif = Image.Exif()
    sub = {}
    if seconds is not None:
        sub[ExifTags.Base.ExposureTime] = rational(seconds)
    if iso is not None:
        sub[ExifTags.Base.ISOSpeedRatings] = int(iso)
    if f_number is not None:
        sub[ExifTags.Base.FNumber] = rational(f_number)
    exif[ExifTags.IFD.Exif] = sub
    Image.fromarray((np.clip(ldr, 0, 1) * 255).round().astype(np.uint8)).save(path, exif=exif)


def test_a_photo_set_in_auto_mode_takes_each_photos_exposure_from_its_exif(tmp_path):
    """Photos of one spot taken in auto mode (shutter and ISO vary): the nerfstudio loader reads
    each photo's EXIF exposure, so the frames land on one radiance scale with no parameter."""
    from capture_fixtures import PANORAMA, write_nerfstudio
    from core.camera import Camera, Intrinsics
    from core.sim.panorama_room import PanoramaRoom, load_panorama, render_clip
    from core.sim.state import pose_from_yaw_pitch
    from core.tracking.room import assumed_room

    poses = [pose_from_yaw_pitch((0, 0, 0), 0.0, 0.0)] * 3
    intr = Intrinsics.from_hfov(64, 48, 60.0)
    room = PanoramaRoom(load_panorama(PANORAMA, 128), assumed_room(), torch.zeros(3))
    _, depth, hdr = render_clip(room, [Camera(intr, p) for p in poses], supersample=1)
    hdr = hdr * (0.18 / float(luminance(hdr).mean()))
    shots = [(1 / 60, 100, 0.0), (1 / 120, 100, -1.0), (1 / 60, 200, 1.0)]  # (seconds, ISO, stops vs the first)
    root = write_nerfstudio(tmp_path / "set", np.zeros((3, 48, 64, 3)), depth.numpy(), intr, [p.numpy() for p in poses])
    for i, (sec, iso, ev) in enumerate(shots):
        _photo_with_exposure(root / f"images/frame_{i:05d}.png", tonemap(hdr[i], ev).numpy(), sec, iso, 1.8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cap = load_prepared_capture(root)
    assert cap.frame_ev.tolist() == pytest.approx([0.0, -1.0, 1.0], abs=1e-3)
    assert "EXIF" in cap.metadata["exposure_source"]
    lin = cap.linear()
    ok = (cap.frames < 0.95).all(-1).all(0) & (cap.frames > 0.1).all(-1).all(0)  # unclipped, above the 8-bit floor
    assert int(ok.sum()) > 500
    for i in (1, 2):  # one radiance scale: within 8-bit quantisation of frame 0
        assert float((torch.log(lin[i][ok]) - torch.log(lin[0][ok])).abs().median()) < 0.03
    with warnings.catch_warnings():  # "locked" still overrides what the files say
        warnings.simplefilter("ignore")
        assert load_prepared_capture(root, params=CaptureParams(frame_ev="locked")).stated_ev is None


def test_exif_exposures_need_every_photo_to_state_them():
    from core.io.metadata import ImageMetadata, frames_exposure_ev

    a = ImageMetadata(exposure_time_s=1 / 50, iso=100, f_number=2.0)
    b = ImageMetadata(exposure_time_s=1 / 100, iso=400, f_number=2.0)
    assert frames_exposure_ev([a, b]) == pytest.approx([0.0, 1.0])
    assert frames_exposure_ev([a, ImageMetadata(exposure_time_s=1 / 100, iso=None, f_number=2.0)]) is None
    assert frames_exposure_ev([a]) is None  # one photo: nothing to put on a scale
    no_aperture = [ImageMetadata(exposure_time_s=1 / 50, iso=100), ImageMetadata(exposure_time_s=1 / 25, iso=100)]
    assert frames_exposure_ev(no_aperture) == pytest.approx([0.0, 1.0])  # a phone's fixed aperture
    wide = (
        ImageMetadata(exposure_time_s=30.0, iso=100, f_number=2.0),
        ImageMetadata(exposure_time_s=1e-6, iso=50, f_number=22),
    )
    assert frames_exposure_ev(list(wide)) is None  # a spread no camera shoots: a broken file
