"""The time gain (core.fields.components.encodings.TimeGain): a log gain per knot (one, or one per colour
channel) multiplying a field's network, not its emitters, on every evaluation path."""
from __future__ import annotations

import math

import pytest
import torch

from core.fields import FieldConfig, SceneBounds, build_field
from core.fields.components.encodings import LOG_GAIN_LIMIT, TimeGain
from core.fields.kinds.base import EMITTER_PIXEL_SIGMA
from tests.test_fields import assert_paths_agree_and_reload

BOX = SceneBounds((-3.0, -2.0, -3.0), (3.0, 2.0, 3.0), 0.0, 3.0)


def gained_field(knots=4, **kw):
    torch.manual_seed(0)
    return build_field(FieldConfig(kind="mlp", uses_time=True, time_gain_knots=knots, **kw), BOX).eval()


def test_the_gain_scales_the_network_at_its_knots_and_interpolates_between_them():
    field = gained_field(knots=4)  # knots at t = 0, 1, 2, 3 s
    x, d = torch.tensor([[0.5, 0.2, -1.0]]), torch.tensor([[0.0, 0.0, -1.0]])
    with torch.no_grad():
        before = [field(x, torch.tensor([t]), d) for t in (0.0, 1.0, 1.5)]
        field.time_gain.set_gain(torch.tensor([0.0, math.log(0.5), math.log(0.25), 0.0]))
        after = [field(x, torch.tensor([t]), d) for t in (0.0, 1.0, 1.5)]
    assert torch.allclose(after[0], before[0])
    assert torch.allclose(after[1], 0.5 * before[1], rtol=1e-5)
    assert torch.allclose(after[2], math.sqrt(0.125) * before[2], rtol=1e-5)  # linear in the log between knots


def test_every_path_answers_the_same_with_a_gain_and_the_artefact_reloads_it(tmp_path):
    field = gained_field(knots=5, view_detail_heights=(8,), view_anchors=((0.0, 0.0, 0.0),), emitter_count=1,
                         emitter_sigma_floor=EMITTER_PIXEL_SIGMA * math.pi / 8)  # the lobe width `envmaps` gives 8 rows
    field.emitters.set_sources(torch.tensor([[1.0, 1.0, 1.0]]), torch.tensor([0.05]), torch.full((1, 1, 3), 2.0))
    field.time_gain.set_gain(torch.tensor([0.3, -1.0, 2.0, -4.0, 0.0]))
    xs = torch.tensor([[0.1, 0.2, -1.0], [1.0, 0.5, -1.5], [0.0, 0.0, 0.0]])
    maps = assert_paths_agree_and_reload(field, xs, torch.tensor([0.4, 2.9, 1.6]), 8, tmp_path)
    assert torch.isfinite(maps).all()


def test_the_gain_leaves_the_emitters_alone():
    """Emitters carry their own measured time curve: the gain multiplies only the network."""
    field = gained_field(knots=2, emitter_count=1)
    field.emitters.set_sources(torch.tensor([[0.0, 0.0, -2.0]]), torch.tensor([0.05]), torch.full((1, 1, 3), 50.0))
    x, d, t = torch.zeros(1, 3), torch.tensor([[0.0, 0.0, -1.0]]), torch.tensor([0.0])
    with torch.no_grad():
        lobe = field(x, t, d) - field.activate(field.logits(*field.normalize_inputs(x, t, d)), None)
        field.time_gain.set_gain(torch.tensor([-20.0, -20.0]))
        dimmed = field(x, t, d)
    assert torch.allclose(dimmed, lobe, rtol=1e-3)


def test_extreme_gains_stay_finite_within_the_field_range():
    field = gained_field(knots=3)
    lo, hi = field.config.log_radiance_min, field.config.log_radiance_max
    x, d = torch.zeros(2, 3), torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    for g in (1e30, -1e30, float("inf"), float("nan")):
        field.time_gain.set_gain(torch.full((3,), g))
        assert float(field.time_gain.log_gain.abs().max()) <= LOG_GAIN_LIMIT
        with torch.no_grad():
            out = field(x, torch.tensor([0.0, 3.0]), d)
        assert torch.isfinite(out).all() and (out >= math.exp(lo) * 0.999).all() and (out <= math.exp(hi) * 1.001).all()


def test_a_field_without_a_time_input_has_no_gain():
    field = build_field(FieldConfig(kind="mlp", uses_time=False, time_gain_knots=4), BOX)
    assert field.time_gain is None and not any(n.startswith("time_gain") for n, _ in field.named_parameters())


def test_a_gain_of_too_few_knots_is_refused():
    try:
        TimeGain(1)
    except ValueError as e:
        assert "knots >= 2" in str(e)
    else:
        raise AssertionError("TimeGain(1) was accepted")


def test_the_time_variation_penalty_includes_the_gain():
    """A gain that changes between knots is penalised like the codes (distill.time_tv_weight)."""
    field = gained_field(knots=3)
    flat = float(field.time_variation())
    field.time_gain.set_gain(torch.tensor([0.0, 1.0, 1.0]))
    assert float(field.time_variation()) == pytest.approx(flat + 0.5, abs=1e-6)  # mean |step| over 2 steps x 3 channels
