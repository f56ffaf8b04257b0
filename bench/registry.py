"""Benches by name: the one front door to bench/ (`lightfield bench list`, `lightfield bench run
NAME [--quick] [ARGS ...]`). A bench is one module with a `python -m` entry point plus its line
here; a module under bench/ that is not a bench is named in LIBRARIES, and
tests/test_bench_registry.py holds both lists against the files.

The table is data, not decorators in the bench modules: listing must not import them (most
import torch, some start servers), and each bench runs in its own process, as its docstring
shows it run, so a bench that starts subprocesses finds the repository on their path."""
from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Bench:
    name: str
    module: str  # run as `python -m module`
    summary: str
    quick: tuple[str, ...] | None = None  # arguments of `--quick` (None: the bench has no quick mode)
    leading: tuple[str, ...] = ()  # arguments before the user's (a subcommand)
    kind: str = "bench"  # "bench", or "calibration": fits constants that are pasted into core/

    def command(self, args: list[str], quick: bool = False) -> list[str]:
        if quick and self.quick is None:
            raise ValueError(f"bench {self.name!r} has no quick mode; run it without --quick")
        return [sys.executable, "-m", self.module, *self.leading, *(self.quick if quick else ()), *args]


BENCHES: dict[str, Bench] = {}


def register_bench(bench: Bench) -> Bench:
    if BENCHES.get(bench.name, bench) != bench:
        raise ValueError(f"bench {bench.name!r} is already registered as {BENCHES[bench.name].module}")
    BENCHES[bench.name] = bench
    return bench


def bench(name: str) -> Bench:
    if name not in BENCHES:
        raise ValueError(f"unknown bench {name!r}; `lightfield bench list` shows {len(BENCHES)}: {', '.join(BENCHES)}")
    return BENCHES[name]


def run_bench(name: str, args: list[str], quick: bool = False) -> int:
    """Run one bench in a child process from the repository root; its exit status."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    return subprocess.call(bench(name).command(args, quick), cwd=REPO, env=env)


# Modules under bench/ that are imported by benches, not run on their own.
LIBRARIES = (
    "bench",
    "bench.calibration",
    "bench.methods",  # the methods `lightfield bench` compares
    "bench.overrides",  # `--set key=value` parsing
    "bench.panoramas",  # the panorama set (MANIFEST.tsv) and the camera that looks into a panorama
    "bench.report",  # results.json -> results.md, plots and the README table
    "bench.registry",
    "bench.run",  # the suite's driver (registered as "suite" through the CLI)
    "bench.scaling",  # the suite's scaling section (its `--point` is the child it forks)
    "bench.tracking",  # the suite's tracking section and the clips other benches reuse
    "bench.hostile_inputs",  # hostile files generated in code (tests and hostile_uploads)
    "bench.pbr",  # Mitsuba rooms, cameras and truth of pbr_sessions
    "bench.suite",  # simulated suites and their scoring
)

_SPLIT = ("--split", "dev", "--limit", "1")
for _b in (
    Bench("suite", "cli", "accuracy vs time: simulated suites, real panoramas, scaling, stability, tracking "
          "(`lightfield bench [--quick]`, what `make bench` runs)", quick=("--quick",), leading=("bench",)),
    # what a user gets, on real panoramas
    Bench("real_panoramas", "bench.real_panoramas", "one photo of a panorama room -> estimate -> env map, "
          "against the panorama", quick=("--limit", "1")),
    Bench("room_scans", "bench.room_scans", "a phone's room scan (plain MP4) of each panorama room, end to end"),
    Bench("auto_exposure_pans", "bench.auto_exposure_pans", "pans under an unrecorded auto-exposure", quick=_SPLIT),
    Bench("handheld", "bench.handheld", "tracking under motion blur, rolling shutter and noise", quick=_SPLIT),
    Bench("transients", "bench.transients", "a person walking through a static view: light change or painted out",
          quick=_SPLIT),
    Bench("sfm_starts", "bench.sfm_starts", "each COLMAP initial pair on handheld walks, and the one kept",
          quick=_SPLIT),
    Bench("photo_colour", "bench.photo_colour", "what decides a single photo's diffuse angle (shortcuts)",
          quick=("--limit", "1")),
    Bench("unseen_shape_fit", "bench.unseen_shape_fit", "whether a photo predicts the unseen light's shape"),
    Bench("camera_response", "bench.camera_response", "per camera curve, from room-scan and photo reports"),
    Bench("pbr_sessions", "bench.pbr_sessions", "AR sessions in Mitsuba-rendered rooms (needs mitsuba)",
          quick=("--quick",)),
    Bench("live_sessions", "bench.live_sessions", "captures replayed as live sessions: latency, versions, load"),
    Bench("self_check_flags", "bench.self_check_flags", "the job's self-check: faults flagged, good answers kept",
          quick=("--rooms", "1")),
    # the simulator's suites
    Bench("accuracy_probe", "bench.accuracy_probe", "the draft field vs its prior vs a constant map, per suite",
          quick=("--suites", "spatial")),
    Bench("ablate_simulator", "bench.ablate_simulator", "each accuracy mechanism of the draft off on its own"),
    Bench("temporal_stretches", "bench.temporal_stretches", "frame by frame, the draft between `temporal`'s switches"),
    Bench("in_view_switch", "bench.in_view_switch", "a light switching off inside the photo"),
    Bench("clip_tracks", "bench.clip_tracks", "a static camera's clipped sources over time vs the truth"),
    Bench("pan_light_changes", "bench.pan_light_changes", "a pan's temporal decision: pools switching off, figures"),
    # cost
    Bench("presets", "bench.presets", "CPU and wall time of the CPU presets on their clips",
          quick=("--presets", "draft")),
    Bench("sim_speed", "bench.sim_speed", "the simulator: one frame and 9 env maps", quick=("--repeats", "1")),
    Bench("query_latency", "bench.query_latency", "query latency per field kind, exact vs baked", quick=("--quick",)),
    Bench("export_latency", "bench.export_latency", "the hand-off products (KTX2, glTF, USDZ, 2K EXR)",
          quick=("--reps", "1")),
    Bench("service_latency", "bench.service_latency", "one client over HTTP vs bare evaluation",
          quick=("--reps", "10")),
    Bench("service_load", "bench.service_load", "the service under 100 clients; fast and baked vs exact"),
    Bench("upload_cost", "bench.upload_cost", "decodes and API memory per upload"),
    Bench("hostile_uploads", "bench.hostile_uploads", "what hostile uploads cost the API"),
    Bench("storage_fetch", "bench.storage_fetch", "what a shared S3-compatible store costs a query"),
    Bench("ui_latency", "bench.ui_latency", "the web page's endpoints", quick=("--repeats", "2")),
    Bench("diffusion_step", "bench.diffusion_step", "one diffusion prior step on this CPU"),
    Bench("diffusion_gpu", "bench.diffusion_gpu", "the diffusion prior's step at SD-2 sizes on a GPU"),
    # calibration: fits the constants pasted into core/
    Bench("clip_rule", "bench.calibration.clip_rule", "the clip rule's coefficients and spill colour "
          "(core/capture/highlights.py)", kind="calibration"),
    Bench("indoor_fill", "bench.calibration.indoor_fill", "the indoor fill's elevation gain "
          "(core/priors/indoor_fill.py)", kind="calibration"),
):
    register_bench(_b)
