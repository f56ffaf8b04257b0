"""Artefact: exact round trip, clear errors for every kind of damage, atomic writes."""
import json
import os

import pytest
import torch

import core.fields.stored.artefact as artefact_mod
from core.conventions import CONVENTIONS_VERSION
from core.fields import FieldConfig, SceneBounds, build_field
from core.fields.kinds.grid import GridSettings
from core.fields.kinds.mlp import MLPSettings
from core.fields.kinds.trunk import TrunkSettings
from core.fields.stored.artefact import (
    META_FILE,
    WEIGHTS_FILE,
    ArtefactError,
    LightFieldArtefact,
    QueryError,
    save_artefact,
)

BOUNDS = SceneBounds((-2.0, -1.0, -4.0), (2.0, 2.0, 0.5), t0=0.0, t1=3.0)


def small_field(kind="mlp", uses_time=True, seed=0):
    cfg = FieldConfig(
        kind=kind,
        uses_time=uses_time,
        mlp=MLPSettings(width=16, layers=3, skip_layer=2),
        grid=GridSettings(resolution=(2, 2, 2), env_height=4, time_keyframes=2),
        trunk=TrunkSettings(trunk_width=16, trunk_layers=1, feature_dim=8, head_width=16),
    )
    field = build_field(cfg, BOUNDS)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in field.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.5)
    return field


@pytest.fixture
def saved(tmp_path):
    field = small_field()
    path = save_artefact(
        tmp_path / "art", field, {"capture": {"fps": 10.0}, "training": {"loss_curve": [1.0, float("nan")]}}
    ).path
    return field, path


@pytest.mark.parametrize("kind", ["mlp", "grid", "trunk"])
@pytest.mark.parametrize("uses_time", [True, False])
def test_round_trip_is_bit_identical(tmp_path, kind, uses_time):
    field = small_field(kind, uses_time)
    art = LightFieldArtefact.load(save_artefact(tmp_path / "a", field, {}).path)
    x = torch.tensor([[0.1, 0.2, -1.0], [9.0, 0.0, 0.0]])
    t = torch.tensor([0.5, 2.0]) if uses_time else None
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 1.0, 0.0], [1.0, -1.0, 0.5]]), dim=-1)
    with torch.no_grad():
        assert torch.equal(art.radiance(x, t, d), field(x, t, d))
        assert torch.equal(art.envmaps(x, t, 5)[0], field.envmaps(x, t, 5))
    hdr, flags = art.envmap(x[1], None if t is None else t[1], 5)
    assert hdr.shape == (5, 10, 3) and hdr.dtype == torch.float32
    assert flags == {"extrapolated_x": True, "extrapolated_t": False}
    assert art.config == field.config and art.bounds == field.bounds


def test_metadata_is_stored_and_nan_becomes_null(saved):
    _, path = saved
    doc = json.loads((path / META_FILE).read_text())
    assert doc["schema_version"] == 1 and doc["conventions_version"] == CONVENTIONS_VERSION
    assert doc["capture"] == {"fps": 10.0}
    assert doc["training"]["loss_curve"] == [1.0, None]
    assert LightFieldArtefact.load(path).meta["bounds"]["t1"] == 3.0


def test_flags_for_time_and_space(saved):
    _, path = saved
    art = LightFieldArtefact.load(path)
    _, flags = art.envmaps(
        torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 5.0, -1.0]]), torch.tensor([1.0, 4.0, -1.0]), 2
    )
    assert flags == [
        {"extrapolated_x": False, "extrapolated_t": False},
        {"extrapolated_x": False, "extrapolated_t": True},
        {"extrapolated_x": True, "extrapolated_t": True},
    ]


def test_query_errors_name_the_offending_input(saved):
    _, path = saved
    art = LightFieldArtefact.load(path)
    with pytest.raises(QueryError, match="t is required"):
        art.envmap((0, 0, 0), None, 4)
    with pytest.raises(QueryError, match="x must be finite"):
        art.envmap((0, float("nan"), 0), 0.0, 4)
    with pytest.raises(QueryError, match="t must be finite"):
        art.envmap((0, 0, 0), float("inf"), 4)
    with pytest.raises(QueryError, match="height"):
        art.envmap((0, 0, 0), 0.0, 0)
    with pytest.raises(QueryError, match="height"):
        art.envmap((0, 0, 0), 0.0, 2.5)
    with pytest.raises(QueryError, match=r"x must have shape"):
        art.envmap((0, 0), 0.0, 4)
    with pytest.raises(QueryError, match="d must"):
        art.radiance([[0, 0, 0]], [0.0], [[0, 0, 0]])


def test_static_field_accepts_missing_time(tmp_path):
    art = LightFieldArtefact.load(save_artefact(tmp_path / "s", small_field(uses_time=False), {}).path)
    a, flags = art.envmap((0, 0, -1), None, 4)
    b, _ = art.envmap((0, 0, -1), 2.0, 4)
    assert torch.equal(a, b) and flags == {"extrapolated_x": False, "extrapolated_t": False}


# ------------------------------------------------------------------ damage
def _edit_json(path, fn, reseal: bool = True):
    """Edit lightfield.json; `reseal` recomputes its checksum, as a crafted file would, so the
    deeper checks below are what refuses it."""
    from core.integrity import seal_document

    doc = json.loads((path / META_FILE).read_text())
    fn(doc)
    (path / META_FILE).write_text(json.dumps(seal_document(doc) if reseal else doc))


def test_edited_or_truncated_json_is_a_checksum_mismatch_or_unparseable(saved):
    _, path = saved
    original = (path / META_FILE).read_text()
    _edit_json(path, lambda d: d["capture"].update(fps=11.0), reseal=False)  # valid JSON, other content
    with pytest.raises(ArtefactError, match="lightfield.json: checksum mismatch"):
        LightFieldArtefact.load(path)
    (path / META_FILE).write_text(original[: len(original) // 2])
    with pytest.raises(ArtefactError, match="not valid JSON"):
        LightFieldArtefact.load(path)


def test_missing_files(saved, tmp_path):
    _, path = saved
    with pytest.raises(ArtefactError, match="does not exist"):
        LightFieldArtefact.load(tmp_path / "nowhere")
    (path / WEIGHTS_FILE).unlink()
    with pytest.raises(ArtefactError, match=f"missing {WEIGHTS_FILE}"):
        LightFieldArtefact.load(path)
    (path / META_FILE).unlink()
    with pytest.raises(ArtefactError, match=f"missing {META_FILE}"):
        LightFieldArtefact.load(path)


def test_truncated_weights(saved):
    _, path = saved
    data = (path / WEIGHTS_FILE).read_bytes()
    (path / WEIGHTS_FILE).write_bytes(data[: len(data) // 2])
    with pytest.raises(ArtefactError, match="checksum mismatch"):
        LightFieldArtefact.load(path)


def test_truncated_weights_with_matching_checksum_fail_to_parse(saved):
    """Even if someone 'fixes' the checksum, a truncated file is refused by the parser."""
    _, path = saved
    data = (path / WEIGHTS_FILE).read_bytes()[:-100]
    (path / WEIGHTS_FILE).write_bytes(data)
    _edit_json(path, lambda d: d["weights"].update(sha256=artefact_mod._sha256(data)))
    with pytest.raises(ArtefactError, match="cannot be parsed as safetensors"):
        LightFieldArtefact.load(path)


def test_flipped_byte_is_a_checksum_mismatch(saved):
    _, path = saved
    data = bytearray((path / WEIGHTS_FILE).read_bytes())
    data[-5] ^= 0xFF
    (path / WEIGHTS_FILE).write_bytes(bytes(data))
    with pytest.raises(ArtefactError, match="checksum"):
        LightFieldArtefact.load(path)


def test_garbage_json(saved):
    _, path = saved
    (path / META_FILE).write_text("{not json")
    with pytest.raises(ArtefactError, match="not valid JSON"):
        LightFieldArtefact.load(path)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d.update(schema_version=2), "schema_version"),
        (lambda d: d.pop("schema_version"), "schema_version"),
        (lambda d: d.update(conventions_version="2.0"), "conventions_version"),
        (lambda d: d["field"].update(kind="nerf"), "'field'"),
        (lambda d: d["bounds"].update(hi=[0, 0, 0]), "'bounds'"),
        (lambda d: d.pop("weights"), "'weights'"),
        (lambda d: d["weights"].update(sha256="0" * 64), "checksum mismatch"),
    ],
)
def test_edited_json_is_refused_with_a_named_field(saved, edit, message):
    _, path = saved
    _edit_json(path, edit)
    with pytest.raises(ArtefactError, match=message):
        LightFieldArtefact.load(path)


def test_config_that_disagrees_with_tensor_shapes(saved):
    _, path = saved
    _edit_json(path, lambda d: d["field"]["mlp"].update(width=32))
    with pytest.raises(ArtefactError, match=r"tensor 'layers.0.weight' has shape \(16, "):
        LightFieldArtefact.load(path)


def test_config_that_implies_other_tensors(saved):
    _, path = saved
    _edit_json(path, lambda d: d["field"].update(kind="grid"))
    with pytest.raises(ArtefactError, match="missing \\['maps'\\]"):
        LightFieldArtefact.load(path)


def test_bounds_edited_in_json_but_not_in_weights(saved):
    _, path = saved
    _edit_json(path, lambda d: d["bounds"].update(hi=[5.0, 5.0, 5.0]))
    with pytest.raises(ArtefactError, match="bounds_hi .* disagrees"):
        LightFieldArtefact.load(path)


def test_loader_never_unpickles(saved, monkeypatch):
    _, path = saved

    def forbidden(*a, **k):
        raise AssertionError("pickle-based loading used")

    monkeypatch.setattr(torch, "load", forbidden)
    monkeypatch.setattr("pickle.load", forbidden)
    monkeypatch.setattr("pickle.loads", forbidden)
    LightFieldArtefact.load(path)


# ------------------------------------------------------------------ atomic writes
def test_failure_mid_write_leaves_no_partial_artefact(tmp_path, monkeypatch):
    def boom(path, document):
        path.write_text("{partial")
        raise OSError("disk full")

    monkeypatch.setattr(artefact_mod, "_write_json", boom)
    with pytest.raises(OSError, match="disk full"):
        save_artefact(tmp_path / "a", small_field(), {})
    assert os.listdir(tmp_path) == []  # neither the final name nor a temp dir


def test_failed_overwrite_keeps_the_previous_artefact(tmp_path, monkeypatch):
    field = small_field(seed=1)
    path = save_artefact(tmp_path / "a", field, {"run": 1}).path
    before = LightFieldArtefact.load(path).radiance([[0, 0, 0]], [0.0], [[0, 1, 0]])

    real_replace = os.replace

    def failing_replace(src, dst):  # fail the rename of the new directory onto the final name
        if str(src).startswith(str(tmp_path / ".a.tmp-")):
            raise OSError("rename failed")
        return real_replace(src, dst)

    monkeypatch.setattr(artefact_mod.os, "replace", failing_replace)
    with pytest.raises(OSError, match="rename failed"):
        save_artefact(tmp_path / "a", small_field(seed=2), {"run": 2})
    monkeypatch.undo()
    assert os.listdir(tmp_path) == ["a"]
    art = LightFieldArtefact.load(path)
    assert art.meta["run"] == 1
    assert torch.equal(art.radiance([[0, 0, 0]], [0.0], [[0, 1, 0]]), before)


def test_overwrite_replaces_previous_artefact(tmp_path):
    save_artefact(tmp_path / "a", small_field(seed=1), {"run": 1})
    (tmp_path / "a" / "baked.safetensors").write_bytes(b"stale")
    save_artefact(tmp_path / "a", small_field(seed=2), {"run": 2})
    assert os.listdir(tmp_path) == ["a"]
    assert sorted(os.listdir(tmp_path / "a")) == [WEIGHTS_FILE, META_FILE]  # derived files of the old run are gone
    assert LightFieldArtefact.load(tmp_path / "a").meta["run"] == 2


def test_reserved_meta_keys_and_unserialisable_values(tmp_path):
    with pytest.raises(ArtefactError, match="'field' is reserved"):
        save_artefact(tmp_path / "a", small_field(), {"field": {"kind": "x"}})
    with pytest.raises(ArtefactError, match="not JSON-serialisable"):
        save_artefact(tmp_path / "b", small_field(), {"obj": object()})
    save_artefact(tmp_path / "c", small_field(), {"conventions_version": CONVENTIONS_VERSION, "arr": torch.arange(3)})
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    assert json.loads((tmp_path / "c" / META_FILE).read_text())["arr"] == [0, 1, 2]


def test_crafted_huge_config_is_refused_without_allocating(saved):
    """Shapes are checked on the meta device first: a config implying 10^12 parameters is an
    ArtefactError, not an out-of-memory crash."""
    _, path = saved
    _edit_json(path, lambda d: d["field"]["mlp"].update(width=1_000_000))
    with pytest.raises(ArtefactError, match="has shape"):
        LightFieldArtefact.load(path)


def test_save_returns_the_artefact_exactly_as_loading_it_would(tmp_path):
    field = small_field(seed=3)
    saved = save_artefact(tmp_path / "a", field, {"note": [1.5, float("inf")]})
    loaded = LightFieldArtefact.load(saved.path)
    assert saved.meta == loaded.meta and saved.weights_sha256 == loaded.weights_sha256
    a, b = saved.field.state_dict(), loaded.field.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert saved.field is not field and not any(p.requires_grad for p in saved.field.parameters())
    x = torch.tensor([[0.1, 0.2, -0.5]])
    torch.testing.assert_close(saved.envmaps(x, [0.5], 8)[0], loaded.envmaps(x, [0.5], 8)[0], rtol=0, atol=0)
