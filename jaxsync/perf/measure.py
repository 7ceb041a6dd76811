"""Measuring the machine: the one best-of timing harness, and the rates it is compared with.

Every wall-clock measurement of jaxsync and its benchmarks goes through
:func:`sample_times`: each call is run once untimed (compilation, first touch of the
pages), then ``repeats`` timed rounds run every call once each, round-robin, so that a
slow drift of the machine's load hits all calls alike; a call's result is waited for
(``jax.block_until_ready``) before its clock stops. On a shared machine the best round
of a call is the one the OS did not interrupt: :func:`best_times` keeps it.

Rates of the machine, for the roofline (:mod:`jaxsync.perf.roofline` only counts):

    :func:`copy_bandwidth`    read + write bytes per second of ``numpy.copyto`` between
                              two float64 arrays [bytes/s]
    :func:`matmul_flop_rate`  2 n^3 flops per second of a jitted (n, n) x (n, n) product
                              [flop/s]

and :func:`describe_devices`, the line a report prints about the devices it ran on.
"""

from __future__ import annotations

import math
import os
import time
from typing import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ProblemError
from ..parallel.devices import device_summary

__all__ = ["sample_times", "best_times", "best_time", "per_step_times", "copy_bandwidth",
           "matmul_flop_rate", "describe_devices"]

F64 = 8  # bytes per float64


def _positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ProblemError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def sample_times(calls: Mapping[str, tuple[Callable, tuple]], repeats: int, *,
                 clock: Callable[[], float] = time.perf_counter) -> dict:
    """Wall times of every call in every round.

    Args:
        calls: {name: (fn, args)}; ``fn(*args)`` is one timed call (its result, any
            pytree of arrays or None, is waited for).
        repeats: timed rounds (after one untimed warm-up call of each).
        clock: the clock [s] (``time.perf_counter``; tests pass a fake one).

    Returns:
        {name: (repeats,) float array of wall times [s]}, in the order of ``calls``.

    Raises:
        ProblemError: ``repeats`` not a positive integer, or no calls.
    """
    repeats = _positive_int(repeats, "repeats")
    if not calls:
        raise ProblemError("sample_times needs at least one call to time")
    for fn, args in calls.values():
        jax.block_until_ready(fn(*args))
    samples = {name: np.empty(repeats) for name in calls}
    for k in range(repeats):
        for name, (fn, args) in calls.items():
            start = clock()
            jax.block_until_ready(fn(*args))
            samples[name][k] = clock() - start
    return samples


def best_times(calls: Mapping[str, tuple[Callable, tuple]], repeats: int, *,
               clock: Callable[[], float] = time.perf_counter) -> dict:
    """{name: the best wall time [s]} of :func:`sample_times`."""
    return {name: float(t.min()) for name, t in sample_times(calls, repeats, clock=clock).items()}


def best_time(fn: Callable, repeats: int, *args, clock: Callable[[], float] = time.perf_counter) -> float:
    """The best wall time [s] of ``fn(*args)`` over ``repeats`` timed calls (after one
    untimed warm-up call)."""
    return best_times({"fn": (fn, args)}, repeats, clock=clock)["fn"]


def per_step_times(best: Mapping[str, float], n_steps: int, call: str = "call") -> dict:
    """Per-step times [s] of calls that each advance ``n_steps`` steps.

    ``best[call]`` is the wall time of a call that does no step (dispatch, argument
    handling): it is removed from every other entry before dividing by ``n_steps``, and
    a difference below 0 (noise) is clipped to 0.

    Returns:
        {name: seconds per step} for every name except ``call``.
    """
    n_steps = _positive_int(n_steps, "n_steps")
    if call not in best:
        raise ProblemError(f"per_step_times needs the time of a call that does no step, "
                           f"{call!r}; got {sorted(best)}")
    return {name: max(t - best[call], 0.0) / n_steps for name, t in best.items() if name != call}


def copy_bandwidth(n_bytes: float = 400e6, repeats: int = 5, *,
                   clock: Callable[[], float] = time.perf_counter) -> float:
    """The machine's memory bandwidth [bytes/s]: read + write bytes (2 ``n_bytes``) of
    ``numpy.copyto`` between two float64 arrays of ``n_bytes`` bytes each, best of
    ``repeats`` (after a first copy that touches the pages). Use an array well above the
    caches (the default 400 MB) for the memory bandwidth; small sizes measure a cache.

    Raises:
        ProblemError: n_bytes below 8 or repeats below 1.
    """
    if not (isinstance(n_bytes, (int, float, np.integer, np.floating)) and math.isfinite(n_bytes)
            and n_bytes >= F64):
        raise ProblemError(f"n_bytes must be a finite size >= 8 bytes, got {n_bytes!r}")
    repeats = _positive_int(repeats, "repeats")
    a = np.random.default_rng(0).random(int(n_bytes) // F64)
    b = np.empty_like(a)
    best = best_time(np.copyto, repeats, b, a, clock=clock)
    return 2 * a.nbytes / max(best, 1e-12)


def matmul_flop_rate(n: int = 1024, dtype: str = "float32", repeats: int = 5, *,
                     clock: Callable[[], float] = time.perf_counter) -> float:
    """The machine's attainable floating-point rate [flop/s]: 2 n^3 flops of a jitted
    (n, n) x (n, n) ``jnp.dot`` in ``dtype`` on the default device, best of ``repeats``
    after a warm-up call. float32 is what the surrogates compute in; use it as the flop
    roof of t_d.

    Raises:
        ProblemError: n or repeats below 1, or an unknown dtype.
    """
    n = _positive_int(n, "n")
    repeats = _positive_int(repeats, "repeats")
    if dtype not in ("float32", "float64"):
        raise ProblemError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    a = jnp.asarray(np.random.default_rng(0).random((n, n)), dtype=dtype)
    best = best_time(jax.jit(jnp.dot), repeats, a, a, clock=clock)
    return 2.0 * n ** 3 / max(best, 1e-12)


def describe_devices(devices) -> str:
    """One line about ``devices``: count, platform, kind, and whether they are emulated
    host devices sharing this machine's cores (then a collective between them is a
    meeting of threads, not a message)."""
    info = device_summary(devices)
    text = f"{info['n_devices']} x {info['platform']} device ({info['device_kind']})"
    if info["emulated"]:
        text += f", emulated host devices sharing {os.cpu_count()} CPU cores"
    elif info["platform"] == "cpu" and jax.process_count() == 1:
        text += ": every part on this one device, so no synchronization cost is measured"
    return text
