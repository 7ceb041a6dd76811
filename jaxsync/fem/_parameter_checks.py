"""Checks of the numbers a material, a load or a boundary condition is built from.

Every parameter is checked when its object is built, so that a NaN, an infinity or a
value out of range is refused with a message naming that parameter, instead of surfacing
later as another error (a zero time step, a singular system, an empty node set).

JAX rebuilds these objects with tracers, stacked arrays (ensembles) or placeholders as
their leaves: only concrete numbers and numeric arrays are checked; a stacked array is
checked for finiteness only.
"""

from __future__ import annotations

import numpy as np

from ..errors import ProblemError
from ..pytree import concrete_scalar

__all__ = ["check_number", "check_finite_array"]


def _is_text(value) -> bool:
    return isinstance(value, (str, bytes))


def check_number(value, name: str, *, error: type = ProblemError, above: float | None = None,
                 at_least: float | None = None, below: float | None = None, unit: str = "",
                 hint: str = "") -> None:
    """Raise ``error`` unless ``value`` is a finite number in range (when concrete).

    Args:
        value: the parameter (a tracer, a stacked array or a placeholder passes).
        name: how the message names it (``"LinearElastic.E"``).
        error: the exception type (a :class:`jaxsync.JaxsyncError` subclass).
        above, at_least, below: the range: ``value > above``, ``value >= at_least``,
            ``value < below``.
        unit: the unit, for the message; hint: the fix, appended to the message.
    """
    if _is_text(value) or isinstance(value, (bool, np.bool_, list, tuple, dict, set)):
        raise error(f"{name} must be a number{f' [{unit}]' if unit else ''}, got {value!r}")
    v = concrete_scalar(value)
    if v is None:
        if isinstance(value, np.ndarray) and value.dtype.kind in "fiu" and value.size:
            check_finite_array(value, name, error=error)
        return
    units = f" {unit}" if unit else ""
    tail = f"; {hint}" if hint else ""
    if not np.isfinite(v):
        raise error(f"{name} must be a finite number, got {v}{units}{tail}")
    if above is not None and not v > above:
        bound = "positive" if above == 0 else f"> {above:g}{units}"
        raise error(f"{name} must be {bound}, got {v:g}{units}{tail}")
    if at_least is not None and not v >= at_least:
        raise error(f"{name} must be >= {at_least:g}{units}, got {v:g}{tail}")
    if below is not None and not v < below:
        raise error(f"{name} must be < {below:g}{units}, got {v:g}{tail}")


def check_finite_array(value, name: str, *, error: type = ProblemError, length: int | None = None) -> None:
    """Raise ``error`` unless the concrete array ``value`` holds finite numbers (and, with
    ``length``, when given as a tuple or list, exactly that many). Tracers pass."""
    if _is_text(value):
        raise error(f"{name} must be numbers, got {value!r}")
    if length is not None and isinstance(value, (tuple, list)) and len(value) != length:
        raise error(f"{name} must have {length} components, got {value!r}")
    if isinstance(value, (tuple, list)):
        if any(_is_text(v) for v in value):
            raise error(f"{name} must be numbers, got {value!r}")
        try:
            value = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            return  # pytree placeholders or tracers inside: checked when concrete
    if not isinstance(value, (np.ndarray, np.generic, int, float)):
        import jax

        if not isinstance(value, jax.Array) or isinstance(value, jax.core.Tracer):
            return
    array = np.asarray(value)
    if array.dtype.kind not in "fiu":
        if array.dtype.kind in "SUO" and array.dtype != object:
            raise error(f"{name} must be numbers, got {value!r}")
        return
    bad = ~np.isfinite(array)
    if bad.any():
        where = np.argwhere(bad)[0].tolist() if array.ndim else []
        raise error(f"{name} must be finite, got {array.ravel()[np.flatnonzero(bad.ravel())[0]]}"
                    + (f" at index {tuple(where)}" if where else ""))
