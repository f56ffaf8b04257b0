"""bench/prior_smoothness.py: the prior blended from its answers at the lattice nodes around a probe."""
import torch

from bench.prior_smoothness import blended_prior, parse_lattices
from core.fields.components.normalization import SceneBounds

LO, HI = torch.tensor([0.0, 0.0, 0.0]), torch.tensor([4.0, 2.0, 3.0])
BOX = SceneBounds((0.0, 0.0, 0.0), (4.0, 2.0, 3.0))


class LogLinearPrior:
    """A stand-in prior whose log radiance is linear in position (one map per centre), so a
    trilinear blend in log radiance must reproduce it exactly between the nodes; `asked` records
    where it was queried."""

    def __init__(self):
        self.asked = []

    def envmaps(self, centers, time, height):
        self.asked.append(centers.clone())
        g = torch.tensor([0.3, -0.5, 0.2])
        log_l = centers @ g + 0.1 * time  # [N]
        base = torch.linspace(0.5, 2.0, height * 2 * height * 3).reshape(height, 2 * height, 3)
        return base[None] * torch.exp(log_l)[:, None, None, None]


class BumpPrior(LogLinearPrior):
    """Bright only within 0.1 m of one point: a blend from nodes 1 m away cannot see it."""

    def envmaps(self, centers, time, height):
        near = ((centers - torch.tensor([1.5, 0.75, 1.2])).norm(dim=-1) < 0.1).float()
        return torch.ones(centers.shape[0], height, 2 * height, 3) * (1.0 + 99.0 * near)[:, None, None, None]


def test_a_log_linear_prior_is_reproduced_between_the_nodes():
    prior = LogLinearPrior()
    x = torch.tensor([1.3, 0.7, 2.2])
    blend = blended_prior(prior, x, 0.5, BOX, (5, 3, 4), height=4)
    direct = prior.envmaps(x[None], 0.5, 4)[0]
    assert torch.allclose(blend, direct, rtol=1e-4)
    nodes = prior.asked[0]
    assert nodes.shape == (8, 3)
    # the corners of x's cell: spacing (1, 1, 1) m on this lattice, x inside their box
    assert torch.allclose(nodes.amin(0), torch.tensor([1.0, 0.0, 2.0])) and torch.allclose(
        nodes.amax(0), torch.tensor([2.0, 1.0, 3.0])
    )


def test_a_sharp_feature_between_the_nodes_is_lost_by_the_blend():
    prior = BumpPrior()
    x = torch.tensor([1.5, 0.75, 1.2])
    direct = prior.envmaps(x[None], 0.0, 4)[0]
    blend = blended_prior(prior, x, 0.0, BOX, (5, 3, 4), height=4)
    assert float(direct.mean()) == 100.0 and torch.allclose(blend, torch.ones_like(blend))


def test_a_probe_outside_the_box_blends_the_nearest_face():
    prior = LogLinearPrior()
    blended_prior(prior, torch.tensor([9.0, -1.0, 1.5]), 0.0, BOX, (3, 3, 3), height=2)
    nodes = prior.asked[0]
    assert torch.all(nodes >= LO - 1e-6) and torch.all(nodes <= HI + 1e-6)


def test_lattices_are_parsed_and_checked():
    assert parse_lattices("4,2,4:8,4,8") == [(4, 2, 4), (8, 4, 8)]
    for bad in ("4,2", "1,2,2"):
        try:
            parse_lattices(bad)
        except SystemExit as e:
            assert bad in str(e)
        else:
            raise AssertionError(bad)
