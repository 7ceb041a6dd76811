"""The programs the timing breakdown times: variants of the stepper, one per stage, and
the whole SPMD programs.

Inside one compiled step there is nowhere to put a timer between stages, so each stage
is timed as a separately compiled *variant* of the stepper with the solver's own loop
structure (``lax.scan`` over ``n_steps`` steps, ``unroll=STEP_UNROLL``, the same
:class:`~jaxsync.fem.SolverState` carry), built from the stepper's public pieces
(:func:`~jaxsync.fem.step`, ``central_difference``, ``apply_dirichlet``). Every
local variant has the signature ``(system, state, scale, n_steps) -> state``: ``system``
an :class:`~jaxsync.fem.ExplicitSystem` of n nodes, ``state`` d(n), d(n-1) of
shape (n, 3) and the step counter, ``scale`` a float64 scalar passed at run time (the
timing passes 0; XLA cannot fold a run-time 0 away), ``n_steps`` static.

    local_step             the real step without synchronization     (T_full)
    step_without_force     the step with K d replaced by zero         (T_other)
    step_with_scaled_force the step with K d times ``scale``: with 0   (T_force)
                           the force is computed inside the real
                           update loop, as XLA fuses it there, but does
                           not act; with 1 it is the real step
    scatter_only           (recompute) d <- d + scale segment_sum(     (T_scat)
                           weight (F + scale d_00)) for given element
                           forces F (n_elements, 4, 3): the scatter-add
                           alone (scale d_00 keeps it inside the loop)
    scaled_carry           d(n+1) = d(n) + scale d(n-1): the loop, the (T_empty)
                           carry and one axpy, no work
    no_step                no step at all: d + scale, the cost of a    (T_call)
                           call (dispatch, argument handling)

Why the internal force is timed inside the update loop: XLA fuses the mat-vec and the
update into one loop, and there the mat-vec costs 10-15 % more than as a kernel of its
own (measured on this machine: the mat-vec alone plus the update alone came to 0.90-0.92
of the real step at 234 to 4949 nodes).

The SPMD programs (all built by :func:`jaxsync.parallel.spmd_program`, the parts of
a device vmapped, the parts sharded over the devices): the distributed runner's own
chunk with and without synchronization (:func:`distributed_step`), the same shape doing
no step (:func:`distributed_no_step`), and one refill prediction of every part
(:func:`prediction_program`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..fem._stepper import STEP_UNROLL, SolverState, apply_dirichlet, backward_velocity, central_difference, step
from ..parallel._spmd import spmd_program

__all__ = ["local_step", "step_without_force", "step_with_scaled_force", "scatter_only",
           "scaled_carry", "no_step", "LOCAL_VARIANTS", "distributed_step",
           "distributed_no_step", "prediction_program", "part_prediction", "no_prediction"]


def _scan(body, state: SolverState, n_steps: int) -> SolverState:
    """``n_steps`` applications of ``body`` in the solver's loop structure
    (:func:`jaxsync.fem.advance`), so that every variant pays its loop costs."""
    return jax.lax.scan(lambda s, _: (body(s), None), state, None, length=n_steps,
                        unroll=STEP_UNROLL)[0]


def local_step(system, state: SolverState, scale, n_steps: int) -> SolverState:
    """``n_steps`` real steps (:func:`jaxsync.fem.step`) without synchronization;
    ``scale`` is unused."""
    return _scan(lambda s: step(system, s), state, n_steps)


def _update(system, s: SolverState, internal_force) -> SolverState:
    new = central_difference(system, s, internal_force)
    t_new = jnp.asarray(s.step + 1, dtype=system.dt.dtype) * system.dt
    return SolverState(apply_dirichlet(system, new, t_new), s.displacement, s.step + 1)


def step_without_force(system, state: SolverState, scale, n_steps: int) -> SolverState:
    """``n_steps`` steps with the internal force K d replaced by zeros (n, 3)."""
    return _scan(lambda s: _update(system, s, jnp.zeros_like(s.displacement)), state, n_steps)


def step_with_scaled_force(system, state: SolverState, scale, n_steps: int) -> SolverState:
    """``n_steps`` steps with the internal force ``scale * K d`` (scale = 1: the real step;
    with stiffness-proportional damping, its force beta K v included as the step forms it)."""
    def force(s):
        v = backward_velocity(system, s)
        if v is None:
            return system.stiffness.matvec(s.displacement)
        return system.stiffness.damped_matvec(s.displacement, v, system.stiffness_damping)

    return _scan(lambda s: _update(system, s, scale * force(s)), state, n_steps)


def scatter_only(system, state: SolverState, scale, n_steps: int, forces) -> SolverState:
    """Recompute mode: ``n_steps`` times d <- d + scale * (the (n_elements, 4, 3) element
    forces ``forces`` + scale d[0, 0], times the padding weight, summed into the nodes),
    the sum as :meth:`jaxsync.fem.forces.ElementStiffness.matvec` does it."""
    k = system.stiffness

    def body(s):
        element = (forces + scale * s.displacement[0, 0]) * k.weight[:, None, None]  # not loop-invariant
        nodal = jax.ops.segment_sum(element.reshape(-1, 3), k.tets.reshape(-1),
                                    num_segments=s.displacement.shape[0])
        return SolverState(s.displacement + scale * nodal, s.displacement, s.step + 1)

    return _scan(body, state, n_steps)


def scaled_carry(system, state: SolverState, scale, n_steps: int) -> SolverState:
    """``n_steps`` times (d(n), d(n-1)) -> (d(n) + scale d(n-1), d(n)): the loop alone."""
    return _scan(lambda s: SolverState(s.displacement + scale * s.previous, s.displacement, s.step + 1),
                 state, n_steps)


def no_step(system, state: SolverState, scale, n_steps: int) -> SolverState:
    """No step: (d + scale, d_prev, n), whatever ``n_steps``."""
    return SolverState(state.displacement + scale, state.previous, state.step)


LOCAL_VARIANTS = {"full": local_step, "other": step_without_force, "force": step_with_scaled_force,
                  "scatter": scatter_only, "empty": scaled_carry, "call": no_step}
"""The local variants by the name the timing gives them (T_full, T_other, ...)."""


def distributed_step(runner, n_steps: int, synchronize: bool):
    """The padded SPMD program of a :class:`jaxsync.solve.executors.DistributedRunner`,
    ``(parts, state) -> (state, saved)``, advancing ``n_steps`` steps in one chunk with
    or without the force synchronization: the runner's own program."""
    return runner.program(1, save_every=n_steps, synchronize=synchronize)


def distributed_no_step(runner):
    """The same SPMD shape doing no step, ``(parts, state) -> state`` (:func:`no_step` on
    every part): the cost of a call of the whole program."""
    def per_part(part, state):
        return no_step(part.system, state, jnp.zeros(()), 0)

    return spmd_program(per_part, runner.device_mesh, n_in=2, n_out=1)


def prediction_program(device_mesh):
    """One refill prediction of every part at once, ``(predictor, buffer) -> predictions``:
    ``predictor`` stacked on the part axis (as :class:`jaxsync.solve.executors.PredictedPhase`
    places it), ``buffer`` (n_parts, n_s n_p, n_dof), predictions (n_parts, n_s n_f, n_dof)."""
    return spmd_program(lambda pred, buf: pred.predict(buf, 0), device_mesh, n_in=2, n_out=1)


def part_prediction():
    """One part's refill prediction on one device, ``(predictor, buffer (n_s n_p, n_dof))
    -> (n_s n_f, n_dof)``, jitted."""
    return jax.jit(lambda pred, buf: pred.predict(buf, 0))


def no_prediction():
    """The cost of a call with a buffer argument, ``buffer -> buffer + 0``, jitted."""
    return jax.jit(lambda buf: buf + 0.0)
