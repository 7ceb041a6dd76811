"""The known load signals of a problem: what a load-aware surrogate is told.

A problem's loads are prescribed: each load (:class:`~jaxsync.fem.BodyForce`,
:class:`~jaxsync.fem.Pressure`, :class:`~jaxsync.Traction`) is a spatial
part times a scalar time function g_i(t), and a prescribed motion
(:class:`jaxsync.Dirichlet` with ``time=``) follows its own g(t). Their values are known
exactly at every step, past and future, so a surrogate that predicts the shared-node
displacements may be given them (:class:`~jaxsync.surrogate.models.LSTMArchitecture`,
:class:`~jaxsync.surrogate.models.LinearArchitecture`: the ``n_load`` inputs).

The signal vector u(t) (n_u,) holds, in this order, g_i(t) of every load of
``problem.loads`` and then g(t) of every Dirichlet condition of ``problem.dirichlet`` that
has a time function (dimensionless, as the time functions are). It is sampled at the
time t_k = k dt of displacement step k (the displacement d(k) that the surrogate sees).

:class:`LoadInput` describes one signal (where it comes from, the form of its time
function, its parameters in words); a surrogate file records them, and a surrogate runs
only on a problem whose signals have the same sources and forms (:func:`check_load_inputs`).
The parameters may differ: a surrogate trained under one pressure pulse runs under
another :class:`~jaxsync.fem.Periodic` waveform, or with another
:class:`~jaxsync.fem.StepOff` time. :class:`LoadSignals` evaluates the signals of
one problem at one time step (static, hashable: it is part of a compiled program).
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import CheckpointError, ConfigError
from ..pytree import is_traced
from ._loads import Constant, Periodic, Product, Ramp, StepOff

__all__ = ["LoadInput", "LoadSignals", "RecordedLoadSignals", "load_inputs_of", "check_load_inputs",
           "time_function_form", "describe_time_function", "record_load_signal"]


def time_function_form(g) -> str:
    """The form of a time function, without its parameters: ``"Constant"``, ``"Ramp"``,
    ``"Periodic"``, ``"StepOff(Ramp)"``, ``"Product(Ramp, Periodic)"``; another
    :class:`~jaxsync.fem.TimeFunction` subclass by its class name."""
    if isinstance(g, StepOff):
        return f"StepOff({time_function_form(g.inner)})"
    if isinstance(g, Product):
        return "Product(" + ", ".join(time_function_form(f) for f in g.factors) + ")"
    return type(g).__name__


def describe_time_function(g) -> str:
    """A time function with its parameters, in words (a Periodic waveform by its period,
    sample count and value range)."""
    if isinstance(g, Constant):
        return "Constant()"
    if isinstance(g, Ramp):
        return f"Ramp(t_end={float(g.t_end):g} s)"
    if isinstance(g, StepOff):
        return f"StepOff(t_off={float(g.t_off):g} s, inner={describe_time_function(g.inner)})"
    if isinstance(g, Periodic):
        values = np.asarray(g.values, float)
        return (f"Periodic(period={float(g.period):g} s, {values.size} samples, values "
                f"{values.min():g} .. {values.max():g})")
    if isinstance(g, Product):
        return " * ".join(describe_time_function(f) for f in g.factors)
    return repr(g)


@dataclasses.dataclass(frozen=True)
class LoadInput:
    """One known load signal of a surrogate (what its file records).

    Attributes:
        source: where the signal comes from: ``"loads[i]"`` or ``"dirichlet[i]"`` (the
            index in ``Problem.loads`` / ``Problem.dirichlet``).
        kind: the load's type, ``"BodyForce"``, ``"Pressure"``, ``"Traction"`` or
            ``"Dirichlet"`` (a prescribed motion).
        form: the form of its time function (:func:`time_function_form`), e.g.
            ``"StepOff(Constant)"``.
        function: the time function with its parameters in words
            (:func:`describe_time_function`; for the record, not compared).
    """

    source: str
    kind: str
    form: str
    function: str = ""

    @property
    def signature(self) -> tuple[str, str, str]:
        """``(source, kind, form)``: what must agree between the loads a surrogate was
        trained with and those it runs with (the parameters need not)."""
        return self.source, self.kind, self.form

    def to_dict(self) -> dict[str, str]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "LoadInput":
        try:
            return cls(**{k: str(values[k]) for k in ("source", "kind", "form")},
                       function=str(values.get("function", "")))
        except (KeyError, TypeError) as err:
            raise CheckpointError(f"a load input record {values!r} lacks {err}; the file is damaged") from err

    def __str__(self) -> str:
        return f"{self.source} {self.kind} with {self.function or self.form}"


def _signal_terms(problem) -> list[tuple[str, str, Any]]:
    """(source, kind, time function) of every signal of ``problem``, in signal order."""
    terms = [(f"loads[{i}]", type(load).__name__, load.time) for i, load in enumerate(problem.loads)]
    terms += [(f"dirichlet[{i}]", "Dirichlet", bc.time) for i, bc in enumerate(problem.dirichlet)
              if bc.time is not None]
    return terms


def load_inputs_of(problem) -> tuple[LoadInput, ...]:
    """The :class:`LoadInput` of every load signal of ``problem`` (module docstring: one per
    load, then one per Dirichlet condition with a time function)."""
    return tuple(LoadInput(source, kind, time_function_form(g), describe_time_function(g))
                 for source, kind, g in _signal_terms(problem))


def check_load_inputs(trained: Sequence[LoadInput], problem, what: str = "the surrogates") -> None:
    """Refuse to run surrogates trained with the load signals ``trained`` on ``problem``
    unless its signals have the same count, sources, kinds and time-function forms (the
    parameters may differ: another waveform, another step-off time).

    Raises:
        CheckpointError: naming the first difference and the fix.
    """
    here = load_inputs_of(problem)
    fix = ("give the problem the loads the surrogates were trained with (other parameters of the same form are "
           "fine), or retrain them on a run of this problem (jaxsync train)")
    if len(here) != len(trained):
        raise CheckpointError(
            f"{what} take {len(trained)} load signal(s) ({'; '.join(map(str, trained)) or 'none'}) but this problem "
            f"has {len(here)} ({'; '.join(map(str, here)) or 'none'}): {fix}")
    for a, b in zip(trained, here):
        if a.signature != b.signature:
            raise CheckpointError(
                f"{what} were trained with {a.source} a {a.kind} of time function form {a.form} ({a.function}) but "
                f"this problem's {b.source} is a {b.kind} of form {b.form} ({b.function}): {fix}")


def _evaluate(g, times) -> jax.Array:
    """g at every entry of ``times`` (vmapped: a time function is written for one scalar t)."""
    return jax.vmap(lambda t: jnp.asarray(g(t), dtype=jnp.result_type(float)).reshape(()))(times)


@dataclasses.dataclass(frozen=True, eq=False)
class LoadSignals:
    """The load signals of one problem at its time step: u(t_k), t_k = k dt.

    Static data of a compiled program (hashed and compared by a fingerprint of the time
    functions' values and dt), so the time functions and dt must be concrete.

    Attributes:
        functions: (n_u,) the time functions, in signal order.
        inputs: (n_u,) their :class:`LoadInput` descriptions.
        dt: the time step [s].
    """

    functions: tuple
    inputs: tuple[LoadInput, ...]
    dt: float

    def __post_init__(self):
        object.__setattr__(self, "dt", float(self.dt))
        leaves, treedef = jax.tree_util.tree_flatten(self.functions)
        digest = hashlib.sha256(repr((str(treedef), self.dt)).encode())
        for leaf in leaves:
            digest.update(np.ascontiguousarray(np.asarray(leaf, np.float64)).tobytes())
        object.__setattr__(self, "_key", digest.hexdigest())

    def __eq__(self, other):
        return isinstance(other, LoadSignals) and other._key == self._key

    def __hash__(self):
        return hash(self._key)

    @classmethod
    def of(cls, problem, dt) -> "LoadSignals":
        """The signals of ``problem`` at time step ``dt`` [s].

        Raises:
            ConfigError: traced time functions or dt (inside ``jax.grad``/``jit`` over them):
                a load-aware surrogate needs their values when its program is built."""
        terms = _signal_terms(problem)
        functions = tuple(g for _, _, g in terms)
        if is_traced(functions, dt):
            raise ConfigError("a surrogate with load inputs evaluates the problem's time functions when its program "
                              "is built, but they (or dt) are traced here; keep the time functions and dt concrete, "
                              "or use surrogates trained without load inputs (load_input=False)")
        return cls(functions, load_inputs_of(problem), float(dt))

    @property
    def n_signals(self) -> int:
        return len(self.functions)

    def at_times(self, times) -> jax.Array:
        """(len(times), n_u) the signals at ``times`` [s]."""
        times = jnp.asarray(times, dtype=jnp.result_type(float))
        if not self.functions:
            return jnp.zeros(times.shape + (0,), times.dtype)
        return jnp.stack([_evaluate(g, times) for g in self.functions], axis=-1)

    def at_steps(self, first_step, n_steps: int) -> jax.Array:
        """(n_steps, n_u) the signals at steps ``first_step .. first_step + n_steps - 1``
        (``first_step`` may be traced)."""
        steps = first_step + jnp.arange(n_steps, dtype=jnp.result_type(first_step))
        return self.at_times(steps.astype(jnp.result_type(float)) * self.dt)


@dataclasses.dataclass(frozen=True, eq=False)
class RecordedLoadSignals:
    """Load signals read from a record instead of time functions: a trajectory's
    ``load_signal`` kept at every step (what the offline checks of a training use).
    Static like :class:`LoadSignals` (hashed by the table's values).

    Attributes:
        table: (n_steps, n_u) the signals at steps 0 .. n_steps - 1; steps past the end
            read the last row, steps before 0 the first.
        inputs: (n_u,) their :class:`LoadInput` descriptions.
    """

    table: np.ndarray
    inputs: tuple[LoadInput, ...]

    def __post_init__(self):
        table = np.asarray(self.table, np.float64)
        if table.ndim != 2 or table.shape[1] != len(self.inputs) or table.shape[0] == 0:
            raise ConfigError(f"a load-signal record must have shape (n_steps >= 1, {len(self.inputs)}), got "
                              f"{table.shape}")
        object.__setattr__(self, "table", table)
        object.__setattr__(self, "_key", hashlib.sha256(table.tobytes() + repr(self.inputs).encode()).hexdigest())

    def __eq__(self, other):
        return isinstance(other, RecordedLoadSignals) and other._key == self._key

    def __hash__(self):
        return hash(self._key)

    @property
    def n_signals(self) -> int:
        return self.table.shape[1]

    def at_steps(self, first_step, n_steps: int) -> jax.Array:
        """(n_steps, n_u) the recorded signals at steps ``first_step ..`` (clamped to the record)."""
        rows = jnp.clip(first_step + jnp.arange(n_steps, dtype=jnp.result_type(first_step)), 0,
                        self.table.shape[0] - 1)
        return jnp.asarray(self.table)[rows]


def record_load_signal(problem, dt, steps) -> tuple[np.ndarray, tuple[LoadInput, ...]] | None:
    """``(signal (len(steps), n_u) float64, inputs)``: the problem's load signals at the
    given steps, for a trajectory; None when the time functions or dt are traced (a
    traced run records none)."""
    try:
        with jax.ensure_compile_time_eval():
            signals = LoadSignals.of(problem, dt)
            values = np.asarray(signals.at_steps(0, 0) if len(steps) == 0 else
                                signals.at_times(np.asarray(steps, np.float64) * float(dt)), np.float64)
    except (ConfigError, jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError, TypeError):
        return None
    return values.reshape(len(steps), signals.n_signals), signals.inputs

