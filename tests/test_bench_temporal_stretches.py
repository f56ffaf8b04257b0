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
