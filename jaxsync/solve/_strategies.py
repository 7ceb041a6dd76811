"""How a run is carried out, as small frozen objects (the options of the solvers).

Each is validated when it is made (a :class:`~jaxsync.errors.ProblemError` or
:class:`~jaxsync.errors.ConfigError` naming the fix) and documented where it is defined;
the solvers take them as arguments, and the command line's strings map onto them
(:func:`sync_strategy`, :meth:`SaveAt.of`, :meth:`SolverCheckpoint.of`).

* How the parts exchange (``sync=``): :class:`Psum`, :class:`Ppermute`, :class:`Mpi`,
  :class:`Halo`, defined in :mod:`jaxsync.parallel.exchange` (with the registry of their
  names) and importable from here too.
* What a run keeps (``save=``): :class:`SaveAt`.
* Where a run can resume from (``checkpoint=``): :class:`SolverCheckpoint`.
* Who runs it (``executor=``): :class:`HostExecutor` (compiled chunks driven from Python:
  progress, divergence checks, checkpoints, error control) or :class:`TracedExecutor`
  (one traced JAX program: inside ``jax.grad`` and ``jit``), with its reverse-pass
  policy (``adjoint=``): :class:`Recompute` or :class:`StoreAll`.
* When a synchronization-avoiding run synchronizes again: :class:`ResyncTolerance`, and
  the load-jump policy (:data:`jaxsync.options.LoadJumps`).
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np

from ..errors import ProblemError
from ..parallel.exchange._builtin import Halo, Mpi, Ppermute, Psum, sync_strategy, transport

__all__ = ["Psum", "Ppermute", "Mpi", "Halo", "sync_strategy", "SaveAt", "SolverCheckpoint",
           "HostExecutor", "TracedExecutor", "Recompute", "StoreAll", "ResyncTolerance", "choose_executor",
           "transport"]


def _positive_int(name: str, value, error=ProblemError) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise error(f"{name} must be a positive integer, got {value!r}")
    return int(value)


# --------------------------------------------------------------------------- saving


@dataclasses.dataclass(frozen=True)
class SaveAt:
    """What a run keeps.

    Attributes:
        every: the full displacement field every this many steps (and at t = 0).
        shared_every: distributed runs: each part's shared-node displacements every this
            many steps (a divisor of ``every``; default ``every``). The surrogates train on
            every step: ``shared_every=1`` keeps that small history while the full field is
            kept only every ``every`` steps.
    """

    every: int = 1
    shared_every: int | None = None

    def __post_init__(self):
        every = _positive_int("SaveAt.every (save every this many steps)", self.every)
        shared = every if self.shared_every is None else _positive_int("SaveAt.shared_every", self.shared_every)
        if every % shared:
            raise ProblemError(f"shared_every={shared} must be a positive divisor of save_every={every}")
        object.__setattr__(self, "every", every)
        object.__setattr__(self, "shared_every", shared)

    @classmethod
    def of(cls, value) -> "SaveAt":
        """A :class:`SaveAt` as it is, or an int k: ``SaveAt(every=k)``."""
        return value if isinstance(value, cls) else cls(every=value)

    def check_steps(self, n_steps) -> int:
        """``n_steps`` as an int, checked to be a whole number of saves (ProblemError naming
        the fix)."""
        if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 0:
            raise ProblemError(f"n_steps must be an integer >= 0, got {n_steps!r}")
        n_steps = int(n_steps)
        if n_steps % self.every:
            raise ProblemError(f"n_steps={n_steps} is not a multiple of save_every={self.every}; "
                               f"use n_steps={n_steps - n_steps % self.every + self.every}")
        return n_steps

    @property
    def records_every_step(self) -> bool:
        """True when the shared-node history is kept more often than the full field."""
        return self.shared_every != self.every


# --------------------------------------------------------------------------- resuming


@dataclasses.dataclass(frozen=True)
class SolverCheckpoint:
    """The resumable state of a synchronized run (:mod:`jaxsync.io.checkpoint`).

    A run given a checkpoint stores its state there as it goes, and a run started again
    with the same problem continues from the last one, giving the same trajectory.

    Attributes:
        path: the HDF5 file.
        every: checkpoint every this many steps (rounded up to whole chunks); None: at
            most once per :data:`jaxsync.io.checkpoint.CHECKPOINT_SECONDS` of wall
            time, and at the end.
    """

    path: str
    every: int | None = None

    def __post_init__(self):
        if not isinstance(self.path, (str, os.PathLike)):
            raise ProblemError(f"SolverCheckpoint.path must be a file path, got {self.path!r}")
        object.__setattr__(self, "path", os.fspath(self.path))
        if self.every is not None:
            object.__setattr__(self, "every", _positive_int("SolverCheckpoint.every", self.every))

    @classmethod
    def of(cls, value) -> "SolverCheckpoint | None":
        """None, a :class:`SolverCheckpoint` as it is, or a path: ``SolverCheckpoint(path)``."""
        if value is None or isinstance(value, cls):
            return value
        return cls(value)


# --------------------------------------------------------------------------- executors


@dataclasses.dataclass(frozen=True)
class HostExecutor:
    """Runs a schedule as compiled chunks driven from Python (concrete inputs).

    Between chunks it shows progress, checks for divergence, writes checkpoints and, in a
    synchronization-avoiding run with a tolerance, decides on re-synchronization.

    Attributes:
        progress: a tqdm bar (True/False; None: for runs of 20 000 steps or more), or a
            :class:`jaxsync.solve.executors.Progress` to report to (shared by several runs).
        chunk_steps: steps per compiled chunk of synchronized steps, between checks.
        cycles_per_chunk: refill cycles per compiled call of an unmonitored predicted
            phase (default: about 20 000 steps).
        blowup_factor: a displacement larger than this times the mesh's bounding-box
            diagonal counts as divergence.
        check_stability: refuse a dt above the exact stability bound before running (False
            forces it through).
    """

    progress: Any = None
    chunk_steps: int = 5000
    cycles_per_chunk: int | None = None
    blowup_factor: float = 1e3
    check_stability: bool = True

    def __post_init__(self):
        object.__setattr__(self, "chunk_steps", _positive_int("HostExecutor.chunk_steps", self.chunk_steps))
        if self.cycles_per_chunk is not None:
            object.__setattr__(self, "cycles_per_chunk",
                               _positive_int("HostExecutor.cycles_per_chunk", self.cycles_per_chunk))
        if not (isinstance(self.blowup_factor, (int, float, np.floating)) and self.blowup_factor > 0):
            raise ProblemError(f"HostExecutor.blowup_factor must be a number > 0, got {self.blowup_factor!r}")


@dataclasses.dataclass(frozen=True)
class Recompute:
    """Reverse pass by recomputation (``jax.checkpoint`` segments): the forward pass keeps
    the states at segment boundaries only and the reverse pass recomputes one segment at a
    time, so memory grows like sqrt(n_steps) for one more forward run
    (:mod:`jaxsync.solve`).

    Attributes:
        budget_bytes: None (default): always recompute, in segments of about
            sqrt(n_steps) steps. A number of bytes: store every step when all of them fit
            in it (no recomputation, faster), else recompute.
    """

    budget_bytes: int | None = None

    def __post_init__(self):
        if self.budget_bytes is not None:
            object.__setattr__(self, "budget_bytes", _positive_int("Recompute.budget_bytes", self.budget_bytes))


@dataclasses.dataclass(frozen=True)
class StoreAll:
    """Reverse pass of the plain ``lax.scan``: every step's residuals stored (memory linear
    in n_steps; fastest for short runs)."""


@dataclasses.dataclass(frozen=True)
class TracedExecutor:
    """Runs a schedule as one traced JAX program (``lax.scan``; used inside ``jax.grad``
    and ``jit``, and on request with concrete inputs): no progress, divergence checks,
    checkpoints or error control; the trajectory holds JAX arrays, and its ``result``
    says whether every value is finite.

    Attributes:
        adjoint: the reverse pass, :class:`Recompute` (default) or :class:`StoreAll`.
    """

    adjoint: Recompute | StoreAll = Recompute()

    def __post_init__(self):
        if not isinstance(self.adjoint, (Recompute, StoreAll)):
            raise ProblemError(f"TracedExecutor.adjoint must be jaxsync.Recompute() or jaxsync.StoreAll(), "
                               f"got {self.adjoint!r}")


def choose_executor(executor, traced: bool):
    """The executor of a run: ``executor`` as given (a :class:`HostExecutor` refused when
    inputs are traced: it needs concrete values between chunks), or by default the
    traced executor for traced inputs and the host executor otherwise."""
    if executor is None:
        return TracedExecutor() if traced else HostExecutor()
    if not isinstance(executor, (HostExecutor, TracedExecutor)):
        raise ProblemError(f"executor must be jaxsync.HostExecutor(...) or jaxsync.TracedExecutor(...), got "
                           f"{executor!r}")
    if traced and isinstance(executor, HostExecutor):
        raise ProblemError("the inputs are JAX tracers (inside jax.grad, jit or vmap), and the host executor "
                           "needs concrete values between its chunks: pass executor=jaxsync.TracedExecutor(...) "
                           "or leave executor out")
    return executor


# --------------------------------------------------------------------------- error control


@dataclasses.dataclass(frozen=True)
class ResyncTolerance:
    """The error above which a synchronization-avoiding run re-synchronizes.

    Give it in cm (``ResyncTolerance(absolute=1e-4)``, or just ``1e-4``) or relative to
    the observed amplitude (``ResyncTolerance(relative=0.01)``, or ``"1%"``): a fraction
    of the largest |displacement| at the shared nodes seen in the synchronized steps so
    far (the amplitude that the run itself has measured; no reference needed). Under a
    load that ramps up, that amplitude is small when the prediction starts; ``amplitude``
    [cm] fixes the one a relative tolerance refers to instead (e.g. the largest shared
    displacement of the run the surrogates were trained on).

    ``indicator``: what is held to the tolerance. ``"estimate"`` (default): es_hat of
    every cycle's predictions before it runs (paper eq. 26, the parts' disagreement), and
    the estimated largest nodal error since the last synchronized state after it runs
    (:mod:`jaxsync.solve.coupling`: the force-balance defect probed at the saved
    steps, one exchange of partial forces each, propagated through the ``modes`` lowest
    vibration modes), which also sees the errors that all parts make alike. ``"es_hat"``:
    es_hat alone (no exchange in the predicted phase; blind to shared errors).

    ``linearization`` (a hyperelastic law, with ``indicator="estimate"``): the state whose
    tangent stiffness the estimate's linear propagator is built from: ``"rest"``
    (default: the reference configuration, built once) or ``"synchronized"`` (the last
    synchronized state before each predicted stretch, rebuilt there: one sparse
    factorization and eigensolve per stretch). A linear law's propagator is the same
    either way.

    ``learning``: learn while synchronized: after every rejected cycle the surrogates train
    on the steps recomputed synchronized (and on windows replayed from the first
    synchronized stretch) before the run predicts again (:mod:`jaxsync.surrogate.training`).
    True: the defaults of :class:`jaxsync.surrogate.OnlineLearning`, or one of those (its
    ``budget_seconds`` bounds the update time of the run); None or False (default): the
    surrogates stay as given.
    """

    absolute: float | None = None
    relative: float | None = None
    amplitude: float | None = None
    indicator: str = "estimate"
    modes: int | None = None
    linearization: str = "rest"
    learning: object = None

    def __post_init__(self):
        if self.indicator not in ("estimate", "es_hat"):
            raise ProblemError(f"resync_tolerance: indicator={self.indicator!r}; use 'estimate' (es_hat and the "
                               "estimated error, the default) or 'es_hat' (the parts' disagreement only)")
        if self.modes is not None and (isinstance(self.modes, bool) or not isinstance(self.modes, int)
                                       or self.modes < 1):
            raise ProblemError(f"resync_tolerance: modes={self.modes!r} must be a whole number >= 1")
        if self.linearization not in ("rest", "synchronized"):
            raise ProblemError(f"resync_tolerance: linearization={self.linearization!r}; use 'rest' (the tangent "
                               "stiffness at the reference configuration, the default) or 'synchronized' (at the "
                               "last synchronized state)")
        if self.linearization != "rest" and self.indicator != "estimate":
            raise ProblemError("resync_tolerance: linearization= sets the error estimate's tangent; it goes with "
                               "indicator='estimate'")
        if self.modes is not None and self.indicator != "estimate":
            raise ProblemError("resync_tolerance: modes= sets the error estimate's modes; it goes with "
                               "indicator='estimate'")
        if (self.absolute is None) == (self.relative is None):
            raise ProblemError("resync_tolerance: give exactly one of absolute (cm) or relative")
        value = self.absolute if self.absolute is not None else self.relative
        if not _positive(value):
            raise ProblemError(f"resync_tolerance must be a tolerance > 0 (cm, or a fraction of the "
                               f"amplitude), got {value!r}")
        if self.relative is not None and not self.relative <= 1.0:
            raise ProblemError(f"resync_tolerance {100 * self.relative:g}% of the amplitude is above 100%: an error as "
                               "large as the displacement itself would pass, so the control would accept any "
                               "prediction; give a percentage up to 100% (typically 1% to 10%), or leave the "
                               "tolerance out (none) to run without error control")
        if not (self.learning is None or isinstance(self.learning, bool)
                or type(self.learning).__name__ == "OnlineLearning"):
            raise ProblemError(f"resync_tolerance: learning={self.learning!r}; give True (the defaults), "
                               "jaxsync.surrogate.OnlineLearning(...), or None/False (no learning)")
        if self.amplitude is not None and (self.relative is None or not _positive(self.amplitude)):
            raise ProblemError(f"resync_tolerance: amplitude={self.amplitude!r} must be a length > 0 [cm] "
                               "and goes with a relative tolerance")

    @classmethod
    def parse(cls, value) -> "ResyncTolerance":
        """A tolerance from a number (cm), a string ``"1e-4"`` (cm) or ``"2%"`` (relative),
        or a :class:`ResyncTolerance`."""
        if isinstance(value, cls):
            return value
        if isinstance(value, str):
            text = value.strip()
            try:
                number = float(text[:-1] if text.endswith("%") else text)
            except ValueError:
                raise ProblemError(f"resync_tolerance {value!r} is neither a length in cm (e.g. 1e-4) "
                                   "nor a percentage of the amplitude (e.g. 2%)") from None
            # checked by __post_init__, which names what is wrong with the number
            return cls(relative=number / 100.0) if text.endswith("%") else cls(absolute=number)
        return cls(absolute=value)  # checked by __post_init__

    def cm(self, amplitude: float) -> float:
        """The tolerance in cm given the observed amplitude [cm] (not used when the
        tolerance is absolute or has its own ``amplitude``)."""
        if self.absolute is not None:
            return float(self.absolute)
        return float(self.relative) * (amplitude if self.amplitude is None else float(self.amplitude))

    def __str__(self) -> str:
        text = (f"{self.absolute:g} cm" if self.absolute is not None else
                f"{100 * self.relative:g} %" + ("" if self.amplitude is None else f" of {self.amplitude:.4g} cm"))
        text += " (es_hat only)" if self.indicator == "es_hat" else ""
        return text + (" + learning" if self.learning not in (None, False) else "")


def _positive(value) -> bool:
    """A real number > 0 (not a bool, not NaN; an infinite absolute tolerance monitors a run
    without ever re-synchronizing it)."""
    return (not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
            and value > 0)
