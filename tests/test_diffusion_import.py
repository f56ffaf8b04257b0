"""`lightfield prior import` on folders laid out exactly like the releases (tiny random
modules, tests/diffusion_releases.py), then a distillation end to end through
`run_job` with each imported prior. Sockets are blocked throughout: nothing may be fetched.
"""
from __future__ import annotations

import json
import shutil
import socket
import warnings

import pytest
import torch

from core.priors.base import PriorError

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.slow]


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    def refuse(*a, **k):
        raise AssertionError("network access attempted")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)


@pytest.fixture(scope="module")
def releases(tmp_path_factory):
    from tests.diffusion_releases import (
        write_authors_release,
        write_diffusionlight_sd2_release,
        write_diffusionlight_sdxl_release,
    )

    root = tmp_path_factory.mktemp("releases")
    return {"authors": write_authors_release(root / "a"), "sdxl": write_diffusionlight_sdxl_release(root / "x"),
            "sd2": write_diffusionlight_sd2_release(root / "n")}


@pytest.fixture(scope="module")
def imported(releases, tmp_path_factory):
    from cli.main import main

    out = tmp_path_factory.mktemp("imported")
    pipe, cn = releases["authors"]
    assert main(["prior", "import", str(pipe), "--controlnet", str(cn), "-o", str(out / "authors")]) == 0
    sdxl, cn, vae, lora = releases["sdxl"]
    assert main(["prior", "import", str(sdxl), "--controlnet", str(cn), "--vae", str(vae), "--lora", str(lora),
                 "-o", str(out / "sdxl")]) == 0
    pipe, cn = releases["sd2"]
    assert main(["prior", "import", str(pipe), "--controlnet", str(cn), "-o", str(out / "sd2")]) == 0
    return {k: out / k for k in ("authors", "sdxl", "sd2")}


def _distil(weights, tmp_path, preset_name="draft", profile=None):
    from core.engine import run_job
    from core.engine.params import JobParams
    from core.engine.presets import preset
    from core.fields.stored.artefact import LightFieldArtefact
    from core.io import write_png

    write_png(tmp_path / "in.png", torch.rand(24, 32, 3, generator=torch.Generator().manual_seed(0)).numpy())
    cfg = preset(preset_name).with_overrides({"distill": {
        "iterations": 2, "n_probes": 2, "work_height": 24, "warmup_steps": 1, "checkpoint_every": 1000,
        "supersample": 1, "threads": 1, "perceptual_weight": 0.0}})
    params = JobParams(prior="diffusion", prior_weights=str(weights), prior_profile=profile, preset=preset_name, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        result = run_job(tmp_path / "in.png", None, params, tmp_path / "art", config=cfg)
    meta = json.loads((result.path / "lightfield.json").read_text())
    env, _ = LightFieldArtefact.load(result.path).envmap(torch.tensor([0.0, 0.0, -1.0]), None, 8)
    assert torch.isfinite(env).all() and all(v == v for v in meta["training"]["loss_curve"])
    return meta


def test_authors_release_imports_and_distils_with_the_seed_profile(imported, tmp_path):
    d = imported["authors"]
    card = json.loads((d / "lightfield_prior.json").read_text())
    assert card["version"] == 2 and card["base_family"] == "sd2" and card["unet_in_channels"] == 9
    assert card["controlnet_conditioning"] == "depth" and card["profile"] == "seed" and card["multi_ball"] is True
    rec = card["imported"]["components"]
    assert (
        rec["unet"]["from_pickle"]
        and rec["vae"]["from_pickle"]
        and rec["text_encoder"]["files"] == ["pytorch_model.bin"]
    )
    assert not list(d.rglob("*.bin")) and not list(d.rglob("*.pkl"))  # safetensors only, no pickle copied
    assert not (d / "feature_extractor").exists()
    from safetensors import safe_open

    with safe_open(str(d / "vae" / "diffusion_pytorch_model.safetensors"), "pt") as f:
        assert not any(".query." in k for k in f.keys())  # deprecated attention names renamed
    meta = _distil(d, tmp_path, "seed")
    assert meta["prior"]["profile"]["name"] == "seed" and meta["engine_config"]["name"] == "seed"
    assert meta["prior"]["control_encoding"] == "authors_disparity"
    assert meta["training"]["perceptual"]["wanted"] == "lpips-vgg"


def test_diffusionlight_sdxl_release_imports_with_lora_and_distils(imported, releases, tmp_path):
    from safetensors.torch import load_file

    from core.priors.diffusion import DiffusionPrior

    d = imported["sdxl"]
    card = json.loads((d / "lightfield_prior.json").read_text())
    assert card["base_family"] == "sdxl" and card["unet_in_channels"] == 4 and card["multi_ball"] is False
    assert card["lora"]["scale"] == 0.75 and card["profile"] == "diffusionlight" and card["sampler"] == "unipc"
    assert card["imported"]["components"]["unet"]["variant"] == "fp16"
    assert card["imported"]["components"]["vae"]["source"].endswith("sdxl-vae-fp16-fix")
    # the LoRA is fused: the loaded UNet's weights differ from the file's by the LoRA's delta
    prior = DiffusionPrior.from_pretrained(d)
    raw = load_file(str(d / "unet" / "diffusion_pytorch_model.safetensors"))
    name = next(k for k in raw if k.endswith("attn1.to_q.weight"))
    fused = dict(prior.components.unet.named_parameters())[name].detach()
    lora = load_file(str(d / "lora" / "pytorch_lora_weights.safetensors"))
    key = "unet." + name[: -len(".weight")]
    delta = lora[key + ".lora.up.weight"] @ lora[key + ".lora.down.weight"]
    torch.testing.assert_close(fused, raw[name].float() + 0.75 * delta, rtol=1e-3, atol=2e-3)
    assert not any("lora" in n for n, _ in prior.components.unet.named_modules())  # plain UNet again
    meta = _distil(d, tmp_path)
    assert meta["prior"]["card"]["base_family"] == "sdxl"


def test_diffusionlight_sd2_normals_release_imports_and_distils(imported, tmp_path):
    d = imported["sd2"]
    card = json.loads((d / "lightfield_prior.json").read_text())
    assert card["controlnet_conditioning"] == "normals" and card["base_family"] == "sd2"
    meta = _distil(d, tmp_path)
    assert meta["prior"]["control_encoding"] == "normals"


def _import_error(*args, **kw) -> str:
    from core.priors.diffusion.importing import import_prior

    with pytest.raises(PriorError) as exc:
        import_prior(*args, **kw)
    return str(exc.value)


def test_wrong_folders_are_named(releases, tmp_path, capsys):
    from cli.main import main

    pipe, cn = releases["authors"]
    assert "not an existing local directory" in _import_error(
        "stabilityai/stable-diffusion-2-inpainting", tmp_path / "o"
    )
    assert "no ControlNet" in _import_error(pipe, tmp_path / "o1")
    assert "single model folder" in _import_error(cn, tmp_path / "o2")
    broken = tmp_path / "broken"
    shutil.copytree(pipe, broken)
    shutil.rmtree(broken / "vae")
    assert "vae/config.json" in _import_error(broken, tmp_path / "o3", controlnet=cn)
    renamed = tmp_path / "my-controlnet"
    shutil.copytree(cn, renamed)
    assert "--conditioning" in _import_error(pipe, tmp_path / "o4", controlnet=renamed)
    sdxl, sdxl_cn, vae, _ = releases["sdxl"]
    assert "exposure LoRA" in _import_error(sdxl, tmp_path / "o5", controlnet=sdxl_cn, vae=vae)
    assert "cross_attention_dim" in _import_error(pipe, tmp_path / "o6", controlnet=sdxl_cn, conditioning="depth")
    msg = _import_error(pipe, tmp_path / "o7", controlnet=cn, layout="diffusionlight-sdxl")
    assert "sdxl UNet" in msg and "sd2 UNet" in msg
    # a pickle that is not a weights file is refused without being run
    evil = tmp_path / "evil"
    shutil.copytree(pipe, evil)
    import os
    import pickle

    class Boom:
        def __reduce__(self):
            return (os.system, (f"touch {tmp_path / 'PWNED'}",))

    with open(evil / "unet" / "diffusion_pytorch_model.bin", "wb") as f:
        pickle.dump({"conv_in.weight": Boom()}, f)
    assert "refused" in _import_error(evil, tmp_path / "o8", controlnet=cn)
    assert not (tmp_path / "PWNED").exists() and not (tmp_path / "o8").exists()  # nothing half-written
    # wrong shapes against the config
    shapes = tmp_path / "shapes"
    shutil.copytree(pipe, shapes)
    cfg = json.loads((shapes / "unet" / "config.json").read_text())
    cfg["block_out_channels"] = [16, 64]
    (shapes / "unet" / "config.json").write_text(json.dumps(cfg))
    assert "wrong shape" in _import_error(shapes, tmp_path / "o9", controlnet=cn)
    # the CLI says it in one line, exit 2, no traceback
    assert main(["prior", "import", str(pipe), "-o", str(tmp_path / "o10")]) == 2
    err = capsys.readouterr().err
    assert "no ControlNet" in err and "Traceback" not in err


def test_bench_diffusionlight_methods_run_on_the_imported_weights(imported, tmp_path):
    from types import SimpleNamespace

    from bench.methods import core_methods, diffusion_centre_envmap
    from core.engine.presets import preset
    from core.io import write_png

    names = {m.name: m for m in core_methods(diffusionlight_weights=str(imported["sdxl"]))}
    assert names["diffusionlight"].family == "global" and names["diffusionlight-distilled"].family == "field"
    write_png(tmp_path / "in.png", torch.rand(24, 32, 3, generator=torch.Generator().manual_seed(0)).numpy())
    suite = SimpleNamespace(capture_dir=tmp_path / "in.png", global_time=0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        env = diffusion_centre_envmap(
            names["diffusionlight"], suite, preset("draft").with_overrides({"distill.work_height": 24}), 8
        )
    assert env.shape == (8, 16, 3) and torch.isfinite(env).all() and float(env.max()) > 0


def test_gpu_bench_script_runs_tiny_on_cpu():
    from bench.diffusion_gpu import main

    out = main(["--tiny", "--device", "cpu", "--dtype", "fp32", "--steps", "1", "--warmup", "0", "--frame", "32x32"])
    assert out["steps_timed"] == 1 and out["seconds_per_step_mean"] > 0 and out["projection"]["iterations"] == 3000
