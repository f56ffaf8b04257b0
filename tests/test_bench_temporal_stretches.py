"""bench/temporal_stretches.py's helpers: the relative course and the variant syntax."""
import torch

from bench.temporal_stretches import parse_variant, relative_course


def test_a_scaled_follower_has_a_flat_course_and_a_lagging_one_does_not():
    truth = torch.tensor([4.0, 3.0, 2.0, 1.0])
    assert relative_course(7.0 * truth, truth) == [1.0, 1.0, 1.0, 1.0]  # the scale does not matter
    lagging = torch.tensor([4.0, 3.5, 2.5, 1.5])  # dims less than the truth
    course = relative_course(lagging, truth)
    assert course[0] < 1.0 < course[-1] and abs(sum(course) / len(course) - 1.0) < 1e-3


def test_variants_name_their_overrides():
    assert parse_variant("no_emitters:distill.emitters=0") == ("no_emitters", {"distill.emitters": 0})
    name, sets = parse_variant("two:distill.emitters=0,field.view_detail_heights=[]")
    assert name == "two" and sets == {"distill.emitters": 0, "field.view_detail_heights": []}
    assert parse_variant("draft") == ("draft", {})
