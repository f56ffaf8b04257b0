"""bench.photo_colour: the variants of a photo's map that tell what decides its diffuse angle."""
from __future__ import annotations

import torch

from bench.photo_colour import summarise, variants
from core.exposure import luminance


def test_each_variant_swaps_only_its_part():
    """Seen directions keep the prior's map except in `seen exact` (the truth at the map's
    scale); unseen ones keep it except in the fill and colour variants, which keep its
    luminance where they recolour."""
    g = torch.Generator().manual_seed(0)
    prior = torch.rand(8, 16, 3, generator=g, dtype=torch.float64) + 0.1
    truth = torch.rand(8, 16, 3, generator=g, dtype=torch.float64) + 0.1
    constant = torch.tensor([0.6, 0.3, 0.1], dtype=torch.float64).expand(8, 16, 3)
    seen = torch.zeros(8, 16, dtype=torch.bool)
    seen[3:5, 6:10] = True
    truth[seen] = 3.0 * prior[seen]  # the map is the truth / 3 where seen
    v = variants(prior, constant, truth, seen)
    assert torch.allclose(v["seen exact"][seen], prior[seen]) and torch.equal(v["seen exact"][~seen], prior[~seen])
    assert torch.equal(v["fill x2"][seen], prior[seen]) and torch.allclose(v["fill x2"][~seen], 2 * prior[~seen])
    recoloured = v["unseen in constant colour"][~seen]
    assert torch.allclose(luminance(recoloured), luminance(prior[~seen]))
    chroma = recoloured / luminance(recoloured)[:, None]
    assert torch.allclose(chroma, (constant[0, 0] / luminance(constant[0, 0])).expand_as(chroma))
    assert torch.equal(v["unseen in true colour"][seen], prior[seen])


def test_the_summary_is_each_variants_error_over_the_constant_maps():
    from bench.real_panoramas import CONSTANT

    def row(si, ang, const_si, const_ang):
        return {"prior": {"si_rmse_rel": si, "angular_deg": ang},
                CONSTANT: {"si_rmse_rel": const_si, "angular_deg": const_ang}}

    rows = {"a": row(1.0, 2.0, 2.0, 2.0), "b": row(1.0, 6.0, 2.0, 4.0)}
    assert summarise(rows) == {"prior": {"si_rmse_rel": 0.5, "angular_deg": round(8 / 6, 4)}}
