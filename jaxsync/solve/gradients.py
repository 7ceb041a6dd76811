"""Reverse mode through long explicit runs in bounded memory (recomputation).

``jax.grad`` through the one ``lax.scan`` of :func:`jaxsync.fem.stepper.advance` keeps
the residuals of every step: two (n_nodes, 3) float64 fields per step (d(n) for the
derivative of K d(n) in the Lame parameters, d(n-1) for the damping term), so memory
grows like n_steps. :func:`advance_checkpointed` computes the same values, but splits
the time loop into segments whose bodies are ``jax.checkpoint``-ed: the forward pass
keeps only the states at segment boundaries, and the reverse pass recomputes one
segment at a time from its boundary state (one extra forward run). With segments of
about sqrt(n_steps) steps the reverse pass holds about 2 sqrt(n_steps) states plus the
saved outputs, for one more forward pass of compute.

When ``save_every`` exceeds the segment length (few saves, many steps between them),
the steps of one save are themselves split into checkpointed sub-segments of about
sqrt(save_every) steps: memory is then n_saves + 2 sqrt(save_every) states, for two
extra forward passes.

:func:`partitioned_trajectory` runs the same checkpointed loop over parts under
``jax.shard_map`` (the distributed solver's programs) with traced material, damping,
loads and dt, so that distributed runs are differentiable too.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ProblemError
from ..fem.stepper import STEP_UNROLL, ExplicitSystem, SolverState, advance, step
from ..parallel.exchange import PartSystems

__all__ = ["advance_checkpointed", "advance_for_gradients", "segment_steps_for_budget",
           "state_bytes", "step_residual_bytes", "partitioned_trajectory",
           "sync_avoiding_trajectory"]


def state_bytes(n_nodes: int, itemsize: int = 8) -> int:
    """Bytes of one state's two (n_nodes, 3) displacement levels."""
    return 2 * 3 * int(n_nodes) * int(itemsize)


def step_residual_bytes(system: ExplicitSystem, itemsize: int = 8) -> int:
    """Estimated bytes reverse mode stores per step of ``system`` (one part's).

    With the symmetric node-blocked ELL stiffness of :func:`jaxsync.fem.stepper.build_system`,
    whose product has its own reverse pass (:class:`jaxsync.fem.sparse.BlockEll`,
    ``symmetric=True``: only u is kept): 3 (n_nodes, 3) fields, as measured on the coarse
    cantilever (compiled temp memory of plain reverse mode / n_steps: 3.03-3.12 fields).
    A general BlockEll keeps every gathered neighbour value, 3 width + 2 fields (29 on the
    cantilever, measured before the symmetric product). For the matrix-free stiffness only
    the two displacement levels are counted (a lower bound)."""
    from ..fem.sparse import BlockEll

    n_nodes = int(np.shape(system.mass)[-2])
    fields = 2
    if isinstance(system.stiffness, BlockEll):
        fields = 3 if system.stiffness.symmetric else 2 + 3 * int(np.shape(system.stiffness.columns)[-1])
    return fields * 3 * n_nodes * int(itemsize)


def segment_steps_for_budget(n_steps: int, bytes_per_step: int, budget_bytes: int | None = None) -> int | None:
    """Steps per checkpointed segment for a reverse pass through ``n_steps`` steps that
    store ``bytes_per_step`` each (:func:`step_residual_bytes`).

    Returns None (no checkpointing: the plain scan, one forward pass less) when storing
    every step, ``n_steps * bytes_per_step``, fits in ``budget_bytes``; otherwise about
    sqrt(n_steps), the segment length that minimizes the steps held (boundaries plus one
    segment, about 2 sqrt(n_steps)). ``budget_bytes=None``: always checkpoint. A budget
    below that cannot be met by two levels of recomputation; the sqrt split is used
    anyway (the least memory this module offers)."""
    n_steps = int(n_steps)
    if budget_bytes is not None and n_steps * int(bytes_per_step) <= int(budget_bytes):
        return None
    return max(1, math.isqrt(max(n_steps, 1)))


def _checkpointed_scan(body, carry, n: int, length: int, unroll: int = 1):
    """``lax.scan(body, carry, None, length=n)`` in segments of ``length`` iterations,
    each ``jax.checkpoint``-ed: the reverse pass keeps the carry at segment boundaries and
    recomputes one segment at a time. The n % length iterations left over form one more
    (shorter) checkpointed segment. Outputs are stacked (n, ...) as by the plain scan."""
    def segment(count):
        # prevent_cse=False: inside a scan the recomputation cannot be CSE'd away (the
        # JAX docs' advice), and the CSE barrier would only cost time
        @functools.partial(jax.checkpoint, prevent_cse=False)
        def run(c, _):
            return jax.lax.scan(body, c, None, length=count, unroll=unroll)
        return run

    n_full, rest = divmod(int(n), int(length))
    pieces = []
    if n_full:
        carry, ys = jax.lax.scan(segment(length), carry, None, length=n_full)
        pieces.append(jax.tree_util.tree_map(lambda y: y.reshape(n_full * length, *y.shape[2:]), ys))
    if rest:
        carry, ys = segment(rest)(carry, None)
        pieces.append(ys)
    if len(pieces) == 1:
        return carry, pieces[0]
    return carry, jax.tree_util.tree_map(lambda *ys: jnp.concatenate(ys), *pieces)


def advance_checkpointed(system: ExplicitSystem, state: SolverState, n_saves: int, save_every: int,
                         *, segment_steps: int | None = None, synchronize=None):
    """:func:`jaxsync.fem.stepper.advance` with a bounded-memory reverse pass.

    Args:
        system: the (possibly traced) :class:`ExplicitSystem` (one part's, under
            ``shard_map``).
        state: the :class:`SolverState` to start from, fields (n_nodes, 3) [cm].
        n_saves, save_every: run ``n_saves * save_every`` steps, keeping the displacement
            after every ``save_every`` steps (static ints).
        segment_steps: steps per checkpointed segment, the steps whose states the reverse
            pass holds at once (default about sqrt(n_saves * save_every)). Segments are
            whole saves when ``save_every <= segment_steps``; otherwise each save is one
            checkpointed unit, split into sub-segments of about sqrt(save_every) steps.
        synchronize: see :func:`jaxsync.fem.stepper.step` (the distributed psum).

    Returns:
        (final state, (n_saves, n_nodes, 3) saved displacements [cm]), equal in value to
        ``advance(system, state, n_saves, save_every, synchronize=synchronize)``.
        Reverse-mode memory: about n_steps / segment_steps boundary states
        (:func:`state_bytes`) plus segment_steps steps' residuals
        (:func:`step_residual_bytes`), plus the saved outputs.
    """
    n_saves, save_every = int(n_saves), int(save_every)
    if n_saves < 1 or save_every < 1:
        raise ProblemError(f"need n_saves >= 1 and save_every >= 1, got {n_saves}, {save_every}")
    n_steps = n_saves * save_every
    length = max(1, math.isqrt(n_steps)) if segment_steps is None else max(1, int(segment_steps))

    def one_step(s, _):
        return step(system, s, synchronize), None

    if save_every <= length:
        # segments of whole saves; a save's steps run in a plain (unrolled) scan
        def one_save(s, _):
            if save_every == 1:
                s, _ = one_step(s, None)
            else:
                s, _ = jax.lax.scan(one_step, s, None, length=save_every, unroll=STEP_UNROLL)
            return s, s.displacement

        return _checkpointed_scan(one_save, state, n_saves, max(1, length // save_every))

    # long saves: every save is a checkpointed unit (n_saves boundary states), and its
    # steps run in checkpointed sub-segments of about sqrt(save_every) steps
    inner = max(1, math.isqrt(save_every))
    if n_saves == 1:
        # one save: its sub-segments alone (a checkpoint around them would only recompute
        # the whole run once more, for the same memory)
        s, _ = _checkpointed_scan(one_step, state, save_every, inner, unroll=STEP_UNROLL)
        return s, s.displacement[None]

    def long_save(s, _):
        s, _ = _checkpointed_scan(one_step, s, save_every, inner, unroll=STEP_UNROLL)
        return s, s.displacement

    return _checkpointed_scan(long_save, state, n_saves, 1)


def advance_for_gradients(system: ExplicitSystem, state: SolverState, n_saves: int, save_every: int,
                          checkpoints: bool | int = True, synchronize=None):
    """The time loop of a traced (differentiated) run, per ``checkpoints``:

    * ``True``: :func:`advance_checkpointed` with sqrt(n_steps) segments;
    * ``False``: the plain :func:`jaxsync.fem.stepper.advance` (reverse mode stores every
      step: fastest, memory linear in n_steps);
    * an int: a memory budget [bytes] for the stored states: the plain loop when all
      steps fit in it (:func:`step_residual_bytes` per step), else sqrt checkpointing
      (:func:`segment_steps_for_budget`).
    """
    if isinstance(checkpoints, bool):
        segment = max(1, math.isqrt(n_saves * save_every)) if checkpoints else None
    elif isinstance(checkpoints, (int, np.integer)) and checkpoints > 0:
        segment = segment_steps_for_budget(n_saves * save_every, step_residual_bytes(system),
                                           int(checkpoints))
    else:
        raise ProblemError(f"gradient_checkpoints must be True, False or a positive memory budget "
                           f"in bytes, got {checkpoints!r}")
    if segment is None:
        return advance(system, state, n_saves, save_every, synchronize=synchronize)
    return advance_checkpointed(system, state, n_saves, save_every, segment_steps=segment,
                                synchronize=synchronize)


def partitioned_trajectory(problem, system: ExplicitSystem, state: SolverState, partitions, *,
                           n_saves: int, save_every: int, checkpoints: bool | int = True,
                           mode: str = "preassembled", seed: int = 0, devices=None,
                           sync: str | None = None):
    """The global (n_saves, n_nodes, 3) saved displacements [cm] of a distributed run
    with traced ``system`` / ``state`` (inside ``jax.grad``): the parts of
    :class:`jaxsync.solve.distributed.DistributedRunner` advanced by
    :func:`advance_for_gradients` under ``shard_map``, with the shared-node forces summed
    by psum (or ``sync="ppermute"``), and merged into the global field in JAX.

    The runner's per-part systems are built on the host in numpy from a concrete stand-in
    of the problem; the traced values enter as JAX computations: the stiffness blocks as
    lam K_lambda + mu K_mu (part blocks of each Lame operator, built once each), the mass,
    loads and Dirichlet values gathered from the global system, damping and dt broadcast.
    ``sync="psum"`` and ``"ppermute"`` only (``"mpi"`` and ``"halo"`` are refused)."""
    traced = _TracedParts(problem, system, state, partitions, save_every=save_every, mode=mode,
                          seed=seed, devices=devices, sync=sync)

    def one_part(part: PartSystems, s: SolverState):
        return advance_for_gradients(part.system, s, n_saves, save_every, checkpoints,
                                     traced.runner.force_sum(part))[1]

    return traced.run(one_part, traced.parts, traced.state)


def sync_avoiding_trajectory(problem, system: ExplicitSystem, state: SolverState, predictor, partitions, *,
                             n_cri: int, n_steps: int, save_every: int, checkpoints: bool | int = True,
                             mode: str = "preassembled", seed: int = 0, devices=None,
                             sync: str | None = None):
    """The global (n_steps // save_every, n_nodes, 3) saved displacements [cm] of a
    synchronization-avoiding run (paper Algorithm 3, no error control) as one traced JAX
    computation: differentiable in the material, damping, loads and dt of ``system`` /
    ``state`` and in the predictor's parameters (a traced
    :class:`jaxsync.surrogate.Surrogate`).

    The same program as :func:`jaxsync.solve.syncavoid.simulate_sync_avoiding`'s: steps
    1 .. n_cri synchronized (psum or ``sync="ppermute"``; the last n_s n_p of them record
    each part's shared dofs, the networks' first input history), then refill cycles of
    n_s n_f unsynchronized steps, each step followed by overwriting the part's shared dofs
    with the prediction (:func:`jaxsync.solve.predicted.overwritten_steps`); a last
    partial cycle uses the first rows of its refill. Saved values are the mean over the
    parts that hold each node (they differ at shared nodes after n_cri).

    Reverse-mode memory: the synchronized steps as :func:`advance_for_gradients`; the
    predicted ones with ``checkpoints`` (True or a budget) in checkpointed segments of
    about sqrt(n_cycles) cycles, each cycle's n_s n_f steps recomputed from its boundary.

    Args:
        predictor: stacked over the parts (leading part axis), e.g. a
            :class:`jaxsync.surrogate.Surrogate` or an
            :class:`~jaxsync.solve.predictors.OraclePredictor`, with ``n_s``, ``n_past``,
            ``n_future`` and ``predict(buffer, step)`` for one part.
        partitions: n_parts or a :class:`jaxsync.Partition` (the predictor's).
        n_cri, n_steps, save_every: as for ``simulate_sync_avoiding`` (checked there), counted
            from ``state`` (which may be a state in the middle of a run: its step counter
            carries on, for the loads' time functions).
    """
    from ..surrogate.data import shared_dof_layout
    from ..surrogate.refill import refill_cycle
    from .predicted import overwritten_steps

    traced = _TracedParts(problem, system, state, partitions, save_every=save_every, mode=mode,
                          seed=seed, devices=devices, sync=sync)
    n_dof, _ = shared_dof_layout(traced.runner.partition)
    n_parts = traced.runner.partition.n_parts
    made_for = (getattr(predictor, "n_parts", n_parts), getattr(predictor, "n_dof", n_dof))
    if made_for != (n_parts, n_dof):
        from ..errors import CheckpointError

        raise CheckpointError(f"the surrogates were made for {made_for[0]} parts of {made_for[1]} shared dofs "
                              f"but this partition has {n_parts} parts of up to {n_dof}: pass the "
                              "partition they were trained on")
    history = predictor.n_s * predictor.n_past
    cycle_steps = predictor.n_s * predictor.n_future
    before = n_cri - history  # synchronized steps before the recorded history
    before_saves, before_rest = divmod(before, save_every)
    first_save = (-before - 1) % save_every  # the history's first step that ends a save
    n_cycles, rest = divmod(n_steps - n_cri, cycle_steps)
    # segments of about sqrt(n_cycles) cycles (checkpointing on), or the plain scan
    cycles_per_segment = max(1, math.isqrt(n_cycles)) if checkpoints is not False else None

    def one_part(part: PartSystems, predict, s: SolverState):
        synchronize = traced.runner.force_sum(part)
        pieces = []
        if before_saves:
            s, saved = advance_for_gradients(part.system, s, before_saves, save_every, checkpoints, synchronize)
            pieces.append(saved)
        if before_rest:
            s, _ = advance(part.system, s, 1, before_rest, synchronize=synchronize)

        s, (every_step, recorded) = advance(part.system, s, history, 1, synchronize=synchronize,
                                            record=part.shared_displacement)
        pieces.append(every_step[first_save::save_every])
        buffer = recorded.reshape(history, -1)
        buffer = jnp.pad(buffer, ((0, 0), (0, n_dof - buffer.shape[1])))

        def cycle(carry, _):
            s, buffer, last = carry
            pred, buffer = refill_cycle(predict, buffer, last)
            s, disp, _ = overwritten_steps(part, s, pred, cycle_steps, save_every)
            return (s, buffer, last + cycle_steps), disp

        carry = (s, buffer, s.step)  # the last known step: n_cri after the given state's
        if n_cycles:
            if cycles_per_segment is None:
                carry, disp = jax.lax.scan(cycle, carry, None, length=n_cycles)
            else:
                carry, disp = _checkpointed_scan(cycle, carry, n_cycles, cycles_per_segment)
            pieces.append(disp.reshape(-1, *disp.shape[2:]))
        if rest:
            s, buffer, last = carry
            pred, _ = refill_cycle(predict, buffer, last)
            pieces.append(overwritten_steps(part, s, pred, rest, save_every)[1])
        return jnp.concatenate(pieces)

    return traced.run(one_part, traced.parts, predictor, traced.state)


class _TracedParts:
    """The distributed solver's parts with traced values (inside ``jax.grad``/``jit``):
    the runner and its tables built on the host from a concrete stand-in of the problem,
    the traced per-part systems and state as JAX computations of the global ones, and
    :meth:`run`, which runs a per-part function under ``shard_map`` and merges its saved
    local fields into the global one."""

    def __init__(self, problem, system: ExplicitSystem, state: SolverState, partitions, *, save_every: int,
                 mode: str, seed: int, devices, sync: str | None):
        from types import SimpleNamespace

        from ..fem.material import LinearElastic
        from ..fem.sparse import BlockEll
        from ..fem.stepper import build_system
        from ..options import Mode, Sync, check_option
        from ..parallel.exchange import build_part_systems
        from .distributed import DistributedRunner

        check_option("mode", mode, Mode, error=ProblemError)
        sync = "psum" if sync is None else check_option("sync", sync, Sync)
        if sync not in ("psum", "ppermute"):
            raise ProblemError(f"differentiating a distributed run supports sync='psum' or 'ppermute', "
                               f"got sync={sync!r}")
        # concrete stand-in: same mesh, Dirichlet conditions and operators, no traced values
        stand_in = problem.replace(material=LinearElastic(1.0, 0.25, 1.0), damping=0.0, loads=(),
                                   initial_displacement=None, initial_velocity=None)
        # host-side construction on concrete values, also when called under jit (which would
        # otherwise stage the stand-in's jnp operations and hand numpy tracers)
        with jax.ensure_compile_time_eval():
            stand_in_system = build_system(stand_in, 1.0, mode)
            runner = DistributedRunner(stand_in, stand_in_system, partitions, save_every=save_every,
                                       mode=mode, seed=seed, devices=devices, sync=sync)
            layout = runner.layout
            n_parts, n_local = layout.n_parts, runner.n_local
            template = build_part_systems(stand_in, stand_in_system, layout, mode)

            def lame_blocks(lam, mu):  # the parts' blocks of lam K_lambda + mu K_mu, numpy
                shim = SimpleNamespace(mesh=problem.mesh, material=SimpleNamespace(lam=lam, mu=mu))
                return build_part_systems(shim, stand_in_system, layout, mode).system.stiffness.blocks

            if mode == "preassembled":
                blocks_lambda, blocks_mu = lame_blocks(1.0, 0.0), lame_blocks(0.0, 1.0)
        m = problem.material
        if mode == "preassembled":
            stiffness = BlockEll(jnp.asarray(template.system.stiffness.columns),
                                 m.lam * jnp.asarray(blocks_lambda) + m.mu * jnp.asarray(blocks_mu),
                                 symmetric=True)
        else:
            base = template.system.stiffness
            stiffness = type(base)(jnp.asarray(base.points), jnp.asarray(base.tets), jnp.asarray(base.weight),
                                   jnp.broadcast_to(m.lam, (n_parts,)), jnp.broadcast_to(m.mu, (n_parts,)))
        # local node p of part k is global node index[k, p]; padding slots (valid False) read fill
        index = np.zeros((n_parts, n_local), dtype=np.int32)
        valid = np.zeros((n_parts, n_local), dtype=bool)
        for k, part in enumerate(layout.parts):
            index[k, :part.n_local], valid[k, :part.n_local] = part.nodes, True

        def local(field, fill):  # (..., n_nodes, 3) -> (n_parts, ..., n_local, 3)
            gathered = jnp.moveaxis(jnp.asarray(field)[..., index, :], -3, 0)
            mask = valid.reshape((n_parts,) + (1,) * (gathered.ndim - 3) + (n_local, 1))
            return jnp.where(mask, gathered, fill)

        def broadcast(x):
            return jnp.broadcast_to(x, (n_parts,) + jnp.shape(x))

        self.parts = PartSystems(
            ExplicitSystem(stiffness=stiffness, mass=local(system.mass, 1.0),
                           damping=broadcast(system.damping), dt=broadcast(system.dt),
                           load_vectors=local(system.load_vectors, 0.0),
                           load_times=jax.tree_util.tree_map(broadcast, system.load_times),
                           fixed=jnp.asarray(template.system.fixed),
                           fixed_values=local(system.fixed_values, 0.0)),
            jnp.asarray(template.shared_local), jnp.asarray(template.shared_interface))
        # the step counter carries on from the given state's (load time functions read it)
        self.state = SolverState(local(state.displacement, 0.0), local(state.previous, 0.0),
                                 jnp.broadcast_to(jnp.asarray(state.step, dtype=jnp.int32), (n_parts,)))
        self.runner, self.n_parts, self.n_local = runner, n_parts, n_local
        self.n_nodes = problem.mesh.n_nodes
        # global node of each kept local value, and how many parts hold it (for the mean)
        self._global, self._local = runner.global_index, runner.local_index
        self._count = np.bincount(self._global, minlength=self.n_nodes).astype(float)

    def run(self, per_part, *args):
        """``per_part(*one_part_args) -> (n_saved, n_local, 3)`` over all parts under
        ``shard_map``; returns the global (n_saved, n_nodes, 3) field, each node the mean
        over the parts that hold it."""
        from ..parallel.spmd import spmd_program

        program = spmd_program(per_part, self.runner.device_mesh, n_in=len(args), n_out=1, jit=False)

        def merged(*args):
            saved = program(*args)  # (n_parts, n_saved, n_local, 3)
            n_saved = saved.shape[1]
            flat = jnp.moveaxis(saved, 0, 1).reshape(n_saved, self.n_parts * self.n_local, 3)
            total = jnp.zeros((n_saved, self.n_nodes, 3), dtype=flat.dtype)
            total = total.at[:, self._global].add(flat[:, self._local])
            return total / jnp.asarray(self._count, flat.dtype)[None, :, None]

        # the program runs on the mesh's devices; the rest of a traced (eager) computation on
        # the default device: move the inputs there and the result (and, in the reverse pass,
        # the cotangents: device_put's transpose) back, or eager adds of the two meet arrays
        # committed to different devices (only when the computation runs eagerly, e.g. under
        # jax.grad alone; a staged (jitted) computation places everything on the mesh itself)
        if not all(_concrete(x) for x in jax.tree_util.tree_leaves(args)):
            return merged(*args)
        home = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        spread = jax.sharding.NamedSharding(self.runner.device_mesh, jax.sharding.PartitionSpec())
        args = jax.device_put(args, spread, src=home)
        return jax.device_put(merged(*args), home, src=spread)


def _concrete(x) -> bool:
    """True when ``x`` has a value now (an array, or a tracer of an eager jax.grad), False
    when it is staged into a jaxpr (under jit)."""
    from jax._src import core  # jax.core.is_concrete is deprecated; no public successor

    return not isinstance(x, jax.core.Tracer) or core.is_concrete(x)
