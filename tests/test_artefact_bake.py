"""Baked fast path: exact at lattice nodes, close between them on a smooth field, never stale."""
import pytest
import torch

from core.envmap import resize_envmap
from core.fields import FieldConfig, SceneBounds, build_field
from core.fields.kinds.trunk import TrunkSettings
from core.fields.stored.artefact import ArtefactError, LightFieldArtefact, QueryError, save_artefact
from core.fields.stored.bake import BAKED_FILE, BakedField, bake, load_or_bake

BOUNDS = SceneBounds((-2.0, -1.0, -4.0), (2.0, 2.0, 0.5), t0=0.0, t1=3.0)


def smooth_artefact(tmp_path, uses_time=True, seed=0, name="a"):
    """A trunk field without positional frequencies for x and t and small output weights:
    its log-radiance varies by ~0.2 (std) between probes, by ~3 over directions."""
    cfg = FieldConfig(
        kind="trunk",
        uses_time=uses_time,
        trunk=TrunkSettings(
            x_freqs=0, t_freqs=0, d_freqs=1, trunk_width=16, trunk_layers=1, feature_dim=8, head_width=16
        ),
    )
    field = build_field(cfg, BOUNDS)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in field.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.3)
        field.head[-1].weight.mul_(1.0 / 3.0)
    return LightFieldArtefact.load(save_artefact(tmp_path / name, field, {}).path)


@pytest.mark.parametrize("uses_time", [True, False])
def test_baked_equals_exact_at_lattice_nodes(tmp_path, uses_time):
    art = smooth_artefact(tmp_path, uses_time)
    baked = bake(art, grid=(3, 2, 4), times=3, height=8)
    b = art.bounds
    # (0, 1, 2) of (3, 2, 4)
    node = torch.tensor([b.lo[0], b.hi[1], 0.5 * (b.lo[2] + b.hi[2]) + (b.hi[2] - b.lo[2]) / 6])
    t = 1.5 if uses_time else None  # middle keyframe
    exact, _ = art.envmap(node, t, 8)
    fast, _ = baked.envmap(node, t, 8)
    assert torch.allclose(fast, exact, rtol=1e-5)


def test_baked_approximates_exact_between_nodes(tmp_path):
    """Stated tolerance on a smooth field: 5^3 x 4 keys at height 16, queried at random
    points and times at height 16: median relative error < 2 %, 99th percentile < 15 %."""
    art = smooth_artefact(tmp_path)
    baked = bake(art, grid=(5, 5, 5), times=4, height=16)
    torch.manual_seed(1)
    lo, hi = torch.tensor(art.bounds.lo), torch.tensor(art.bounds.hi)
    xs = lo + (hi - lo) * torch.rand(12, 3)
    ts = torch.rand(12) * 3.0
    exact, _ = art.envmaps(xs, ts, 16)
    fast, flags = baked.envmaps(xs, ts, 16)
    rel = ((fast - exact).abs() / exact).flatten()
    assert rel.median() < 0.02 and rel.quantile(0.99) < 0.15, (rel.median(), rel.quantile(0.99))
    assert not any(f["extrapolated_x"] or f["extrapolated_t"] for f in flags)


def test_baked_resamples_to_other_heights_and_flags_outside(tmp_path):
    art = smooth_artefact(tmp_path, uses_time=False)
    baked = bake(art, grid=(2, 2, 2), height=8)
    small, flags = baked.envmap((100.0, 0.0, 0.0), None, 4)
    big, _ = baked.envmap((0.0, 0.0, 0.0), None, 16)
    assert small.shape == (4, 8, 3) and big.shape == (16, 32, 3)
    assert flags == {"extrapolated_x": True, "extrapolated_t": False}
    assert torch.isfinite(small).all() and (small > 0).all()
    native, _ = baked.envmap((0.0, 0.0, 0.0), None, 8)
    assert torch.allclose(big, resize_envmap(native, 16), rtol=1e-5)  # cached stencil == core resize
    assert torch.allclose(baked.envmap((0.0, 0.0, 0.0), None, 4)[0], resize_envmap(native, 4), rtol=1e-5)


def test_save_load_and_staleness(tmp_path):
    art = smooth_artefact(tmp_path, seed=0)
    baked = load_or_bake(art, grid=(2, 2, 2), times=2, height=4)
    assert (art.path / BAKED_FILE).is_file()
    assert torch.equal(BakedField.load(art).maps, baked.maps)
    # re-estimated (other weights) under the same name: the old bake must not be used
    other = smooth_artefact(tmp_path, seed=1, name="b")
    (other.path / BAKED_FILE).write_bytes((art.path / BAKED_FILE).read_bytes())
    with pytest.raises(ArtefactError, match="stale"):
        BakedField.load(other)
    rebaked = load_or_bake(other, grid=(2, 2, 2), times=2, height=4)
    assert not torch.equal(rebaked.maps, baked.maps)
    assert torch.equal(BakedField.load(other).maps, rebaked.maps)


def test_corrupt_bake_is_refused(tmp_path):
    art = smooth_artefact(tmp_path)
    load_or_bake(art, grid=(2, 2, 2), times=2, height=4)
    data = (art.path / BAKED_FILE).read_bytes()
    (art.path / BAKED_FILE).write_bytes(data[: len(data) // 3])
    with pytest.raises(ArtefactError, match="cannot be read"):
        BakedField.load(art)


def test_flipped_bytes_in_the_maps_are_refused_and_rebaked(tmp_path):
    """Issue 14: flipped bytes in baked.safetensors parsed fine and answered 1e-22..7e19.
    The maps' checksum refuses them; load_or_bake bakes again from the verified field."""
    art = smooth_artefact(tmp_path)
    good = load_or_bake(art, grid=(2, 2, 2), times=2, height=4)
    data = bytearray((art.path / BAKED_FILE).read_bytes())
    for k in range(1, 40, 3):  # inside the float data, far from the header
        data[-4 * k] ^= 0x7F
    (art.path / BAKED_FILE).write_bytes(bytes(data))
    with pytest.raises(ArtefactError, match="checksum mismatch"):
        BakedField.load(art)
    again = load_or_bake(art, grid=(2, 2, 2), times=2, height=4)
    assert torch.equal(again.maps, good.maps)
    assert torch.equal(BakedField.load(art).maps, good.maps)  # the corrupt file was replaced


def test_separable_upsampling_equals_resize_envmap_and_its_cache_is_bounded():
    from core.envmap import separable_taps, upsample_envmaps

    maps = torch.rand(3, 8, 16, 3) + 0.1
    for height in (9, 16, 33):
        ref = torch.stack([resize_envmap(m, height) for m in maps])
        assert torch.allclose(upsample_envmaps(maps, height), ref, rtol=1e-5, atol=1e-6)
    for height in range(9, 200):
        upsample_envmaps(maps[:1], height)
    assert separable_taps.cache_info().currsize <= separable_taps.cache_info().maxsize


def test_bake_argument_errors(tmp_path):
    art = smooth_artefact(tmp_path)
    with pytest.raises(QueryError, match="grid"):
        bake(art, grid=(1, 2, 2))
    with pytest.raises(QueryError, match="times"):
        bake(art, grid=(2, 2, 2), times=1)
    with pytest.raises(QueryError, match="MiB"):
        bake(art, grid=(64, 64, 64), times=8, height=256)
    baked = bake(art, grid=(2, 2, 2), times=2, height=4)
    with pytest.raises(QueryError, match="t is required"):
        baked.envmap((0, 0, 0), None)
    with pytest.raises(QueryError, match=r"x must have shape \[3\]"):
        baked.envmap((0, 0), 1.0)
    with pytest.raises(QueryError, match="finite"):
        baked.envmap((0, float("inf"), 0), 1.0)
    with pytest.raises(QueryError, match="height"):
        baked.envmap((0, 0, 0), 1.0, height=-1)


@pytest.mark.parametrize("kind", ["mlp", "trunk", "grid", "baked", "mlp+view-detail"])
def test_a_query_answers_the_same_bits_whatever_is_batched_with_it(tmp_path, kind):
    """The service batches unrelated clients' queries into one call: each answer must not
    depend on the others (CPU matrix products round differently with their row count)."""
    if kind == "baked":
        source = bake(smooth_artefact(tmp_path), grid=(3, 3, 3), times=2, height=8)
        maps = lambda xs, ts: source.envmaps(xs, ts, 8)[0]  # noqa: E731
    elif kind == "mlp+view-detail":  # 40 anchors: more than cdist's matmul threshold
        anchors = (torch.rand(40, 3, generator=torch.Generator().manual_seed(1)) * 2.0 - 1.0).tolist()
        field = build_field(FieldConfig(kind="mlp", view_detail_heights=(4, 8), view_detail_radius=1.0,
                                        view_anchors=anchors), BOUNDS)
        with torch.no_grad():
            for grid in field.view_detail.grids:
                grid.normal_(generator=torch.Generator().manual_seed(2))
        maps = lambda xs, ts: field.envmaps(xs, ts, 8)  # noqa: E731
    else:
        field = build_field(FieldConfig(kind=kind), BOUNDS)
        maps = lambda xs, ts: field.envmaps(xs, ts, 8)  # noqa: E731
    g = torch.Generator().manual_seed(3)
    xs = torch.rand(13, 3, generator=g) * 2.0 - 1.0
    ts = torch.rand(13, generator=g) * 3.0
    with torch.no_grad():
        alone = [maps(xs[i:i + 1], ts[i:i + 1])[0] for i in range(13)]
        for n in (2, 5, 13):
            batch = maps(xs[:n], ts[:n])
            assert all(torch.equal(batch[i], alone[i]) for i in range(n))
