"""Convert one pickled PyTorch checkpoint (`*.bin`) to safetensors in a bounded child process.

A `.bin` file is a pickle: unpickling it can run code. The project never unpickles at run
time. This one-time conversion uses `torch.load(weights_only=True)` -- torch's restricted
unpickler that only rebuilds tensors and plain containers -- and runs it in a child process
with resource limits (address space, CPU seconds, size of any file it writes, open files)
and a wall-clock timeout, so a hostile or corrupt file can at worst fail the import.

    python -m core.priors.diffusion.importing.safe_convert SRC.bin DST.safetensors [SRC DST ...]

One child converts all the files of an import (torch starts once); its limits are sized
for the largest file. It prints one JSON line per file ({"tensors": n, "bytes": b,
"dtypes": [...]}); on bad content it exits 2 with one line on stderr naming the file and
the problem.
"""
from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import torch

EXIT_BAD_CONTENT = 2
GIB = 1 << 30


@dataclass(frozen=True)
class ConvertLimits:
    """Bounds of one conversion child. Memory is the address-space limit: torch itself needs
    about 2 GiB of it, the memory-mapped checkpoint its size, and writing it once more."""

    base_memory_bytes: int = 3 * GIB
    memory_per_checkpoint_byte: float = 2.5
    cpu_seconds: int = 900
    wall_seconds: float = 1200.0
    max_output_factor: float = 1.5  # output safetensors <= this x input size (+ 1 MiB of header)

    def memory_for(self, size: int) -> int:
        return int(self.base_memory_bytes + self.memory_per_checkpoint_byte * size)


class ConvertError(RuntimeError):
    pass


def convert_bin(src: Path, dst: Path, limits: ConvertLimits = ConvertLimits()) -> dict:
    """Run the child on `src`, writing `dst`; returns its summary or raises ConvertError."""
    return convert_bins([(src, dst)], limits)[0]


def convert_bins(pairs: list[tuple[Path, Path]], limits: ConvertLimits = ConvertLimits()) -> list[dict]:
    """Convert every (src, dst) pair in one bounded child; raises ConvertError naming the failing file."""
    if not pairs:
        return []
    size = max(src.stat().st_size for src, _ in pairs)
    src, dst = pairs[0]
    mem, out_max = limits.memory_for(size), int(limits.max_output_factor * size) + (1 << 20)

    def bound():  # runs in the child between fork and exec
        resource.setrlimit(resource.RLIMIT_AS, (mem, mem))
        resource.setrlimit(resource.RLIMIT_CPU, (limits.cpu_seconds, limits.cpu_seconds))
        resource.setrlimit(resource.RLIMIT_FSIZE, (out_max, out_max))
        os.setsid()

    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "PYTHONPATH": str(Path(__file__).resolve().parents[4]),
           "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1", "PYTHONDONTWRITEBYTECODE": "1"}
    cmd = [sys.executable, "-m", "core.priors.diffusion.importing.safe_convert"]
    cmd += [str(p) for pair in pairs for p in pair]
    try:
        proc = subprocess.run(cmd, stdin=subprocess.DEVNULL, capture_output=True, text=True, env=env,
                              cwd=str(dst.parent), preexec_fn=bound, timeout=limits.wall_seconds)
    except subprocess.TimeoutExpired:
        _remove([d for _, d in pairs])
        raise ConvertError(f"{src}: conversion took longer than {limits.wall_seconds:.0f} s and was stopped") from None
    summaries = []
    for line in proc.stdout.strip().splitlines():
        try:
            summaries.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    if proc.returncode == 0:
        if len(summaries) != len(pairs):
            raise ConvertError(f"{src}: the converter gave {len(summaries)} summaries for {len(pairs)} files")
        return summaries
    _remove([d for _, d in pairs])
    src = pairs[min(len(summaries), len(pairs) - 1)][0]  # the file being converted when it stopped
    last = (proc.stderr.strip().splitlines() or [""])[-1]
    if proc.returncode == EXIT_BAD_CONTENT:
        raise ConvertError(last)
    if proc.returncode in (-signal.SIGXCPU, -signal.SIGKILL):
        raise ConvertError(f"{src}: conversion hit its CPU-time limit ({limits.cpu_seconds} s)")
    if proc.returncode == -signal.SIGXFSZ:
        raise ConvertError(f"{src}: conversion tried to write more than {out_max} bytes")
    if (
        "MemoryError" in proc.stderr
        or "Cannot allocate memory" in proc.stderr
        or "std::bad_alloc" in proc.stderr
        or "failed to map" in proc.stderr
    ):
        raise ConvertError(f"{src}: conversion needed more than its memory limit ({mem / GIB:.1f} GiB)")
    raise ConvertError(f"{src}: conversion failed (exit {proc.returncode}): {last[-300:]}")


def _remove(paths) -> None:
    for p in paths:
        Path(p).unlink(missing_ok=True)


def _tensors_only(obj) -> dict:
    if isinstance(obj, dict) and "state_dict" in obj and isinstance(obj["state_dict"], dict) and len(obj) <= 4:
        obj = obj["state_dict"]  # some trainers wrap the weights; everything else in the wrapper is dropped
    if not isinstance(obj, dict) or not obj:
        raise ValueError(f"expected a non-empty mapping of parameter names to tensors, found {type(obj).__name__}")
    bad = [k for k, v in obj.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)]
    if bad:
        raise ValueError(f"{len(bad)} entries are not tensors (e.g. {str(bad[0])[:80]!r}); not a weights file")
    return obj


def _child(src: str, dst: str) -> int:
    from safetensors.torch import save_file  # noqa: PLC0415 — safetensors is heavy: imported when used

    try:
        try:
            raw = torch.load(src, map_location="cpu", weights_only=True, mmap=True)
        except RuntimeError as exc:  # the legacy (pre-zip) format cannot be memory-mapped
            if "mmap" not in str(exc):
                raise
            raw = torch.load(src, map_location="cpu", weights_only=True)
        state = _tensors_only(raw)
    except Exception as exc:  # noqa: BLE001 - any failure to read is "bad content", reported in one line
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        if "Weights only load failed" in msg:
            msg = "it holds objects other than tensors; refused (unpickling them could run code)"
        print(f"{src}: cannot read it as a weights-only checkpoint: {msg[:300]}", file=sys.stderr)
        return EXIT_BAD_CONTENT
    # safetensors refuses tensors that share memory (tied weights): give each its own copy
    out, ptrs = {}, set()
    for k, v in state.items():
        t = v.contiguous()
        if t.untyped_storage().data_ptr() in ptrs:
            t = t.clone()
        ptrs.add(t.untyped_storage().data_ptr())
        out[k] = t
    save_file(out, dst, metadata={"format": "pt", "converted_from": os.path.basename(src)})
    print(json.dumps({"tensors": len(out), "bytes": sum(t.numel() * t.element_size() for t in out.values()),
                      "dtypes": sorted({str(t.dtype).replace("torch.", "") for t in out.values()})}), flush=True)
    return 0


if __name__ == "__main__":
    args = sys.argv[1:]
    if not args or len(args) % 2:
        print(
            "usage: python -m core.priors.diffusion.importing.safe_convert SRC.bin DST.safetensors [...]",
            file=sys.stderr,
        )
        sys.exit(EXIT_BAD_CONTENT)
    for i in range(0, len(args), 2):
        rc = _child(args[i], args[i + 1])
        if rc:
            sys.exit(rc)
    sys.exit(0)
