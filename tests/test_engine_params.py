"""JobParams / CaptureParams: the schema shared by `lightfield estimate --params` and the service."""
import json

import pytest
import torch
from pydantic import ValidationError

from core.capture.params import CaptureParams, IntrinsicsParams
from core.engine.params import JobParams, parse_job_params
from core.engine.presets import PRESETS, preset


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
    sweep = preset("draft").distill
    uniform = sweep.model_copy(update={"ev_schedule": "uniform"})
    evs = [uniform.ev_at(s) for s in range(200)]
    assert all(sweep.ev_min <= e <= 0.0 for e in evs)
    assert min(evs) < 0.8 * sweep.ev_min and max(evs) > 0.2 * sweep.ev_min  # spread, not a sweep
    assert any(b > a for a, b in zip(evs, evs[1:]))  # not monotone like the sweep
    assert evs == [uniform.ev_at(s) for s in range(200)]  # a resumed run sees the same exposures


def test_presets_schedules():
    for engine in PRESETS.values():
        cfg = engine.distill
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
    paper = preset("paper")
    assert paper.field.kind == "mlp" and paper.field.section().width == 256 and paper.distill.n_probes == 9
    assert paper.distill.guidance_scale == 12.5 and paper.distill.ev_min == -5
    assert [paper.distill.steps_for_tau(t) for t in (0.0, 0.05, 0.5, 1.0)] == [1, 1, 5, 10]
    with pytest.raises(ValidationError):
        preset("draft").with_overrides({"distill": {"iterations": 0}})
    with pytest.raises(ValueError, match="unknown preset"):
        preset("turbo")


def test_presets_are_whole_config_trees_and_overrides_stay_typed():
    draft = preset("draft")
    assert draft.field.kind == "mlp" and (draft.field.section().width, draft.field.section().layers) == (96, 4)
    assert draft.field.section("trunk").trunk_width == 96  # a job that picks the trunk gets the draft's size
    assert draft.prior_settings("reprojection")["env_height"] == 24 and draft.prior_settings("diffusion") == {}
    nested = draft.with_overrides({"distill": {"iterations": 7}, "field": {"mlp": {"width": 32}}})
    dotted = draft.with_overrides({"distill.iterations": 7, "field.mlp.width": 32})
    assert nested == dotted and dotted.distill.iterations == 7 and dotted.field.section().width == 32
    assert dotted.distill.work_height == draft.distill.work_height and draft.distill.iterations == 400  # a copy
    assert draft.with_field_kind("grid").field.kind == "grid" and draft.with_field_kind(None) is draft
    with pytest.raises(ValidationError, match="iteratons"):
        draft.with_overrides({"distill.iteratons": 7})
    with pytest.raises(ValidationError, match="env_hieght"):
        draft.with_overrides({"priors.reprojection.env_hieght": 8})


def test_seed_preset_is_the_authors_loop():
    seed = preset("seed")
    s = seed.distill
    assert [s.ev_at(i) for i in range(s.iterations)] == [0.0] * s.iterations  # EV fixed at 0
    assert s.iterations == 20 and s.guidance_scale == 12.5 and s.time_normalisation_frames == 30
    assert s.perceptual_net == "vgg" and s.perceptual_weight == 1.0 and s.l2_weight == pytest.approx(0.2)
    assert s.lr_at(s.iterations - 1) == pytest.approx(2e-4, rel=0.2)
    assert seed.field.section("mlp").t_freqs == 6 and seed.field.section("trunk").t_freqs == 6  # PE degree 6 for time
    assert seed.prior_settings("diffusion")["profile"] == "seed"


def test_the_diffusion_profile_is_the_jobs_else_the_presets_else_the_cards():
    from core.engine.job import job_prior_settings

    def profile(preset_name, job_profile=None):
        params = JobParams(preset=preset_name, prior="diffusion", prior_weights="/w", prior_profile=job_profile)
        settings = job_prior_settings(preset(preset_name), params)
        assert settings["weights"] == "/w"
        return settings.get("profile")

    assert profile("seed") == "seed" and profile("seed", "paper") == "paper"
    assert profile("paper") is None and profile("draft", "diffusionlight") == "diffusionlight"  # None: the card's
    reprojection = JobParams(preset="seed", prior="reprojection", prior_profile="seed")
    assert "profile" not in job_prior_settings(preset("seed"), reprojection)  # only priors that have the setting
    with pytest.raises(ValidationError, match="prior_profile"):
        JobParams(prior="diffusion", prior_profile="authors")


def test_time_is_normalised_for_30_frames_with_the_seed_preset():
    from core.engine.scene import normalised_time
    from core.fields import SceneBounds

    b = SceneBounds((0, 0, 0), (1, 1, 1), 0.0, 99 / 30.0)  # a 100-frame clip at 30 fps
    frames = preset("seed").distill.time_normalisation_frames
    nb = normalised_time(b, frames, 30.0)
    assert nb.t1 == pytest.approx(29 / 30.0)
    assert float(nb.normalize_t(torch.tensor(29 / 30.0))) == pytest.approx(1.0)  # frame 29 -> +1, as 2 f / 29 - 1
    assert normalised_time(b, preset("paper").distill.time_normalisation_frames, 30.0) == b
    assert normalised_time(b, frames, None) == b  # a single image has no frame rate
