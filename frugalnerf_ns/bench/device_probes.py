"""What the device checks measure with: a device synchronised around timed calls, peak memory, where a step's
tensors live, and how often the CPU-only grid-sample backward runs (``gpu_check`` and the GPU benchmarks)."""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import resource
import statistics
import time
from typing import Any, Callable, Dict, Iterator, List

import torch


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def reset_peak(device: torch.device) -> None:
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


def peak_mib(device: torch.device) -> float:
    """Peak allocated GPU memory since the last reset; on the CPU the process's peak RSS (never reset)."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def timed(fn: Callable[[], Any], device: torch.device, repeats: int, warmup: int) -> float:
    """Median seconds of ``fn`` after ``warmup`` calls, synchronised around each call."""
    for _ in range(warmup):
        fn()
    synchronize(device)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def misplaced(tensors: Iterator[tuple], device: torch.device) -> List[str]:
    """Names of tensors that are not on ``device``'s type."""
    return [name for name, t in tensors if isinstance(t, torch.Tensor) and t.device.type != device.type]


def walk(name: str, value: Any) -> Iterator[tuple]:
    """(dotted name, tensor) for every tensor in nested dicts, lists and dataclasses (a step's StepRender)."""
    if isinstance(value, torch.Tensor):
        yield name, value
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        for item in dataclasses.fields(value):
            yield from walk(f"{name}.{item.name}", getattr(value, item.name))
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from walk(f"{name}.{key}", item)
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            yield from walk(f"{name}[{i}]", item)


@contextlib.contextmanager
def count_cpu_path_calls() -> Iterator[Dict[str, int]]:
    """Count calls of the CPU-only grid-sample backward (``_BilinearSampleCPU``), split by the plane's device."""
    from frugalnerf_ns.field import tensorial

    counts = {"cpu": 0, "cuda": 0}
    original = tensorial._BilinearSampleCPU.apply

    def counting(plane, x, y, *rest):
        counts[plane.device.type] = counts.get(plane.device.type, 0) + 1
        return original(plane, x, y, *rest)

    tensorial._BilinearSampleCPU.apply = counting  # type: ignore[method-assign]
    try:
        yield counts
    finally:
        tensorial._BilinearSampleCPU.apply = original  # type: ignore[method-assign]
