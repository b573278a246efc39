"""The setting a run was measured in: ``machine()``, what its floating-point results depend on
(written into the benchmarks' JSON), and ``setting_line()``, the line a speed script prints
first: the CPU, the kernels torch dispatches to there, torch's threads, and the versions of
Python and of the packages timed. Ratios measured in one run compare methods on one machine;
the absolute times, and how far DIPOLE's ratios sit from their targets, follow the machine's
cost per torch call (docs/benchmarks/speed.md), so a figure is read beside its setting."""

from __future__ import annotations

import importlib.metadata
import os
import platform
from collections.abc import Sequence
from pathlib import Path

import torch

PACKAGES = ("torch", "numpy", "cma", "pynmmso")


def cpu_model() -> str:
    """The CPU's model name (Linux's ``/proc/cpuinfo``; elsewhere what ``platform`` knows)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() in ("model name", "Model", "Hardware") and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "an unknown CPU"


def machine() -> dict[str, str | int]:
    """What the runs' floating-point results depend on beyond the code and the seeds: the
    architecture, the CPU kernels torch dispatches to (``AVX512``, ``AVX2``, …) and its
    threads. Long runs of the same seed on another CPU diverge once a rounding differs (see
    docs/benchmarks/index.md, *Reproducing the numbers*)."""
    return {
        "architecture": platform.machine(),
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "torch_threads": torch.get_num_threads(),
    }


def version(package: str) -> str | None:
    """The installed version of the distribution ``package``, ``None`` if it is not installed."""
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return None


def setting_line(packages: Sequence[str] = PACKAGES, threads: bool = True) -> str:
    """``"setting: <CPU> (<cores> cores, torch's <capability> kernels[, <n> torch thread(s)]);
    Python <version>; <package> <version>, ..."``, the packages that are installed.

    Args:
        packages: the distributions whose versions to name (those not installed are left out).
        threads: name torch's threads in this process (a script that times other processes
            passes ``False``).
    """
    where = machine()
    cpu = f"{os.cpu_count()} cores, torch's {where['torch_cpu_capability']} kernels"
    if threads:
        count = where["torch_threads"]
        cpu += f", {count} torch thread{'s' if count != 1 else ''}"
    # torch's own string names its build (+cpu, +cu130), which its distribution's may not.
    found = {p: torch.__version__ if p == "torch" else version(p) for p in packages}
    versions = [f"{p} {v}" for p, v in found.items() if v is not None]
    return f"setting: {cpu_model()} ({cpu}); Python {platform.python_version()}; " + ", ".join(
        versions
    )
