"""The optional learned depth estimator: loads only complete local safetensors directories,
turns relative disparity into positive planar depth by the documented rule, and feeds
load_capture / run_job when LIGHTFIELD_DEPTH_MODEL is set."""
import json
from pathlib import Path

import pytest
import torch
from hypothesis import given, settings, strategies as st

from core.camera import Intrinsics
from core.capture.base import CaptureError
from core.capture.depth import assumed_box_depth
from core.capture.depth_model import disparity_to_depth, load_depth_estimator
from core.capture.load import DEPTH_MODEL_ENV
from core.capture.prepare import load_prepared_capture

H, W = 24, 36


def build_tiny_dpt(out_dir: Path) -> Path:
    """A randomly initialised ~30k-parameter DPT saved like a hub checkpoint (safetensors +
    preprocessor config). A large init range makes its output vary over the image."""
    from transformers import DPTConfig, DPTForDepthEstimation, DPTImageProcessor

    torch.manual_seed(0)
    cfg = DPTConfig(hidden_size=16, num_hidden_layers=4, num_attention_heads=2, intermediate_size=32,
                    image_size=32, patch_size=8, backbone_out_indices=[0, 1, 2, 3],
                    neck_hidden_sizes=[8, 8, 8, 8], fusion_hidden_size=8, initializer_range=0.5)
    DPTForDepthEstimation(cfg).save_pretrained(out_dir, safe_serialization=True)
    DPTImageProcessor(size={"height": 32, "width": 32}, keep_aspect_ratio=False).save_pretrained(out_dir)
    return out_dir


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory) -> Path:
    return build_tiny_dpt(tmp_path_factory.mktemp("depth") / "tiny-dpt")


def frames(t=2, seed=0):
    return torch.rand(t, H, W, 3, generator=torch.Generator().manual_seed(seed))


# ---------------------------------------------------------------------------------------
# Conversion rule (analytic)
# ---------------------------------------------------------------------------------------
@settings(max_examples=25, deadline=None)
@given(scale=st.floats(1e-6, 1e6), hfov=st.floats(40, 120))
def test_a_scaled_disparity_of_the_box_room_is_converted_back_to_the_box_room(scale, hfov):
    box = assumed_box_depth(Intrinsics.from_hfov(W, H, hfov))
    pred = (scale / box.double())[None].expand(2, H, W)
    assert torch.allclose(disparity_to_depth(pred, box), box.expand(2, H, W), rtol=1e-4)


def test_median_matches_the_box_room_and_nearer_means_larger_disparity():
    box = assumed_box_depth(Intrinsics.from_hfov(W, H, 90))
    pred = torch.linspace(0, 1e6, H * W - 1)  # odd count: the median is one of the values
    pred = torch.cat([pred, torch.tensor([float("nan")])]).reshape(1, H, W)
    d = disparity_to_depth(pred, box)[0].flatten()
    assert torch.isfinite(d).all() and (d > 0).all()
    assert float(d[:-1].median()) == pytest.approx(float(box.median()), rel=1e-5)
    m = float(box.median())
    assert d.max() <= 20 * m * (1 + 1e-6) and d.min() >= m / 20 * (1 - 1e-6)  # zero disparity: far, not inf
    assert (d[1:-1] <= d[:-2] * (1 + 1e-6)).all()  # disparity increases -> depth decreases


@pytest.mark.parametrize("value", [0.0, -3.0, float("nan")])
def test_a_frame_without_positive_disparity_falls_back_to_the_box_median(value):
    box = assumed_box_depth(Intrinsics.from_hfov(W, H, 60))
    d = disparity_to_depth(torch.full((2, H, W), value), box)
    assert torch.allclose(d, torch.full_like(d, float(box.median())))


# ---------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------
def test_loaded_estimator_returns_positive_finite_depth_at_frame_size(tiny_dir):
    est = load_depth_estimator(tiny_dir, batch_size=2)
    assert not est.metric and est.depth_source == "estimated:tiny-dpt (relative, scale arbitrary)"
    f = frames(t=3)
    d = est(f)
    assert d.shape == (3, H, W) and d.dtype == torch.float32
    assert torch.isfinite(d).all() and (d > 0).all()
    assert float(d[0].std()) > 0  # the model's layout, not a constant
    # batching does not change the result
    assert torch.allclose(load_depth_estimator(tiny_dir, batch_size=1)(f), d, rtol=1e-4)


@pytest.mark.parametrize("bad", ["Intel/dpt-large", "depth-anything/Depth-Anything-V2-Small-hf"])
def test_a_hub_id_is_refused_without_downloading(bad, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(CaptureError, match="hub id") as info:
        load_depth_estimator(bad)
    assert info.value.field == "depth"


def test_missing_or_incomplete_or_pickled_directories_are_refused(tiny_dir, tmp_path):
    with pytest.raises(CaptureError, match="not an existing local directory"):
        load_depth_estimator(tmp_path / "nope")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(CaptureError, match="config.json"):
        load_depth_estimator(empty)
    pickled = tmp_path / "pickled"
    pickled.mkdir()
    for name in ("config.json", "preprocessor_config.json"):
        (pickled / name).write_text((tiny_dir / name).read_text())
    (pickled / "pytorch_model.bin").write_bytes(b"not loaded")
    with pytest.raises(CaptureError, match="pickled") as info:
        load_depth_estimator(pickled)
    assert info.value.field == "depth"


def test_a_corrupt_config_is_a_capture_error(tiny_dir, tmp_path):
    broken = tmp_path / "broken"
    broken.mkdir()
    for p in tiny_dir.iterdir():
        (broken / p.name).write_bytes(p.read_bytes())
    (broken / "config.json").write_text(json.dumps({"model_type": "no-such-architecture"}))
    with pytest.raises(CaptureError, match="cannot load"):
        load_depth_estimator(broken)


# ---------------------------------------------------------------------------------------
# Wiring into load_capture / run_job
# ---------------------------------------------------------------------------------------
@pytest.fixture()
def image_path(tmp_path):
    from core.io import write_png

    write_png(tmp_path / "in.png", frames(t=1, seed=3)[0].numpy())
    return tmp_path / "in.png"


def test_load_capture_uses_the_model_when_the_env_var_is_set(tiny_dir, image_path, monkeypatch):
    monkeypatch.setenv(DEPTH_MODEL_ENV, str(tiny_dir))
    with pytest.warns(UserWarning, match="estimated"):
        cap = load_prepared_capture(image_path)
    assert cap.depth_source.startswith("estimated:tiny-dpt") and "scale arbitrary" in cap.depth_source
    assert any(DEPTH_MODEL_ENV in w for w in cap.warnings)
    assert torch.isfinite(cap.depth).all() and (cap.depth > 0).all()
    assert not torch.allclose(cap.depth[0], assumed_box_depth(cap.intrinsics))


def test_a_given_depth_file_wins_over_the_model(tiny_dir, image_path, monkeypatch, tmp_path):
    import numpy as np

    np.save(tmp_path / "d.npy", np.full((H, W), 2.0, np.float32))
    monkeypatch.setenv(DEPTH_MODEL_ENV, str(tmp_path / "does-not-exist"))  # never read
    cap = load_prepared_capture(image_path, tmp_path / "d.npy")
    assert cap.depth_source == "file:d.npy" and torch.all(cap.depth == 2.0)


def test_a_bad_env_var_fails_the_load_with_a_depth_error(image_path, monkeypatch, tmp_path):
    monkeypatch.setenv(DEPTH_MODEL_ENV, str(tmp_path / "nope"))
    with pytest.raises(CaptureError) as info:
        load_prepared_capture(image_path)
    assert info.value.field == "depth" and DEPTH_MODEL_ENV in str(info.value)


def test_the_upload_check_never_runs_the_model(image_path, monkeypatch, tmp_path):
    """The service's upload check (core.capture.probe) reads headers only: the model runs in
    the worker, not in the API process (a bad directory would fail if it were read)."""
    from core.capture.probe import probe_capture

    monkeypatch.setenv(DEPTH_MODEL_ENV, str(tmp_path / "nope"))
    assert probe_capture(image_path).frames == 1


def test_estimated_depth_feeds_run_job(tiny_dir, image_path, monkeypatch, tmp_path):
    from core.engine import run_job
    from core.engine.params import JobParams
    from core.engine.presets import preset

    monkeypatch.setenv(DEPTH_MODEL_ENV, str(tiny_dir))
    cfg = preset("draft").with_overrides(
        {"distill": dict(work_height=H, checkpoint_every=1000, warmup_steps=2, iterations=4)}
    )
    with pytest.warns(UserWarning):
        out = run_job(image_path, None, JobParams(seed=0), tmp_path / "art", config=cfg).path
    meta = json.loads((out / "lightfield.json").read_text())
    assert meta["capture"]["depth_source"].startswith("estimated:tiny-dpt")
    curve = meta["training"]["loss_curve"]
    assert len(curve) == 4 and all(torch.isfinite(torch.tensor(curve)))
