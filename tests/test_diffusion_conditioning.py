"""Pure image-space and embedding helpers of the diffusion prior (no networks; hypothesis)."""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings, strategies as st

from core.priors.diffusion.conditioning import (
    binary_mask_at,
    combine_per_ball,
    depth_to_control,
    latent_mask,
    model_size,
    paste_outside,
    to_unit,
)
from core.priors.diffusion.exposure import exposure_weight, interpolate

EV_MIN = -5.0
depth_values = st.one_of(
    st.floats(min_value=1e-6, max_value=1e6),
    st.sampled_from([float("nan"), float("inf"), float("-inf"), 0.0, -1.0]),
)


@given(st.floats(allow_nan=True, allow_infinity=True))
def test_exposure_weight_is_clamped_to_unit_interval(ev):
    w = float(exposure_weight(ev, EV_MIN))
    assert 0.0 <= w <= 1.0
    if math.isfinite(ev) and EV_MIN <= ev <= 0.0:
        assert math.isclose(w, ev / EV_MIN, rel_tol=1e-6, abs_tol=1e-7)


@given(st.floats(min_value=EV_MIN, max_value=0.0), st.floats(min_value=EV_MIN, max_value=0.0))
def test_exposure_interpolation_is_monotone_between_anchors(a, b):
    at_max, at_min = torch.zeros(1, 4), torch.ones(1, 4)
    za = interpolate(exposure_weight(a, EV_MIN).reshape(1), at_max, at_min)
    zb = interpolate(exposure_weight(b, EV_MIN).reshape(1), at_max, at_min)
    if a <= b:  # darker exposure -> closer to zeta_min
        assert (za >= zb - 1e-6).all()


@settings(max_examples=60, deadline=None)
@given(st.lists(depth_values, min_size=4, max_size=4 * 6).filter(lambda v: len(v) % 4 == 0))
def test_depth_control_is_bounded_and_orders_valid_depths(values):
    depth = torch.tensor(values, dtype=torch.float32).reshape(-1, 4)
    ctl = depth_to_control(depth)
    assert ctl.shape == (3, *depth.shape) and torch.isfinite(ctl).all()
    assert ctl.min() >= 0 and ctl.max() <= 1
    valid = torch.isfinite(depth) & (depth > 0)
    assert torch.equal(ctl[0][~valid], torch.zeros(int((~valid).sum())))
    d, c = depth[valid], ctl[0][valid]
    order = torch.argsort(d)
    assert (c[order][1:] <= c[order][:-1] + 1e-6).all()  # nearer is never darker


@given(st.integers(1, 4000), st.integers(1, 4000), st.sampled_from([16, 64]))
def test_model_size_is_a_positive_multiple(h, w, multiple):
    mh, mw = model_size(h, w, (512, 512), multiple)
    assert mh % multiple == 0 and mw % multiple == 0 and mh >= multiple and mw >= multiple
    assert max(mh, mw) <= 1024  # a thin strip never asks for a huge canvas


@settings(max_examples=40, deadline=None)
@given(st.integers(8, 40), st.integers(8, 40), st.integers(0, 10_000))
def test_conservative_masks_cover_every_ball_pixel(h, w, seed):
    g = torch.Generator().manual_seed(seed)
    coverage = (torch.rand(2, h, w, generator=g) > 0.97).float() * torch.rand(2, h, w, generator=g)
    small = binary_mask_at(coverage, (8, 8))
    # every covered pixel lies in a masked cell of the 8 x 8 grid (cell of pixel r: floor(8 r / h))
    rows = (torch.arange(h) * 8 // h)[:, None].expand(h, w)
    cols = (torch.arange(w) * 8 // w)[None, :].expand(h, w)
    for b in range(2):
        hit = coverage[b] > 0
        assert bool(small[b][rows[hit], cols[hit]].eq(1).all())
    pixels = (torch.rand(1, 1, 16, 16, generator=g) > 0.9).float()
    lat = latent_mask(pixels, 8)
    assert torch.equal(lat, pixels.reshape(1, 1, 2, 8, 2, 8).amax(dim=(3, 5)))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000))
def test_paste_and_combine_keep_uncovered_pixels_exactly(seed):
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(3, 6, 7, generator=g)
    masks = (torch.rand(2, 6, 7, generator=g) > 0.6).float() * torch.rand(2, 6, 7, generator=g)
    generated = torch.rand(2, 3, 6, 7, generator=g)
    cov = masks.sum(0).clamp(max=1)
    out = paste_outside(combine_per_ball(generated, masks), image, cov)
    assert torch.equal(out[:, cov == 0], image[:, cov == 0])
    only_first = (masks[0] > 0) & (masks[1] == 0) & (cov == 1)
    torch.testing.assert_close(out[:, only_first], generated[0][:, only_first])


def test_to_unit_maps_the_vae_range_and_survives_nan():
    x = torch.tensor([-1.0, 0.0, 1.0, 3.0, float("nan"), float("inf"), float("-inf")])
    assert torch.equal(to_unit(x), torch.tensor([0.0, 0.5, 1.0, 1.0, 0.5, 1.0, 0.0]))


def test_prior_device_follows_the_engines_rule(monkeypatch):
    """One device rule (core.device): LIGHTFIELD_DEVICE overrides the prior's argument too, so
    the engine and the diffusion prior never disagree about where work runs."""
    from core.priors.base import PriorError
    from core.priors.diffusion.loading import resolve_device

    monkeypatch.delenv("LIGHTFIELD_DEVICE", raising=False)
    assert resolve_device(None) == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(PriorError, match="device"):
        resolve_device("tpu")
    monkeypatch.setenv("LIGHTFIELD_DEVICE", "cpu")
    assert resolve_device("cuda") == torch.device("cpu")
