"""A light switching off INSIDE the photo, at the camera (docs/engine.md, view detail limits).

The simulator's `spatial` photo (96x72, file depth) held for 8 frames at 2 fps by a static
camera; a 10x14-pixel patch is clipped white in frames 0-3 and dark (0.2) in frames 4-7. The
draft (600 steps, time input on) is distilled from the reprojection prior; the field's map at
the camera (128 rows) is read along the patch's pixel rays at frame 1 and frame 6 and compared
with the linearised frames (before the switch the prior's clip rule boosts the clipped patch,
so the field is expected above the frame there).

    python -m bench.in_view_switch [--set field.view_detail_time_rank=0 ...]
    # prints field / frame over the patch's rays: the ratio of means and the median ray
"""
from __future__ import annotations

import pathlib
import tempfile

import torch


def main(argv: list[str] | None = None) -> int:
    import argparse

    from bench.overrides import parse_set

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--set", action="append", default=[], help="draft preset override key=value (JSON value)")
    overrides = parse_set(p.parse_args(argv).set)
    from core.capture.load import capture_from_arrays
    from core.capture.prepare import load_prepared_capture
    from core.conventions import inverse_tonemap
    from core.engine.distill import distill
    from core.engine.presets import preset
    from core.envmap import sample_envmap
    from core.priors.reprojection import ReprojectionPrior
    from core.sim.capture import write_capture
    from core.sim.suites import spatial

    torch.set_num_threads(1)
    spec = spatial().model_copy(update={"resolution": (96, 72)})
    out = pathlib.Path(tempfile.mkdtemp())
    write_capture(spec, out, envmap_height=16, video=False)
    base = load_prepared_capture(out)
    frames = base.frames[0].expand(8, -1, -1, -1).clone()
    h, w = frames.shape[1:3]
    patch = torch.zeros(h, w, dtype=torch.bool)
    patch[h // 4:h // 4 + 10, w // 2:w // 2 + 14] = True
    frames[:4, patch] = 1.0
    frames[4:, patch] = 0.2
    cap = capture_from_arrays(frames, base.depth[:1].expand(8, -1, -1), intrinsics=base.intrinsics,
                              poses=base.poses[:1].expand(8, -1, -1), fps=2.0)
    prior = ReprojectionPrior(env_height=24)
    prior.bind(cap, lighting_changes=True)
    field = distill(cap, prior, preset("draft").with_overrides({"distill.checkpoint_every": 1000, **overrides}),
                    uses_time=True, seed=0).field
    cam = cap.camera(0)
    rays = cam.pixel_rays()[1][patch]
    for i in (1, 6):
        with torch.no_grad():
            env = field.envmaps(cam.position[None].float(), torch.tensor([float(cap.times[i])]), 128)[0]
        along, seen = sample_envmap(env, rays), inverse_tonemap(cap.frames[i])[patch]
        pred, frame = float(along.mean()), float(seen.mean())
        median = float((along.mean(-1) / seen.mean(-1).clamp_min(1e-12)).median())
        print(f"frame {i} ({'before' if i < 4 else 'after'} the switch): field {pred:.3f}, frame {frame:.3f}, "
              f"ratio {pred / frame:.2f}, median ray {median:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
