"""JobParams / CaptureParams: the schema shared by `lightfield estimate --params` and the service."""
import json

import pytest
import torch
from pydantic import ValidationError

from core.engine.config import PRESETS, preset
from core.engine.params import CaptureParams, IntrinsicsParams, JobParams, parse_job_params


def test_defaults_are_the_documented_ones():
    p = JobParams()
    assert (p.preset, p.prior, p.temporal, p.field, p.seed) == ("draft", "reprojection", "auto", None, 0)


@pytest.mark.parametrize(
    "data, field",
    [
        ({"intrinsics": {"fx": 100, "fy": 100, "cx": 50}}, "cy"),
        ({"intrinsics": {"fx": float("nan"), "fy": 1, "cx": 1, "cy": 1}}, "fx"),
        ({"intrinsics": {"fx": -1, "fy": 1, "cx": 1, "cy": 1}}, "fx"),
        ({"intrinsics": {"hfov_deg": 180}}, "hfov_deg"),
        ({"intrinsics": {"hfov_deg": 60, "fx": 1, "fy": 1, "cx": 1, "cy": 1}}, "not both"),
        ({"poses": [[1.0] * 15]}, "poses[0]"),
        ({"poses": [[float("inf")] + [0.0] * 15]}, "non-finite"),
        ({"fps": 0}, "fps"),
        ({"fps": 241}, "fps"),
        ({"max_frames": 0}, "max_frames"),
        ({"preset": "fast"}, "preset"),
        ({"prior": "oracle"}, "prior"),
        ({"temporal": "maybe"}, "temporal"),
        ({"field": "nerf"}, "field"),
        ({"colour": 1}, "colour"),  # extra='forbid'
    ],
)
def test_bad_params_name_the_field(data, field):
    with pytest.raises(ValidationError) as exc:
        JobParams.model_validate(data)
    assert field in str(exc.value)


def test_parse_json_string_file_and_overrides(tmp_path):
    text = json.dumps({"intrinsics": {"hfov_deg": 50}, "fps": 10, "preset": "standard"})
    f = tmp_path / "p.json"
    f.write_text(text)
    for src in (text, str(f)):
        p = parse_job_params(src, preset=None, temporal="off")
        assert p.intrinsics == IntrinsicsParams(hfov_deg=50) and p.fps == 10
        assert p.preset == "standard"  # None override keeps the JSON's value
        assert p.temporal == "off"
    with pytest.raises(ValueError, match="--params"):
        parse_job_params("{not json")


def test_capture_params_are_a_subset_of_job_params():
    assert set(CaptureParams.model_fields) <= set(JobParams.model_fields)


def test_uniform_exposure_ablation_covers_the_range_and_repeats_per_step():
    sweep = preset("draft")
    uniform = sweep.model_copy(update={"ev_schedule": "uniform"})
    evs = [uniform.ev_at(s) for s in range(200)]
    assert all(sweep.ev_min <= e <= 0.0 for e in evs)
    assert min(evs) < 0.8 * sweep.ev_min and max(evs) > 0.2 * sweep.ev_min  # spread, not a sweep
    assert any(b > a for a, b in zip(evs, evs[1:]))  # not monotone like the sweep
    assert evs == [uniform.ev_at(s) for s in range(200)]  # a resumed run sees the same exposures


def test_presets_schedules():
    for name, cfg in PRESETS.items():
        assert cfg.ev_at(0) == 0.0
        assert cfg.ev_at(cfg.iterations - 1) == pytest.approx(cfg.ev_min)
        if cfg.tau_schedule == "anneal":
            assert cfg.tau_min_at(0) == 1.0 and cfg.tau_min_at(cfg.iterations - 1) == 0.0
        else:  # the authors' decay_t_min: from t_max down to the 0.02 floor at half the run
            assert cfg.tau_min_at(0) == cfg.tau_max and cfg.tau_min_at(cfg.iterations // 2) == 0.02
        lrs = [cfg.lr_at(s) for s in range(cfg.iterations)]
        peak = max(lrs)
        assert peak == pytest.approx(cfg.lr, rel=1e-6)
        assert lrs[-1] < 0.2 * peak and lrs[0] < peak  # warm-up then decay
    assert preset("paper").field_kind == "mlp" and preset("paper").n_probes == 9
    assert preset("paper").guidance_scale == 12.5 and preset("paper").ev_min == -5
    assert [preset("paper").steps_for_tau(t) for t in (0.0, 0.05, 0.5, 1.0)] == [1, 1, 5, 10]
    with pytest.raises(ValidationError):
        preset("draft", iterations=0)
    with pytest.raises(ValueError, match="unknown preset"):
        preset("turbo")


def test_seed_preset_is_the_authors_loop():
    s = preset("seed")
    assert [s.ev_at(i) for i in range(s.iterations)] == [0.0] * s.iterations  # EV fixed at 0
    assert s.iterations == 20 and s.guidance_scale == 12.5 and s.field_t_freqs == 6 and s.time_normalisation_frames == 30
    assert s.perceptual_net == "vgg" and s.perceptual_weight == 1.0 and s.l2_weight == pytest.approx(0.2)
    assert s.lr_at(s.iterations - 1) == pytest.approx(2e-4, rel=0.2)


def test_time_is_normalised_for_30_frames_with_the_seed_preset():
    from core.engine.distill import build_field_config, normalised_time
    from core.fields import SceneBounds

    b = SceneBounds((0, 0, 0), (1, 1, 1), 0.0, 99 / 30.0)  # a 100-frame clip at 30 fps
    nb = normalised_time(b, preset("seed"), 30.0)
    assert nb.t1 == pytest.approx(29 / 30.0)
    assert float(nb.normalize_t(torch.tensor(29 / 30.0))) == pytest.approx(1.0)  # frame 29 -> +1, as 2 f / 29 - 1
    assert normalised_time(b, preset("paper"), 30.0) == b
    assert build_field_config(preset("seed"), "mlp", True).mlp.t_freqs == 6
