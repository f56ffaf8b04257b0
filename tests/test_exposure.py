"""Exposure: re-exported conventions, DiffusionLight bracket merge, display tone map."""
from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings, strategies as st

import core.conventions as conventions
from core.exposure import (
    DEFAULT_BRACKET_EVS,
    ExposureError,
    display_tonemap,
    expose,
    inverse_tonemap,
    luminance,
    merge_brackets,
    to_uint8,
    tonemap,
)


def test_reexports_are_the_conventions_functions():
    assert tonemap is conventions.tonemap
    assert inverse_tonemap is conventions.inverse_tonemap
    assert expose is conventions.expose


def known_hdr(n=4096, seed=0) -> torch.Tensor:
    """Grey-ish highlights up to 2^5 above white, coloured mid-tones, deep shadows."""
    g = torch.Generator().manual_seed(seed)
    log2_level = torch.empty(n).uniform_(-6.0, 5.0, generator=g)
    tint = torch.empty(n, 3).uniform_(0.6, 1.0, generator=g)
    tint = torch.where((log2_level > -0.2)[:, None], torch.ones_like(tint), tint)  # highlights are grey
    return (2.0**log2_level)[:, None] * tint


def brackets(hdr, evs=DEFAULT_BRACKET_EVS, bits=None):
    out = []
    for ev in evs:
        ldr = tonemap(hdr, ev)
        if bits:
            levels = 2**bits - 1
            ldr = torch.round(ldr * levels) / levels
        out.append(ldr)
    return out


def test_merge_recovers_known_hdr_from_three_brackets():
    hdr = known_hdr()
    assert float(hdr.max()) > 25.0
    merged = merge_brackets(brackets(hdr))
    assert torch.allclose(merged, hdr, rtol=1e-3, atol=1e-6)


def test_merge_recovers_luminance_from_8bit_brackets_within_a_few_percent():
    hdr = known_hdr(seed=1)
    merged = merge_brackets(brackets(hdr, bits=8))
    # 8-bit steps of the brightest usable bracket bound the error for non-dark pixels
    bright_enough = luminance(hdr) > 2.0**-4
    rel = (luminance(merged) - luminance(hdr)).abs() / luminance(hdr)
    assert float(rel[bright_enough].max()) < 0.05


def test_merge_order_and_custom_evs_do_not_matter():
    hdr = known_hdr(512, seed=2)
    evs = (-4.0, 0.0, -2.0)
    merged = merge_brackets(brackets(hdr, evs), evs)
    assert torch.allclose(merged, hdr.clamp(max=16.0), rtol=1e-3, atol=1e-6)


def test_merge_takes_colour_from_ev0_and_whitens_saturated_colour():
    # a saturated red highlight: EV 0 clips it to white, the merge keeps the luminance only
    hdr = torch.tensor([[4.0, 1.0, 1.0]])  # no channel clips at EV -2.5
    merged = merge_brackets(brackets(hdr))
    assert float(luminance(merged)[0]) == pytest.approx(float(luminance(hdr)[0]), rel=1e-3)
    assert torch.allclose(merged[0], merged[0, :1].expand(3))


def test_merge_handles_black_and_fully_saturated_frames():
    black = merge_brackets([torch.zeros(4, 4, 3)] * 3)
    assert torch.equal(black, torch.zeros(4, 4, 3))
    white = merge_brackets([torch.ones(4, 4, 3)] * 3)
    # every bracket saturated: the darkest bracket's clip level is the best lower bound
    assert torch.allclose(white, torch.full((4, 4, 3), 2.0**5), rtol=1e-4)


def test_merge_rejects_bad_arguments():
    with pytest.raises(ExposureError, match="evs"):
        merge_brackets([torch.zeros(2, 3)] * 2, (0.0, -2.5, -5.0))
    with pytest.raises(ExposureError, match="distinct"):
        merge_brackets([torch.zeros(2, 3)] * 2, (0.0, 0.0))
    with pytest.raises(ExposureError, match="shape"):
        merge_brackets([torch.zeros(2, 3), torch.zeros(3, 3)], (0.0, -1.0))


@settings(max_examples=30, deadline=None)
@given(ev=st.floats(-10.0, 5.0), log_l=st.floats(-6.0, 6.0))
def test_tonemap_round_trip_and_finite_over_extreme_exposure(ev, log_l):
    radiance = torch.tensor([10.0**log_l, 0.0, 1e6])
    ldr = tonemap(radiance, ev)
    assert torch.isfinite(ldr).all() and float(ldr.min()) >= 0 and float(ldr.max()) <= 1
    if 0 < float(ldr[0]) < 1:
        assert float(inverse_tonemap(ldr, ev)[0]) == pytest.approx(10.0**log_l, rel=1e-3)


def test_display_tonemap_maps_percentile_to_max_mapping():
    hdr = torch.linspace(0.0, 100.0, 10001)[:, None].expand(-1, 3).contiguous()
    ldr = display_tonemap(hdr, percentile=50.0, gamma=1.0, max_mapping=0.5)
    assert float(ldr[5000, 0]) == pytest.approx(0.5, abs=1e-3)
    assert float(ldr[2500, 0]) == pytest.approx(0.25, abs=1e-3)
    assert float(ldr.max()) == 1.0


@pytest.mark.parametrize(
    "hdr",
    [
        torch.zeros(8, 8, 3),
        torch.full((8, 8, 3), float("inf")),
        torch.full((8, 8, 3), float("nan")),
        torch.tensor([[0.0, float("inf"), 1e-6], [1e6, float("nan"), -3.0]]),
    ],
)
def test_display_tonemap_is_finite_on_hard_inputs(hdr):
    ldr = display_tonemap(hdr)
    assert torch.isfinite(ldr).all() and float(ldr.min()) >= 0 and float(ldr.max()) <= 1
    assert torch.equal(ldr[hdr == float("inf")], torch.ones_like(ldr[hdr == float("inf")]))
    assert torch.equal(ldr[hdr == 0], torch.zeros_like(ldr[hdr == 0]))


def test_to_uint8():
    out = to_uint8(torch.tensor([-1.0, 0.0, 0.5, 1.0, 2.0, float("nan")]))
    assert out.dtype == torch.uint8
    assert out.tolist() == [0, 0, 128, 255, 255, 0]
