"""docs/architecture.md's worked example, "adding a prior and a field", run as written: the two
modules below are the doc's code blocks, character for character (the first test checks it), so
the example stays true to the registries' real APIs.

The registries are global and have no unregister call, so the examples are registered by a
fixture and removed from `PRIORS` / `FIELDS` afterwards: other tests list the registered names
(tests/test_priors_registry.py, tests/test_fields_registry.py). That a job selects them by name
is checked in a fresh interpreter, because `JobParams` reads the registries' names when
core.engine.params is first imported (which is why a new module must be imported by
core/priors/__init__.py or core/fields/__init__.py)."""
from __future__ import annotations

import subprocess
import sys
import types
from pathlib import Path

import pytest
import torch

from core.capture.load import capture_from_arrays
from core.chrome_ball import ball_reflection_rays, composite, place_probe, render_balls
from core.conventions import inverse_tonemap, tonemap
from core.fields import FieldConfig, SceneBounds, build_field, field_kinds
from core.fields.kinds.registry import FIELDS
from core.fields.stored.artefact import LightFieldArtefact, save_artefact
from core.priors.base import PriorError, PriorRequest, ProbeGeometry
from core.priors.registry import PRIORS, build_prior, job_prior_names, prior_class

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "architecture.md"

PRIOR_EXAMPLE = '''\
# core/priors/constant.py
import torch
from pydantic import NonNegativeFloat

from core.priors.base import Prior, PriorCapabilities, PriorConfig, PriorRequest
from core.priors.known import ball_target
from core.priors.registry import register_prior


class ConstantSettings(PriorConfig):  # strict: a misspelt key is an error
    radiance: tuple[NonNegativeFloat, NonNegativeFloat, NonNegativeFloat] = (1.0, 1.0, 1.0)


@register_prior("constant", for_jobs=True)  # for_jobs: JobParams.prior and --prior offer it
class ConstantPrior(Prior):
    Config = ConstantSettings
    capabilities = PriorCapabilities(envmaps=True)  # it answers env maps, cheaply

    def __init__(self, radiance=(1.0, 1.0, 1.0)):  # from_config: ConstantPrior(**settings)
        self.radiance = torch.tensor(radiance, dtype=torch.float32)

    def __call__(self, request: PriorRequest) -> torch.Tensor:
        # every ball reflects the one radiance; outside the balls the image is left as it is
        return ball_target(request, lambda d, ball: self.radiance.expand(d.shape[0], 3))

    def envmaps(self, centers, time, height):  # [N, height, 2 height, 3] linear HDR
        return self.radiance.expand(centers.shape[0], height, 2 * height, 3).clone()

    def describe(self) -> dict:  # recorded in the artefact's lightfield.json
        return {"name": self.name, "radiance": self.radiance.tolist()}
'''

FIELD_EXAMPLE = '''\
# core/fields/kinds/constant.py
import torch
from pydantic import Field

from core.fields.components.settings import FieldSettings
from core.fields.kinds.base import LightField
from core.fields.kinds.registry import register_field


class ConstantSettings(FieldSettings):  # FieldConfig's "constant" section
    initial_radiance: float = Field(1.0, gt=0)


@register_field("constant")
class ConstantField(LightField):
    Config = ConstantSettings

    def __init__(self, config, bounds):
        super().__init__(config, bounds)  # self.settings: this kind's section of `config`
        z = self.logit_for_radiance(self.settings.initial_radiance)
        self.z = torch.nn.Parameter(torch.full((3,), z))  # one learnable logit per colour

    def logits(self, xn, tn, d):  # normalised x [B,3], t [B,1] or None, unit d [B,3] -> [B,3]
        return self.z.expand(xn.shape[0], 3)
'''

BOUNDS = SceneBounds((-2.0, -1.0, -2.0), (2.0, 1.5, 2.0), 0.0, 0.0)


def _module(name: str, source: str) -> types.ModuleType:
    module = types.ModuleType(name)
    exec(compile(source, f"<docs/architecture.md: {name}>", "exec", dont_inherit=True), module.__dict__)
    return module


@pytest.fixture
def example():
    """The doc's two modules, imported (so registered) for one test, then unregistered."""
    prior = field = None
    try:
        prior = _module("core.priors.constant", PRIOR_EXAMPLE)
        field = _module("core.fields.kinds.constant", FIELD_EXAMPLE)
        yield prior, field
    finally:
        if prior is not None and PRIORS.get("constant") is prior.ConstantPrior:
            del PRIORS["constant"]
        if field is not None and FIELDS.get("constant") is field.ConstantField:
            del FIELDS["constant"]


def test_the_doc_shows_exactly_this_code():
    doc = DOC.read_text()
    for source in (PRIOR_EXAMPLE, FIELD_EXAMPLE):
        assert f"```python\n{source}```" in doc


def _tiny_request():
    """One 24 x 32 frame of a grey room with a grey chrome ball in its middle, as the engine
    composites the current field's balls (ev 0)."""
    capture = capture_from_arrays(torch.full((1, 24, 32, 3), 0.4), torch.full((1, 24, 32), 3.0))
    camera, background = capture.camera(0), inverse_tonemap(capture.frames[0])
    center, radius = place_probe(camera, (16.0, 12.0), 2.0)
    centers, radii = center[None], torch.tensor([radius])
    rays = ball_reflection_rays(camera, centers, radii)
    layer = render_balls(camera, centers, radii, lambda d, ball: torch.full((d.shape[0], 3), 0.5), rays=rays)
    image = tonemap(composite(background, layer), 0.0).permute(2, 0, 1)
    probes = ProbeGeometry(centers, radii, torch.tensor([[16.0, 12.0]]), camera, 0, 0.0)
    return PriorRequest(image, layer.coverage, capture.depth[0], 0.0, 1.0, 10, 1.0, probes,
                        extras={"frame_linear": background, "ball_rays": rays})


def test_the_prior_is_found_by_name_built_from_its_settings_and_answers(example):
    prior_module, _ = example
    assert prior_class("constant") is prior_module.ConstantPrior and "constant" in job_prior_names()
    prior = build_prior("constant", {"radiance": (0.75, 0.5, 0.25)})
    assert prior.describe() == {"name": "constant", "radiance": [0.75, 0.5, 0.25]}
    maps = prior.envmaps(torch.zeros(2, 3), 0.0, 4)
    assert maps.shape == (2, 4, 8, 3) and torch.equal(maps[1, 3, 7], torch.tensor([0.75, 0.5, 0.25]))
    with pytest.raises(PriorError, match="radiance"):
        build_prior("constant", {"radiance": (-1.0, 0.0, 0.0)})

    request = _tiny_request()
    target = prior(request)
    assert target.shape == request.image.shape
    centre = target[:, 12, 16]  # the ball's middle reflects the constant radiance, tone mapped at ev 0
    torch.testing.assert_close(centre, tonemap(torch.tensor([0.75, 0.5, 0.25]), 0.0))
    assert not torch.allclose(centre, request.image[:, 12, 16])  # not the grey ball it was given
    outside = request.ball_masks.sum(0) == 0
    assert torch.equal(target[:, outside], request.image[:, outside])  # outside the ball: untouched


def test_the_field_is_found_by_name_built_from_its_section_evaluated_and_saved(example, tmp_path):
    _, field_module = example
    assert field_kinds()[-1] == "constant" and FIELDS["constant"] is field_module.ConstantField
    config = FieldConfig(kind="constant", uses_time=False).with_section(initial_radiance=2.0)
    assert config.model_dump(mode="json")["constant"] == {"initial_radiance": 2.0}
    field = build_field(config, BOUNDS)
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.3, -0.5, 0.8]]), dim=-1)
    radiance = field(torch.zeros(3, 3), None, d)
    torch.testing.assert_close(radiance, torch.full((3, 3), 2.0), rtol=1e-4, atol=1e-4)
    radiance.sum().backward()  # learnable: the distillation moves z
    assert field.z.grad is not None and bool((field.z.grad != 0).all())

    saved = save_artefact(tmp_path / "artefact", field)
    env, _ = LightFieldArtefact.load(saved.path).envmap(torch.tensor([0.5, 0.0, -0.5]), None, 4)
    torch.testing.assert_close(env, torch.full((4, 8, 3), 2.0), rtol=1e-4, atol=1e-4)


JOB_SCRIPT = '''
import sys, warnings
import numpy as np
from PIL import Image

for name, source in (("core.priors.constant", sys.argv[1]), ("core.fields.kinds.constant", sys.argv[2])):
    exec(compile(source, name, "exec"), {"__name__": name})  # as core/priors/__init__.py would import it
from core.engine import run_job
from core.engine.params import JobParams, resolve_job

params = JobParams.model_validate({"prior": "constant", "field": "constant"})
job = resolve_job(params, {"field.constant.initial_radiance": 2.0, "priors.constant.radiance": (0.5, 0.5, 0.5)})
print(job.config.field.kind, job.config.field.section().initial_radiance, job.prior_settings["radiance"])

out = sys.argv[3]
Image.fromarray(np.full((24, 32, 3), 128, np.uint8)).save(out + "/room.png")
tiny = {"distill.iterations": 4, "distill.work_height": 24, "distill.warmup_steps": 1, "distill.fallback": False,
        "priors.constant.radiance": (0.5, 0.5, 0.5)}
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    art = run_job(out + "/room.png", None, params, out + "/art", overrides=tiny).artefact
print(art.config.kind, art.meta["prior"]["name"], art.meta["prior"]["radiance"], art.meta["training"]["supervision"])
'''


def test_a_job_selects_them_by_name_and_runs(tmp_path):
    """In a fresh interpreter, where they are registered before core.engine.params is imported:
    JobParams accepts both names, the overrides reach their settings, and a 4-step run_job on
    a 24 x 32 photo trains the constant field on the constant prior's env maps."""
    done = subprocess.run([sys.executable, "-c", JOB_SCRIPT, PRIOR_EXAMPLE, FIELD_EXAMPLE, str(tmp_path)], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.splitlines()[-2:] == ["constant 2.0 (0.5, 0.5, 0.5)",
                                             "constant constant [0.5, 0.5, 0.5] envmaps"]
