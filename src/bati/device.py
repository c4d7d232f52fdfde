"""The machine a run trained on, as its records name it (eval.json's `device`, benchmarks' headers)."""

from __future__ import annotations

import os
import platform
from pathlib import Path

import jax

__all__ = ["cpu_model", "describe_device", "machine_record", "usable_cores"]


def describe_device() -> str:
    """The accelerator JAX runs on, as JAX reports it (e.g. "gpu: NVIDIA H100 80GB HBM3 x1"); on a CPU its
    model too (e.g. "cpu: 2-core AMD EPYC (x86_64) x1"): XLA's kernels, and with them the last bits of a float,
    differ between CPU models, which a chaotic MuJoCo rollout amplifies (docs/reliability.md)."""
    devices = jax.devices()
    first = devices[0]
    kind = first.device_kind if first.platform != "cpu" else f"{os.cpu_count()}-core {cpu_model()} ({platform.machine()})"
    return f"{first.platform}: {kind} x{len(devices)}"


def usable_cores() -> int:
    """The CPU cores this process may run on: its affinity, which `taskset` narrows. XLA splits a CPU
    computation over them, and with them the order of its sums: one machine gives other numbers on one core
    than on two (docs/reliability.md)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity outside Linux
        return os.cpu_count() or 1


def machine_record() -> dict:
    """What a run's records say of its machine: the device, the cores it could use, JAX's version."""
    return {"device": describe_device(), "cpu_cores": usable_cores(), "jax_version": jax.__version__}


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The CPU's model name from /proc/cpuinfo, with its widest vector instructions where the flags name them
    (e.g. "AMD EPYC, AVX-512"): XLA picks its CPU kernels by them, and two machines that both call themselves
    "AMD EPYC" gave different AntDir data for the same seed, one with AVX-512 and one without (docs/reliability.md).
    "CPU" where there is no model name (e.g. not on Linux)."""
    try:
        lines = cpuinfo.read_text().splitlines()
    except OSError:
        return "CPU"
    field = lambda key: next((line.split(":", 1)[1] for line in lines if line.startswith(key) and ":" in line), "")  # noqa: E731
    model, flags = " ".join(field("model name").split()) or "CPU", set(field("flags").split())
    vector = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "AVX" if "avx" in flags else ""
    return f"{model}, {vector}" if vector and model != "CPU" else model
