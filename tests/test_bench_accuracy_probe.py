"""bench/accuracy_probe.py's helpers: extra held-out probes, bootstrap intervals, the docs' table."""
import pytest
import torch

from bench.accuracy_probe import markdown_table, peak_direction_error
from bench.suite.evaluation import ratio_interval
from bench.suite.simulated import SuiteData, with_extra_probes
from core.sim.render import check_probe
from core.sim.suites import spatial, temporal


def _suite(scene, height=4):
    return SuiteData(
        name=scene.name,
        scene=scene,
        capture_dir=None,
        probes=list(scene.probes),
        gt=torch.ones(len(scene.probes), height, 2 * height, 3),
        global_point=(0.0, 0.0, 0.0),
        global_time=0.0,
    )


@pytest.mark.parametrize("make_scene", [spatial, temporal])
def test_extra_probes_are_in_free_space_and_time_and_reproducible(make_scene):
    scene = make_scene()
    suite = _suite(scene)
    more = with_extra_probes(suite, 5, seed=3)
    extra = more.probes[len(scene.probes):]
    assert len(extra) == 5 and more.gt.shape == (len(scene.probes) + 5, 4, 8, 3)
    assert torch.equal(more.gt[: len(scene.probes)], suite.gt) and torch.isfinite(more.gt).all()
    t_end = (scene.frames - 1) / scene.fps
    for p in extra:
        check_probe(scene, p.x)  # raises outside the room or inside furniture (an L-shaped room's gap too)
        assert 0.0 <= p.t <= t_end
    assert with_extra_probes(suite, 5, seed=3).probes == more.probes
    assert with_extra_probes(suite, 5, seed=4).probes != more.probes
    assert with_extra_probes(suite, 0).probes == suite.probes


def test_ratio_interval_brackets_the_ratio_of_means():
    den = [1.0, 2.0, 3.0, 4.0, 5.0]
    assert ratio_interval([2 * v for v in den], den) == [2.0, 2.0]  # every resample gives 2
    num = [1.5, 1.0, 4.0, 3.0, 6.5]
    lo, hi = ratio_interval(num, den)
    assert lo < sum(num) / sum(den) < hi
    assert ratio_interval(num, den) == [lo, hi]  # seeded


def test_markdown_table_names_the_worst_metric_with_its_interval():
    ratios = {
        "field": {
            "vs_prior": {"diffuse.si_rmse": 1.01, "matte.si_rmse": 0.98, "mirror.si_rmse": 1.0, "matte.nrmse": 1.2},
            "vs_constant": {"diffuse.si_rmse": 0.7, "matte.si_rmse": 0.9},
        },
        "prior": {"vs_constant": {"diffuse.si_rmse": 0.75, "matte.si_rmse": 0.88}},
    }
    report = {"suites": {"temporal": {"probes": [{}] * 12, "ratios": ratios, "cpu_s": {"field": 30.0},
                                      "interval_90": {"field": {"vs_prior": {"matte.nrmse": [1.05, 1.4]}}}}}}
    lines = markdown_table(report).splitlines()
    assert len(lines) == 4
    assert (
        "| temporal | radiance + view (draft) | 12 | 1.20 (matte.nrmse) [1.05, 1.40] | 1.01 | 0.98 | 1.00 | 0.70 | "
        "0.90 | 30.0 |"
        == lines[2]
    )
    assert lines[3].startswith("| temporal | prior (shortcut) | 12 |")


def test_a_field_kind_set_on_the_command_line_is_the_one_trained():
    """`--set field.kind=trunk` must reach the distillation (it was silently replaced by the MLP)."""
    from bench.accuracy_probe import probe_method
    from core.engine.presets import preset

    base = preset("draft").with_overrides({"field.kind": "trunk"})
    assert probe_method("field", base).config(base).field.kind == "trunk"
    assert probe_method("field-balls", base).config(base).distill.supervision == "balls"
    assert probe_method("field-oracle", preset("draft")).prior == "oracle"
    assert probe_method("field", preset("draft")).config(preset("draft")).field.kind == "mlp"


def test_the_prior_row_is_bound_as_the_job_binds_it(tmp_path):
    """The accuracy probe's `prior` row must be the prior the field is distilled from: under
    static lighting a moving camera's requests merge viewpoints (bound as for changing lighting
    it scored a different, on `moving-camera` worse, prior)."""
    import warnings

    from bench.methods import _bound_prior
    from core.engine.presets import preset
    from core.sim.capture import write_capture
    from core.sim.suites import hard, temporal

    merged = {}
    for name, spec in (("hard", hard()), ("temporal", temporal())):
        frames = 4 if name == "hard" else spec.frames
        small = spec.model_copy(update={"frames": frames, "resolution": (96, 72), "probes": []})
        write_capture(small, tmp_path / name, envmap_height=8, video=False)
        suite = SuiteData(name=name, scene=small, capture_dir=tmp_path / name, probes=[], gt=torch.ones(0, 4, 8, 3),
                          global_point=(0.0, 0.0, 0.0), global_time=0.0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            merged[name] = _bound_prior(suite, preset("draft")).merge_views
    assert merged["hard"] == 4  # static lighting, a dolly: every viewpoint merged, as in run_job
    assert merged["temporal"] == 1  # a light switches (and the camera is static): one frame per request


def test_observed_hybrid_takes_the_splat_where_the_prior_saw_and_the_field_elsewhere():
    from types import SimpleNamespace

    from bench.accuracy_probe import observed_hybrid

    class SplatPrior:
        """Sees the upper half of the sphere (colour 5, 3, 1) from every probe, nothing below."""

        def __init__(self):
            self.times = []

        def observed_envmaps(self, centers, time):
            self.times.append(time)
            env = torch.zeros(1, 4, 8, 3)
            seen = torch.zeros(1, 4, 8, dtype=torch.bool)
            env[:, :2] = torch.tensor([5.0, 3.0, 1.0])
            seen[:, :2] = True
            return env, seen

    probes = [SimpleNamespace(x=(1.0, 1.0, 1.0), t=0.1), SimpleNamespace(x=(2.0, 1.0, 1.0), t=0.9)]
    suite = SimpleNamespace(probes=probes, eval_height=8)
    field = torch.full((2, 8, 16, 3), 0.5)
    prior = SplatPrior()
    out = observed_hybrid(prior, suite, field)
    assert prior.times == [0.1, 0.9]  # each probe asks at its own time
    assert out.shape == field.shape
    # seen: the splat, not dimmed at the edge
    assert torch.allclose(out[:, :4], torch.tensor([5.0, 3.0, 1.0]).expand(2, 4, 16, 3), rtol=1e-4)
    assert torch.equal(out[:, 5:], field[:, 5:])  # unseen: the field


def test_the_peak_direction_error_is_the_angle_between_the_brightest_directions_at_any_heights():
    """A lamp found where it stands reads ~0; one found a quarter turn away, 90 degrees; the
    maps may differ in height (the field's and the truth's)."""
    from core.conventions import equirect_directions

    def lamp(height, direction):
        d = equirect_directions(height, dtype=torch.float64)
        env = torch.full((height, 2 * height, 3), 0.1, dtype=torch.float64)
        pixel = (d @ torch.tensor(direction, dtype=torch.float64)).reshape(-1).argmax()
        env.reshape(-1, 3)[pixel] = 50.0
        return env

    truth = lamp(64, (0.0, 0.6, -0.8))
    assert peak_direction_error(lamp(32, (0.0, 0.6, -0.8)), truth) < 5.0
    assert abs(peak_direction_error(lamp(32, (1.0, 0.0, 0.0)), truth) - 90.0) < 5.0
    assert abs(peak_direction_error(truth, truth)) < 1e-6
