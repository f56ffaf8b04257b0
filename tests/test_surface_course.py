"""Surfaces a moving camera saw while a lamp switched on (core.capture.surface_course): each
keeps its own change, the walls near the lamp brighten far more than the far ones, and a wall
seen only before the switch takes its neighbours' change, not the room's average."""
from __future__ import annotations

import torch

from core.capture.surface_course import surface_course

XS = torch.linspace(0.0, 4.0, 400)  # a wall along x; the lamp at x = -0.3
BASE = 1.0
LAMP = 3.0 / (0.3 + XS) ** 2
TINT = torch.tensor([1.0, 0.9, 0.8])


def _walk(views: list[tuple[float, torch.Tensor]]):
    """Readings of the wall by views (time, seen mask), the lamp on after t = 1 s."""
    pts = torch.stack([XS, torch.zeros_like(XS), torch.zeros_like(XS)], -1)
    P, C, V = [], [], []
    for v, (t, seen) in enumerate(views):
        y = BASE + (LAMP if t > 1.0 else 0.0 * LAMP)
        P.append(pts[seen])
        C.append(y[seen, None] * TINT)
        V.append(torch.full((int(seen.sum()),), v))
    times = torch.tensor([t for t, _ in views])
    pos, col = surface_course(torch.cat(P), torch.cat(C), torch.cat(V), times, torch.tensor([0.0, 2.0]), 200)
    order = torch.argsort(pos[:, 0])
    return pos[order, 0], col[order]


def _truth(x: torch.Tensor) -> torch.Tensor:
    return (BASE + 3.0 / (0.3 + x) ** 2) / BASE


def test_each_wall_keeps_its_own_change_where_it_was_seen_before_and_after():
    x, col = _walk([(0.0, XS < 2.2), (0.5, XS < 3.2), (1.5, XS > 1.0), (2.0, XS >= 0.0)])
    ratio = col[:, 1, 1] / col[:, 0, 1]
    truth = _truth(x)
    assert ((ratio / truth).log().abs() < 0.1).float().mean() > 0.9
    # the colour is kept, the time course is not a room-wide gain
    assert torch.allclose(col[:, 0] / col[:, 0, :1], TINT.expand_as(col[:, 0]), atol=1e-4)
    assert float(ratio[x < 0.5].min()) > 3.0 * float(ratio[x > 3.0].max())


def test_a_wall_seen_only_before_the_switch_takes_its_neighbours_change():
    x, col = _walk([(0.0, XS < 2.2), (0.5, XS < 3.2), (1.5, XS > 1.0), (2.0, XS > 0.8)])
    ratio = col[:, 1, 1] / col[:, 0, 1]
    near, far = ratio[x < 0.8], ratio[x > 3.0]
    # the room's mean change (what a room-wide gain gives every wall) is far below the lamp's side
    assert float(near.min()) > 2.5 and float(far.max()) < 1.5


def test_static_light_stays_static_and_one_view_is_held():
    pts = torch.stack([XS, torch.zeros_like(XS), torch.zeros_like(XS)], -1)
    col = (BASE + 0.0 * LAMP)[:, None] * TINT
    both = torch.cat([pts, pts]), torch.cat([col, col]), torch.cat([torch.zeros(400), torch.ones(400)]).long()
    pos, out = surface_course(*both, torch.tensor([0.0, 1.0]), torch.tensor([0.0, 0.5, 1.0]), 100)
    assert torch.allclose(out[:, 0], out[:, 2]) and torch.allclose(out[:, 1, 1], torch.full((pos.shape[0],), 0.9))
    one = surface_course(pts, col, torch.zeros(400, dtype=torch.long), torch.tensor([0.3]),
                         torch.tensor([0.0, 1.0]), 50)
    assert torch.isfinite(one[1]).all() and torch.allclose(one[1][:, 0], one[1][:, 1])
