"""Field kinds plug in by registration: FieldConfig's sections, build_field and the name lists
follow the registry, and an artefact written before the registry existed still loads."""
from pathlib import Path

import pytest
import torch
from pydantic import Field

from core.fields import FieldConfig, LightField, SceneBounds, build_field, field_kinds, register_field
from core.fields.components.settings import FieldSettings
from core.fields.kinds.registry import FIELDS
from core.fields.stored.artefact import LightFieldArtefact, save_artefact

LEGACY = Path(__file__).parent / "data" / "artefact-main-b8e0d65"
BOUNDS = SceneBounds((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0), 0.0, 0.0)


def test_an_artefact_written_by_the_previous_layout_loads_and_answers_the_same():
    """Written by main at b8e0d65 (core.engine.artefact, FieldConfig with fixed sections)."""
    art = LightFieldArtefact.load(LEGACY)
    assert art.config.kind == "mlp" and art.config.section().width == 8 and art.uses_time
    x = torch.tensor([[0.3, 0.2, -1.0], [-1.0, 0.5, -3.0]])
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 1.0, 0.2], [1.0, -0.3, 0.5]]), dim=-1)
    got = art.radiance(x, torch.tensor([0.5, 1.5]), d)
    expected = torch.tensor([[1.1134368181228638, 1.0346728563308716, 0.9447281360626221],
                             [1.177724003791809, 1.0342910289764404, 0.9743016362190247]])
    torch.testing.assert_close(got, expected, rtol=1e-6, atol=1e-6)


def test_the_field_json_keeps_one_key_per_kind():
    doc = FieldConfig(kind="grid").model_dump(mode="json")
    assert list(doc) == ["kind", "uses_time", "log_radiance_min", "log_radiance_max", "view_detail_heights",
                         "view_detail_radius", "view_anchors", "view_detail_time_rank", "view_detail_time_knots",
                         "emitter_count", "emitter_knots", "emitter_gate_resolution", "emitter_sigma_floor",
                         "room_lattice", "room_lattice_height", "surface_points", "surface_knots", "surface_height",
                         "time_gain_knots", "time_gain_channels", *field_kinds()]
    assert field_kinds()[:3] == ("mlp", "grid", "trunk")
    assert FieldConfig.model_validate(doc) == FieldConfig(kind="grid")
    assert FieldConfig(kind="mlp").with_section("mlp", width=7).section().width == 7
    with pytest.raises(ValueError, match="unknown field kind 'hash'"):
        FieldConfig(kind="hash")
    with pytest.raises(ValueError, match="hash"):
        FieldConfig.model_validate({**doc, "hash": {}})
    with pytest.raises(ValueError, match=r"mlp\.widht: Extra inputs"):
        FieldConfig(mlp={"widht": 3})


def test_a_new_field_is_one_class_and_its_registration(tmp_path):
    class ConstantSettings(FieldSettings):
        value: float = Field(2.0, gt=0)

    @register_field("constant-test")
    class ConstantField(LightField):
        Config = ConstantSettings

        def __init__(self, config, bounds):
            super().__init__(config, bounds)
            self.logit = torch.nn.Parameter(torch.tensor(self.logit_for_radiance(self.settings.value)))

        def logits(self, xn, tn, d):
            return self.logit.expand(xn.shape[0], 3)

    try:
        assert "constant-test" in field_kinds()
        cfg = FieldConfig(kind="constant-test", uses_time=False).with_section(value=3.0)
        field = build_field(cfg, BOUNDS)
        art = LightFieldArtefact.load(save_artefact(tmp_path / "a", field).path)
        env, _ = art.envmap(torch.zeros(3), None, 4)
        torch.testing.assert_close(env, torch.full_like(env, 3.0), rtol=1e-4, atol=1e-4)
        with pytest.raises(ValueError, match="already registered"):
            register_field("mlp")(ConstantField)
    finally:
        FIELDS.pop("constant-test", None)
