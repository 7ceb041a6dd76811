"""Floating-point precision of the solver.

The explicit solver integrates 1e5-1e6 steps; in float32 the paper's cantilever ends
2.9 % off the float64 result after 1e5 steps, and 2 parts differ from 1 device by 5e-3.
JAX computes in float32 unless ``jax_enable_x64`` is set, so the entry points refuse to
run without it instead of returning float32 numbers that look like float64 ones.
"""

from __future__ import annotations

import jax

from .errors import PrecisionError

__all__ = ["require_float64"]


def require_float64(entry: str) -> None:
    """Raise :class:`PrecisionError` unless JAX computes in float64 (``jax_enable_x64``)."""
    if not jax.config.jax_enable_x64:
        raise PrecisionError(
            f"{entry} runs in float64, but JAX is in float32 mode: call "
            "jax.config.update(\"jax_enable_x64\", True) at the start of your program (before "
            "creating arrays), or set the environment variable JAX_ENABLE_X64=1. The jaxsync "
            "command line does this for you.")
