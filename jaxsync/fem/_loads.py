"""External loads and their time functions.

A load is a spatial part (a body force per unit volume, a pressure or a traction on a
tagged surface) times a scalar time function ``g(t)``. Time functions are pytrees
evaluated with ``jax.numpy`` inside the compiled time loop; they compose with ``*``, and
they also drive prescribed displacements (:class:`jaxsync.Dirichlet` ``time=``).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ProblemError
from ..pytree import concrete_scalar, is_traced, pytree_dataclass, static_field
from ._parameter_checks import check_finite_array, check_number

__all__ = ["TimeFunction", "Constant", "Ramp", "StepOff", "Periodic", "Product", "load_jumps", "LOAD_JUMP_FRACTION",
           "BodyForce", "Pressure", "Traction", "LOADS"]


class TimeFunction:
    """Scalar function of time g(t), dimensionless. ``f * g`` is their product."""

    def __call__(self, t):  # pragma: no cover - interface
        raise NotImplementedError

    def __mul__(self, other: "TimeFunction") -> "Product":
        if not isinstance(other, TimeFunction):
            return NotImplemented
        return Product((self, other))


@pytree_dataclass
class Constant(TimeFunction):
    """g(t) = 1: the load acts at full magnitude from t = 0."""

    def __call__(self, t):
        return jnp.ones_like(jnp.asarray(t, dtype=float))


@pytree_dataclass
class Ramp(TimeFunction):
    """The paper's ramp R(t, t_end) = t / t_end for t <= t_end, else 1 (t_end [s] > 0)."""

    t_end: float = 1.0

    def __post_init__(self):
        check_number(self.t_end, "Ramp.t_end", above=0.0, unit="s", hint="use Constant() for no ramp")

    def __call__(self, t):
        return jnp.clip(jnp.asarray(t, dtype=float) / self.t_end, 0.0, 1.0)


@pytree_dataclass
class StepOff(TimeFunction):
    """``inner(t)`` while t < t_off [s], zero afterwards (the paper's load switched off)."""

    t_off: float
    inner: Any = Constant()

    def __post_init__(self):
        check_number(self.t_off, "StepOff.t_off", above=0.0, unit="s",
                     hint="a load switched off at t <= 0 never acts: leave it out instead")
        if not isinstance(self.inner, TimeFunction) and not _placeholder(self.inner):
            raise ProblemError(f"StepOff.inner must be a time function (jaxsync.Ramp, Constant...), got "
                               f"{self.inner!r}")

    def __call__(self, t):
        t = jnp.asarray(t, dtype=float)
        return jnp.where(t < self.t_off, self.inner(t), 0.0)


@pytree_dataclass
class Periodic(TimeFunction):
    """Periodic waveform given by samples over one period, linearly interpolated.

    Attributes:
        times: (n_samples,) increasing sample times within [0, period] [s].
        values: (n_samples,) waveform values (dimensionless factor, or the pressure
            itself with a load magnitude of 1).
        period: [s]. The waveform repeats: g(t) = interp(t mod period).
    """

    times: Any
    values: Any
    period: float

    def __post_init__(self):
        check_number(self.period, "Periodic.period", above=0.0, unit="s")
        if concrete_scalar(self.period) is None or is_traced(self.times, self.values):
            return
        check_finite_array(self.times, "Periodic.times")
        check_finite_array(self.values, "Periodic.values")
        times, values = np.asarray(self.times, float), np.asarray(self.values, float)
        if times.ndim != 1 or times.shape != values.shape or len(times) < 2:
            raise ProblemError("Periodic needs 1-D times and values of the same length >= 2, "
                               f"got shapes {times.shape} and {values.shape}")
        if np.any(np.diff(times) <= 0):
            raise ProblemError("Periodic sample times must be strictly increasing")
        if not float(self.period) > 0 or times[0] < 0 or times[-1] > float(self.period) + 1e-12:
            raise ProblemError(f"Periodic sample times must lie in [0, period={self.period}] "
                               "and the period must be positive")
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "values", values)

    def __call__(self, t):
        tau = jnp.mod(jnp.asarray(t, dtype=float), self.period)
        # Close the period so that the value wraps from the last sample to the first.
        times = jnp.concatenate([jnp.asarray(self.times), jnp.asarray([self.times[0] + self.period])])
        values = jnp.concatenate([jnp.asarray(self.values), jnp.asarray(self.values[:1])])
        tau = jnp.where(tau < times[0], tau + self.period, tau)
        return jnp.interp(tau, times, values)


@pytree_dataclass
class Product(TimeFunction):
    """Product of time functions, e.g. ``Ramp(1.0) * Periodic(...)``."""

    factors: tuple

    def __post_init__(self):
        object.__setattr__(self, "factors", tuple(self.factors))
        bad = [f for f in self.factors if not isinstance(f, TimeFunction) and not _placeholder(f)]
        if bad or not self.factors:
            raise ProblemError(f"Product needs one or more time functions, got {self.factors!r}")

    def __call__(self, t):
        out = self.factors[0](t)
        for g in self.factors[1:]:
            out = out * g(t)
        return out


@pytree_dataclass
class BodyForce:
    """Body force per unit volume b(x, t) = vector * time(t) [dyn/cm^3].

    Attributes:
        vector: (3,) force density components.
        time: the time function (default: the paper's 1 s ramp).
    """

    vector: tuple[float, float, float] | Any = (0.0, 0.0, -0.5)
    time: Any = Ramp(1.0)

    def __post_init__(self):
        check_finite_array(self.vector, "BodyForce.vector [dyn/cm^3]", length=3)
        _check_time(self.time, "BodyForce")


@pytree_dataclass
class Pressure:
    """Pressure p(t) = magnitude * time(t) [barye] on the facet set ``surface`` (magnitude 1 by
    default: the time function's values are then the pressure, a measured waveform in barye).

    The traction is -p n with n the outward normal, so a positive pressure pushes into
    the solid (a lumen pressure inflates a vessel).

    ``follower=False`` (default): a dead load, -p n dA on the reference surface (its nodal
    forces fixed). ``follower=True``: the pressure acts on the deformed surface, -p n da
    with the current normal and area (:mod:`jaxsync.fem.forces`), as a fluid's pressure
    does at finite strain; it needs a hyperelastic material (a small-strain law has no
    deformed surface to follow).
    """

    magnitude: Any = 1.0
    time: Any = Constant()
    surface: str = static_field(default="pressure")
    follower: bool = static_field(default=False)

    def __post_init__(self):
        if not isinstance(self.follower, (bool, np.bool_)):
            raise ProblemError(f"Pressure.follower must be True or False, got {self.follower!r}")
        if not isinstance(self.surface, str):
            raise ProblemError(f"Pressure.surface must be the name of a facet set, got {self.surface!r}")
        check_number(self.magnitude, "Pressure.magnitude", unit="barye")
        _check_time(self.time, "Pressure")


@pytree_dataclass
class Traction:
    """Traction t(x, t) = vector * time(t) per unit area [dyn/cm^2] on the facet set
    ``surface``, in a fixed direction (a dead load: it does not turn with the surface).

    Its nodal forces are the surface integrals of N_i t over the facets, N_i the shape
    functions of the problem's element (P1: a third of each triangle's area at each of
    its vertices; P2: a third at each edge node and none at the vertices)."""

    vector: tuple[float, float, float] | Any
    time: Any = Constant()
    surface: str = static_field(default="traction")

    def __post_init__(self):
        check_finite_array(self.vector, "Traction.vector [dyn/cm^2]", length=3)
        if not isinstance(self.surface, str):
            raise ProblemError(f"Traction.surface must be the name of a facet set, got {self.surface!r}")
        _check_time(self.time, "Traction")


def _placeholder(value) -> bool:
    """A leaf JAX puts in a rebuilt pytree (None, object(), a tracer or an array)."""
    return value is None or type(value) is object or hasattr(value, "shape")


def _check_time(time, load: str) -> None:
    if not isinstance(time, TimeFunction) and not _placeholder(time):
        raise ProblemError(f"{load}.time must be a time function (jaxsync.Ramp(t_end), Constant(), StepOff, "
                           f"Periodic, or a product of them), got {time!r}")


LOADS = (BodyForce, Pressure, Traction)
"""The load types a :class:`jaxsync.Problem` takes."""


#: A load "jumps" at a step when its time function changes by more than this fraction
#: of its largest |value| over the run within that one step (a switch-off, a switch-on
#: after t = 0, a ramp shorter than a step). Smooth loads change by about 2 pi dt / T of
#: their amplitude per step (T: their shortest time scale), far below it at any stable dt.
LOAD_JUMP_FRACTION = 0.05


def load_jumps(loads, n_steps: int, dt: float, fraction: float = LOAD_JUMP_FRACTION) -> np.ndarray:
    """The steps n in 1 .. n_steps at which a load's time function jumps: |g(t_n) -
    g(t_{n-1})| > ``fraction`` max_k |g(t_k)| (t_k = k dt, k = 0 .. n_steps).

    The central-difference step from n uses f(t_n), so a jump at step n first moves
    d(n + 1): an autonomous surrogate, which sees only past displacements, cannot foresee it.

    Args:
        loads: :class:`BodyForce` / :class:`Pressure` terms (``Problem.loads``).
        n_steps: steps of the run.
        dt: time step [s].
        fraction: the jump size, a fraction of the load's largest |g| over the run.

    Returns:
        (n_jumps,) int64, increasing: the union over the loads.
    """
    times = np.arange(int(n_steps) + 1, dtype=float) * float(dt)
    steps = set()
    for load in loads:
        # vmapped: a time function written for one scalar t (as the stepper calls it) serves
        g = np.asarray(jax.vmap(lambda t, g=load.time: jnp.asarray(g(t), dtype=float).reshape(()))(
            jnp.asarray(times)), dtype=float)
        scale = float(np.abs(g).max(initial=0.0))
        if scale == 0.0:
            continue
        jumps = np.flatnonzero(np.abs(np.diff(g)) > fraction * scale) + 1
        steps.update(jumps.tolist())
    return np.asarray(sorted(steps), dtype=np.int64)
