"""bench/temporal_stretches.py: the relative course (bench.suite.evaluation) and the variant syntax."""
import torch

from bench.suite.evaluation import relative_course
from bench.temporal_stretches import parse_variant


def test_a_scaled_follower_has_a_flat_course_and_a_lagging_one_does_not():
    truth = torch.tensor([4.0, 3.0, 2.0, 1.0])
    assert torch.allclose(relative_course(7.0 * truth, truth), torch.ones(4, dtype=torch.float64))  # any scale
    lagging = torch.tensor([4.0, 3.5, 2.5, 1.5])  # dims less than the truth
    course = relative_course(lagging, truth)
    assert course[0] < 1.0 < course[-1] and abs(float(course.mean()) - 1.0) < 1e-12


def test_variants_name_their_overrides():
    assert parse_variant("no_emitters:distill.emitters=0") == ("no_emitters", {"distill.emitters": 0})
    name, sets = parse_variant("two:distill.emitters=0,field.view_detail_heights=[]")
    assert name == "two" and sets == {"distill.emitters": 0, "field.view_detail_heights": []}
    assert parse_variant("draft") == ("draft", {})


def test_room_summary_compares_each_point_with_the_prior_at_that_point():
    from bench.temporal_stretches import room_summary, stretch_changes

    class Suite:  # two series over one stretch from t = 0 to t = 1 s (their own positions are not used)
        series = [type("S", (), {"kind": "stretch", "x": (k, 0.0, 0.0), "times": torch.tensor([0.0, 0.5, 1.0])})()
                  for k in (0.0, 2.0)]

    positions = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0)]

    def dimming(factor_at_x):  # a uniform map whose brightness falls to factor(x) at t = 1
        return lambda x, t: torch.full((4, 8, 3), 1.0 - t * (1.0 - factor_at_x(x)))

    prior = stretch_changes(Suite, positions, dimming(lambda x: 0.4))
    field = stretch_changes(Suite, positions, dimming(lambda x: 0.4 if x[0] == 0.0 else 0.6))
    assert len(prior) == 1 and prior[0]["t"] == [0.0, 1.0] and prior[0]["ratios"] == [0.4, 0.4]
    s = room_summary(field, prior)[0]
    assert s["mean_change"] == 0.5 and s["over_prior_mean"] == 1.25 and s["over_prior_sd"] > 0.3
    assert room_summary(prior, prior)[0]["over_prior_sd"] == 0.0
