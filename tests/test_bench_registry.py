"""bench/registry.py, the front door to bench/: every bench module is registered or declared a
library, `lightfield bench list` names every registered bench, and `lightfield bench run` runs one."""
from __future__ import annotations

from pathlib import Path

import pytest

from bench.registry import BENCHES, LIBRARIES, Bench, bench
from cli.main import build_parser, main

BENCH_DIR = Path(__file__).resolve().parents[1] / "bench"


def bench_modules() -> set[str]:
    """Every module under bench/ (a package counts once, by its name: its files belong to it)."""
    found = set()
    for path in BENCH_DIR.rglob("*.py"):
        parts = path.relative_to(BENCH_DIR.parent).with_suffix("").parts
        if "results" in parts:
            continue
        parts = parts[:-1] if parts[-1] == "__init__" else parts
        found.add(".".join(parts))
    return found


def _owned(module: str, names: set[str]) -> bool:
    return any(module == n or module.startswith(n + ".") for n in names)


def test_every_bench_module_is_registered_or_a_library():
    registered = {b.module for b in BENCHES.values()}
    libraries = set(LIBRARIES)
    # a package in LIBRARIES (bench.suite, bench.pbr) owns its modules; bench.calibration does not
    packages = libraries - {"bench", "bench.calibration"}
    stray = sorted(m for m in bench_modules() if m not in registered | libraries and not _owned(m, packages))
    assert not stray, f"register these in bench/registry.py or name them in LIBRARIES: {stray}"
    gone = sorted(m for m in registered - {"cli"} if m not in bench_modules())
    assert not gone, f"registered benches without a module: {gone}"
    assert not registered & libraries


def test_calibration_scripts_live_in_their_package():
    calibration = {b.module for b in BENCHES.values() if b.kind == "calibration"}
    assert calibration == {m for m in bench_modules() if m.startswith("bench.calibration.")}
    assert calibration >= {"bench.calibration.clip_rule", "bench.calibration.indoor_fill"}


def test_bench_list_names_every_registered_bench(capsys):
    assert main(["bench", "list"]) == 0
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert listed == list(BENCHES)


def test_run_passes_quick_as_the_bench_s_own_arguments():
    presets = bench("presets")
    cmd = presets.command(["--set", "x=1"], quick=True)
    assert cmd[1:] == ["-m", "bench.presets", "--presets", "draft", "--set", "x=1"]
    assert bench("suite").command([], quick=True)[1:] == ["-m", "cli", "bench", "--quick"]


def test_unknown_bench_and_missing_quick_mode_are_clear_errors():
    with pytest.raises(SystemExit, match="unknown bench 'nope'.*clip_rule"):
        main(["bench", "run", "nope"])
    with pytest.raises(SystemExit, match="'indoor_fill' has no quick mode"):
        main(["bench", "run", "indoor_fill", "--quick"])
    with pytest.raises(ValueError, match="already registered"):
        from bench.registry import register_bench

        register_bench(Bench("presets", "bench.other", "x"))


def test_run_executes_the_bench_in_its_own_process(capfd):
    assert main(["bench", "run", "indoor_fill", "--", "--help"]) == 0
    assert "ELEVATION_GAIN" in capfd.readouterr().out


def test_the_suite_s_own_options_still_parse_without_a_subcommand():
    """`make bench` runs `lightfield bench --quick -o bench/results`."""
    args = build_parser().parse_args(["bench", "--quick", "-o", "bench/results", "--sections", "scaling"])
    assert args.quick and args.out == "bench/results" and args.bench_command is None
