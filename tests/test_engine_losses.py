"""Distillation losses: the saturation hinge, masking, SSIM fallback, progress/ETA."""
import pytest
import torch

from core.engine.losses import PerceptualLoss, masked_l2, masked_ssim_loss, perceptual_description
from core.engine.progress import Cancelled, Reporter, StageTimer


def test_masked_l2_hinge_on_saturated_targets():
    target = torch.ones(3, 4, 4)  # clipped: "at least white"
    mask = torch.ones(4, 4)
    assert masked_l2(torch.full((3, 4, 4), 1.7), target, mask) == 0  # brighter than white is fine
    below = masked_l2(torch.full((3, 4, 4), 0.5), target, mask)
    assert below == pytest.approx(0.25)
    # an unsaturated target penalises both directions
    t2 = torch.full((3, 4, 4), 0.5)
    assert masked_l2(torch.full((3, 4, 4), 0.7), t2, mask) == pytest.approx(0.04)
    assert masked_l2(torch.full((3, 4, 4), 0.3), t2, mask) == pytest.approx(0.04)


def test_masked_l2_ignores_unmasked_pixels_and_weights_partial_coverage():
    pred, target = torch.zeros(3, 2, 2), torch.zeros(3, 2, 2)
    pred[:, 0, 0] = 0.5  # an error outside the mask
    mask = torch.tensor([[0.0, 1.0], [1.0, 0.5]])
    assert masked_l2(pred, target, mask) == 0
    pred[:, 1, 1] = 0.4
    assert masked_l2(pred, target, mask) == pytest.approx(0.5 * 0.16 / 2.5)
    assert torch.isfinite(masked_l2(pred, target, torch.zeros(2, 2)))  # empty mask: no NaN


def test_ssim_fallback_zero_for_identical_positive_for_different():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(3, 16, 16, generator=g)
    mask = torch.zeros(16, 16)
    mask[4:12, 4:12] = 1
    assert masked_ssim_loss(a, a, mask) == pytest.approx(0.0, abs=1e-6)
    b = a.clone()
    b[:, 4:12, 4:12] = torch.rand(3, 8, 8, generator=g)
    assert masked_ssim_loss(b, a, mask) > 0.3
    assert PerceptualLoss().kind == "ssim" and perceptual_description()["kind"] == "ssim"


def test_ssim_gradient_is_finite_on_flat_black():
    x = torch.zeros(3, 8, 8, requires_grad=True)
    masked_ssim_loss(x, torch.zeros(3, 8, 8), torch.ones(8, 8)).backward()
    assert torch.isfinite(x.grad).all()


def test_reporter_fractions_eta_and_cancel():
    events, cancel = [], {"now": False}
    rep = Reporter(events.append, lambda: cancel["now"])
    rep.stage("loading", 0.0)
    rep.begin(0)
    for i in range(1, 4):
        rep.step(i, 10, loss=1.0 / i)
    assert [e.iteration for e in events[1:]] == [1, 2, 3]
    assert all(0 <= e.fraction <= 1 for e in events)
    assert events[-1].eta_s is not None and events[-1].eta_s >= 0
    assert events[1].fraction < events[2].fraction < events[3].fraction
    cancel["now"] = True
    with pytest.raises(Cancelled):
        rep.step(4, 10, loss=0.1)


def test_stage_timer_accumulates():
    t = StageTimer()
    for _ in range(3):
        with t("a"):
            pass
    assert t.as_dict()["a"]["calls"] == 3 and t.as_dict()["a"]["seconds"] >= 0
