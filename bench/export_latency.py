"""Time the hand-off products on one env map (CPU, this process): main-light fit, prefiltered
cube mips, KTX2, glTF, USDZ, and encoding a 2K (1024 x 2048) EXR with metadata.

    OMP_WAIT_POLICY=PASSIVE python bench/export_latency.py [--reps 5]

The map is the simulator's ground truth at the demo room's first probe (no field evaluation:
that cost is bench/service_latency.py's). Prints one JSON line per product: median and max
seconds over the repetitions.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def timed(fn, reps: int) -> dict:
    fn()  # warm-up (caches, lazy imports)
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return {"median_s": round(statistics.median(times), 4), "max_s": round(max(times), 4), "reps": reps}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--reps", type=int, default=5)
    args = p.parse_args()
    import torch

    from core.envmap import resize_envmap
    from core.export import products
    from core.export.metadata import envmap_attributes
    from core.io.envmap_io import encode_envmap
    from core.lights import extract_dominant_light
    from core.sim.render import render_envmap
    from core.sim.suites import suite

    scene = suite("spatial")
    x = scene.probes[0].x
    big = render_envmap(scene, x, 0.0, height=256)
    env = {h: resize_envmap(big, h) for h in (64, 128)}
    env[256] = big
    env_2k = (
        torch.nn.functional.interpolate(big.permute(2, 0, 1)[None], size=(1024, 2048), mode="bilinear")[0]
        .permute(1, 2, 0)
        .contiguous()
        .numpy()
    )
    cases = {
        "main light fit, 128x256 map": lambda: extract_dominant_light(env[128]),
        "prefiltered cube 64 (5 mips)": lambda: products.prefiltered(env[128], 64),
        "prefiltered cube 128 (6 mips)": lambda: products.prefiltered(env[256], 128),
        "ktx2 cube 64": lambda: products.cube_ktx2(env[128], 64),
        "glb 64": lambda: products.probe_glb(env[128], x, 0.0, 64),
        "usdz 256x512": lambda: products.probe_usdz(env[256], x, 0.0),
        "2K EXR encode + metadata": lambda: encode_envmap(env_2k, "exr", attributes=envmap_attributes(x, 0.0, "bench")),
    }
    for name, fn in cases.items():
        print(json.dumps({"product": name, **timed(fn, args.reps), "threads": torch.get_num_threads()}), flush=True)
    for ratio in (1, 2):  # what the prefilter's source resolution costs and buys
        print(
            json.dumps({"prefilter_source_ratio": ratio, **prefilter_accuracy(env[128], env[256], ratio, args.reps)}),
            flush=True,
        )
    return 0


def prefilter_accuracy(env, reference_env, ratio: int, reps: int) -> dict:
    """Time of a 64-texel prefiltered cube and the sum-relative error of its rough levels against
    direct quadrature of the same GGX kernel over the 256-row map."""
    import torch

    from core.conventions import equirect_directions
    from core.cubemap import cubemap_directions
    from core.envmap import solid_angles
    from core.export import prefilter

    old = prefilter.QUADRATURE_SOURCE_RATIO
    prefilter.QUADRATURE_SOURCE_RATIO = ratio
    try:
        cost = timed(lambda: prefilter.prefiltered_cubemap(env, 64), reps)
        mips = prefilter.prefiltered_cubemap(env, 64)
    finally:
        prefilter.QUADRATURE_SOURCE_RATIO = old
    h = reference_env.shape[0]
    d = equirect_directions(h, dtype=torch.float64).reshape(-1, 3)
    radiance = reference_env.double().reshape(-1, 3) * solid_angles(h, dtype=torch.float64).reshape(-1, 1)
    errors = {}
    for i in range(1, len(mips)):
        n = cubemap_directions(mips[i].shape[1], dtype=torch.float64).reshape(-1, 3)
        w = prefilter.lobe_weight(n @ d.T, prefilter.roughness_of_level(i, len(mips)))
        ref = (w @ radiance) / (w @ solid_angles(h, dtype=torch.float64).reshape(-1, 1))
        errors[f"roughness {prefilter.roughness_of_level(i, len(mips)):.2f}"] = round(
            float((mips[i].reshape(-1, 3).double() - ref).abs().sum() / ref.abs().sum()), 4)
    return {**cost, "sum_relative_error": errors}


if __name__ == "__main__":
    sys.exit(main())
