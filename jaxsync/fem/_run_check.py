"""The run-time check of a hyperelastic run: inverted elements and the deformed state's
stable step, applied by the host executor between compiled chunks
(:class:`RunCheck`; the stable steps and Jacobians of :mod:`jaxsync.fem.forces`)."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import StabilityError
from ._timestep import ALPHA_S, damped_bound
from .forces._total_lagrangian import HyperelasticForce, exact_stable_dt, inverted_elements, stable_dt

__all__ = ["RunCheck"]


def _listed(elements, at_most: int = 12) -> str:
    shown = ", ".join(str(int(e)) for e in elements[:at_most])
    return shown + (f", ... ({len(elements)} in all)" if len(elements) > at_most else "")


@jax.jit
def _replay_jacobians(op, displacements):
    """(n, n_elements) the smallest J = det F of each element in each of the displacement
    fields (n, n_nodes, 3) (NaN where a field is not finite)."""
    return jnp.min(jax.vmap(op.jacobians)(displacements), axis=-1)


@dataclasses.dataclass
class RunCheck:
    """The stable-step and inversion check of a hyperelastic run, applied by the host
    executor to the run's state after every compiled chunk (``HostExecutor.chunk_steps``
    steps, default 5000; :mod:`jaxsync.solve.executors`), so that its cost is that of one
    :func:`stable_dt` and one :func:`inverted_elements` per chunk, not per step.

    :meth:`check` refuses a state with an inverted element (J <= 0) or whose exact stable
    step 2 / omega_max (:func:`exact_stable_dt` of the deformed state: its tangent stiffness,
    the supports' springs, the lumped mass; with beta through
    :func:`jaxsync.fem.damped_bound`) is below dt. The exact bound is computed only
    when the element rule (:func:`stable_dt`, ``rule="element"``, alpha_s = 1, never above
    it) does not already clear dt -- with the default step, alpha_s = 0.9 times the element
    rule at rest, only once the rule's bound has dropped by 10 % -- or when the problem has
    elastic supports (which the element rule leaves out). A run that diverges inside a
    chunk (NaN: an element that inverts makes the next step's forces NaN) is replayed from
    the chunk's start by :meth:`diagnose`, one step at a time on one device, to name the
    step and the elements that inverted.

    Attributes:
        problem: the run's problem.
        system: the run's global :class:`~jaxsync.fem.ExplicitSystem` (its
            ``stiffness`` the whole mesh's :class:`HyperelasticForce`).
        dt: the run's time step [s].
        last: (step, bound [s]) of the last state that passed the check, or None.
    """

    problem: Any
    system: Any
    dt: float
    last: tuple | None = None

    @property
    def operator(self) -> HyperelasticForce:
        return self.system.stiffness

    def _inverted(self, elements, step: int) -> StabilityError:
        before = ""
        if self.last is not None:
            at, bound = self.last
            before = (f" (at step {at}, the last state checked, the stable step was {bound:.4e} s; dt is "
                      f"{self.dt:.4e} s)")
        return StabilityError(
            f"{len(elements)} element(s) inverted (J = det F <= 0) at step {step} (t = {step * self.dt:.6g} s): "
            f"element(s) {_listed(elements)}; no time step is stable once an element folds. Rerun with a "
            f"smaller dt{before}, smaller or more slowly ramped loads, or a finer mesh where the elements "
            "fold", elements=elements)

    def check(self, state) -> float:
        """The stable step [s] (alpha_s = 1) of a global :class:`~jaxsync.fem.SolverState`.

        Raises:
            StabilityError: an inverted element (``elements`` holds them), or dt above the
                state's stable step; the message names the step, the time, the bound and
                the fix.
        """
        step = int(state.step)
        u = jnp.asarray(state.displacement)
        bad = inverted_elements(self.operator, u)
        if len(bad):
            raise self._inverted(bad, step)
        beta = self.problem.stiffness_damping  # the bounds with stiffness-proportional damping
        name = "sqrt((2/omega_max)^2 + beta^2) - beta" if self.problem.stiffness_damped else "2/omega_max"
        bound = damped_bound(stable_dt(self.operator, u, alpha_s=1.0, rule="element"), beta)
        if self.dt > bound or self.problem.supports:
            bound = damped_bound(exact_stable_dt(self.problem, np.asarray(u)), beta)
            if self.dt > bound:
                raise StabilityError(
                    f"dt={self.dt:.4e} s is above the stable step {name} = {bound:.4e} s of the deformed "
                    f"state at step {step} (t = {step * self.dt:.6g} s; its tangent stiffness over the lumped "
                    f"mass): rerun with dt <= {ALPHA_S * bound:.4e} s (alpha_s = {ALPHA_S}) or smaller, as the "
                    "bound can shrink further as the body deforms, or with smaller loads")
        self.last = (step, bound)
        return bound

    def diagnose(self, advance, state, until: int, block: int = 100) -> StabilityError | None:
        """Replay the run from the global ``state`` (the start of the chunk that diverged)
        up to step ``until``, ``block`` steps per call of ``advance`` (a compiled
        :func:`jaxsync.fem.advance`), and return the error naming the first step
        with an inverted element (J <= 0 while the displacement is still finite), or None
        when the displacement went NaN/Inf or blew up first."""
        step = int(state.step)
        while step < until:
            n = min(block, until - step)
            state, saved = advance(self.system, state, n, 1)
            worst = np.asarray(_replay_jacobians(self.operator, saved))  # (n, n_elements)
            finite = np.isfinite(np.asarray(saved)).all(axis=(1, 2))
            bad = ~(np.isfinite(worst) & (worst > 0)).all(axis=1) | ~finite
            if bad.any():
                i = int(np.argmax(bad))
                if not finite[i]:
                    return None
                return self._inverted(np.flatnonzero(~(worst[i] > 0)).astype(np.int64), step + i + 1)
            step += n
        return None
