"""Per-part, per-step timing breakdown of the distributed explicit solver (paper section 7):
:func:`timing_breakdown` (t_e, t_m, t_s, t_o, t_t per part) and :func:`speedup_breakdown`
(the synchronized against the synchronization-avoiding solver, in one run).

The quantities and the reports are defined in :mod:`jaxsync.perf.reports`, the timed
programs in :mod:`jaxsync.perf.kernels`, the harness in :mod:`jaxsync.perf.measure`.

Method. Per part, on one device and at the part's own (unpadded) size, the local
variants of :mod:`jaxsync.perf.kernels` are compiled and timed round-robin, the best of
``repeats`` calls each (:func:`jaxsync.perf.measure.best_times`); the cost of a call
(``no_step``) is removed before dividing by ``n_steps``. Per step, with each T the best
time of its variant:

    internal force:  t_e + t_m = T_force - T_other  (what it adds to the real step)
    recompute:       t_m = T_scat - T_empty (at most t_e + t_m), t_e = the rest
    preassembled:    t_m = T_force - T_other, t_e = 0
    t_o = T_other,  t_local = T_full.

On a shared machine, short calls (about 1 ms: small ``n_steps``) and many repeats work
best: the best repeat is then a call that the OS did not interrupt.

The synchronization cannot be timed on one device: the padded SPMD program of all parts
(exactly the :class:`jaxsync.solve.executors.DistributedRunner`'s) is timed with and
without synchronization, and t_s = T_dist(sync) - T_dist(no sync) is given to every part
(the collective makes every part wait for it). With one part there is nothing to
synchronize and t_s = 0 without measuring. Both distributed timings are in the report
(``t_step``, ``t_step_nosync``): t_step is the real per-step cost of the whole program.

Limits. Differences of variants assume that stage costs add: a row's ``r_sum`` shows how
far they do (``benchmarks/bench_distributed.py`` prints it; on this kind of machine,
unloaded, within 10 %). In recompute mode the real step may overlap the scatter with the
element computation; the split of the internal force into t_e and t_m is the convention
above (scatter timed alone), their sum is measured. Stage times are clipped at 0 when
noise makes a difference negative. Per-part numbers are measured at each part's own size,
while the SPMD program pads every part to the largest, so there every part costs about as
much as the largest. With emulated CPU devices (``--xla_force_host_platform_device_count``)
all "devices" share the machine's cores: t_step is then close to the sum of the parts'
work divided by the core count rather than the largest part's, and t_s includes the cost
of the device threads meeting at a barrier every step on oversubscribed cores, so it
overstates what separate machines would pay. Timings from a loaded machine vary;
``TimingReport.loadavg`` records the load.
"""

from __future__ import annotations

import dataclasses
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError, ProblemError
from ..fem._stepper import SolverState, build_system, initial_state
from ..fem.forces._internal_force import ForceModel, force_model
from ..options import Mode
from ..parallel._layout import PartLayout, part_systems
from ..parallel._partitioning import Partition, partition
from ..parallel.exchange._builtin import Halo, sync_strategy
from ..precision import require_float64
from ..solve.executors._distributed import DistributedParts, DistributedRunner
from ..solve.executors._predicted import PredictedPhase
from ..surrogate.training._histories import shared_dof_layout
from . import kernels
from .measure import best_times, describe_devices, per_step_times
from .reports import PartTiming, SpeedupReport, TimingReport

__all__ = ["timing_breakdown", "speedup_breakdown"]


def _check_counts(**values) -> None:
    for name, value in values.items():
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer))
                                  or value < 1):
            raise ProblemError(f"{name} must be a positive integer, got {value!r}")


def _partition_of(problem, partitions):
    return partitions if isinstance(partitions, Partition) else partition(problem.mesh, partitions)


def _start(problem, dt: float, mode: Mode | ForceModel):
    """(global system, host d(0), host d(-1)) of the paper's start."""
    system = build_system(problem, dt, mode)
    state = initial_state(problem, system)
    return system, np.asarray(state.displacement), np.asarray(state.previous)


def _local_stage_times(problem, system, part_info, part, d0, dm1, mode, n_steps, repeats, device):
    """({variant: seconds per step}, setup seconds) of one part alone on ``device``."""
    start = time.perf_counter()
    stacked = part_systems(problem, system, PartLayout.of(part_info.alone(part.index)), mode)
    setup_s = time.perf_counter() - start
    part_system = jax.device_put(jax.tree_util.tree_map(lambda x: np.asarray(x)[0], stacked.system), device)
    part_state = jax.device_put(SolverState(d0[part.nodes], dm1[part.nodes],
                                            jnp.asarray(0, dtype=jnp.int32)), device)
    scale = jax.device_put(jnp.zeros(()), device)
    recompute = force_model(mode).name == "recompute"
    names = ["full", "other", "force", "empty", "call"] + (["scatter"] if recompute else [])
    calls = {name: (jax.jit(kernels.LOCAL_VARIANTS[name], static_argnums=3),
                    (part_system, part_state, scale, n_steps)) for name in names}
    if recompute:
        forces = jax.device_put(jnp.ones((len(part.elements), 4, 3)), device)
        calls["scatter"] = (calls["scatter"][0], (part_system, part_state, scale, n_steps, forces))
    return per_step_times(best_times(calls, repeats), n_steps), setup_s


def timing_breakdown(problem, partitions=1, *, mode: Mode | ForceModel = "preassembled", n_steps: int | None = None,
                     repeats: int = 100, dt=None, sync="psum", devices=None) -> TimingReport:
    """Measure t_e, t_m, t_s, t_o and t_t per part and per step (method: module docstring).

    Args:
        problem: a :class:`jaxsync.Problem` (concrete, not traced).
        partitions: int n_parts (METIS, seed 0) or a :class:`jaxsync.Partition`.
        mode: ``"preassembled"`` or ``"recompute"`` (paper Remark 2), or a force model
            (e.g. ``Preassembled(product="compact")``: the form a short run compiles,
            :func:`jaxsync.fem.forces.run_force_model`); the report names its
            ``name``.
        n_steps: steps per timed call; about 1 ms per call is a good choice (the per-call
            cost is measured and removed, so short calls lose no accuracy). Default
            (None): 20000 / (nodes of the largest part), clipped to [5, 400].
        repeats: timed calls per variant after the warm-up; the best is kept. The time
            taken is about 5 * repeats * n_steps * (per-step cost) per part, plus the
            compilation of 5-6 small programs per part.
        dt: time step [s] of the timed steps, which start from the paper's initial
            state; default ``problem.dt`` (the speed does not depend on it).
        sync: the exchange timed as t_s, :class:`jaxsync.Psum`, :class:`jaxsync.Ppermute`,
            :class:`jaxsync.Halo` or any other exchange of one process's devices (or a
            registered name), with the devices of the distributed program (default as in
            :func:`jaxsync.simulate`; each part's own program runs on the first). The parts
            are those of its plan (with a halo the grown ones of its depth k, their
            redundant work in t_e, t_m, t_o); an exchange every k steps
            (``plan.cost.every``) gives t_s per step, and ``n_steps`` is rounded up to a
            multiple of k.
        devices: the devices of the distributed program, passed to the exchange's plan
            (None: the exchange's own choice).

    Returns:
        :class:`jaxsync.perf.reports.TimingReport`, times in seconds per step.

    Raises:
        ProblemError: bad ``mode``, ``n_steps`` or ``repeats``.
        PartitionError: a partition that cannot be made or does not fit the mesh.
    """
    require_float64("timing_breakdown")
    mode_name = force_model(mode).name  # a bad name: ProblemError naming the allowed ones
    _check_counts(n_steps=n_steps, repeats=repeats)
    dt = float(problem.dt if dt is None else dt)
    part_info = _partition_of(problem, partitions)
    # The exchange's plan: the parts as the distributed program holds them, the devices.
    distributed = DistributedParts(problem, part_info, sync_strategy(sync), mode=mode, devices=devices)
    if n_steps is None:
        n_steps = int(np.clip(round(20000 / max(p.n_local for p in part_info.parts)), 5, 400))
    n_steps, repeats = int(n_steps), int(repeats)
    every = distributed.plan.cost.every  # timed calls hold whole exchange cycles
    n_steps = -(-n_steps // every) * every
    system, d0, dm1 = _start(problem, dt, mode)

    # The distributed program (padded parts on all devices).
    runner = DistributedRunner(problem, system, distributed, save_every=n_steps)

    # Each part alone, at its own size, on one device.
    setup_s, local_times = 0.0, []
    for part in runner.layout.parts:
        times, seconds = _local_stage_times(problem, system, runner.layout.partition, part, d0, dm1, mode,
                                            n_steps, repeats, runner.devices[0])
        local_times.append(times)
        setup_s += seconds

    if part_info.n_parts > 1:
        dist_state = runner.from_global(SolverState(d0, dm1, 0))
        calls = {"sync": (kernels.distributed_step(runner, n_steps, True), (runner.parts, dist_state)),
                 "nosync": (kernels.distributed_step(runner, n_steps, False), (runner.parts, dist_state)),
                 "call": (kernels.distributed_no_step(runner), (runner.parts, dist_state))}
        dist = per_step_times(best_times(calls, repeats), n_steps)
        t_step, t_step_nosync = dist["sync"], dist["nosync"]
        t_s = max(t_step - t_step_nosync, 0.0)
    else:
        t_step = t_step_nosync = local_times[0]["full"]
        t_s = 0.0

    rows = []
    for part, t in zip(runner.layout.parts, local_times):
        t_force = max(t["force"] - t["other"], 0.0)
        t_m = min(max(t["scatter"] - t["empty"], 0.0), t_force) if mode_name == "recompute" else t_force
        rows.append(PartTiming(part=part.index, n_nodes=part.n_local, n_elements=len(part.elements),
                               n_shared=part.n_shared, t_e=t_force - t_m, t_m=t_m,
                               t_s=t_s, t_o=t["other"], t_local=t["full"], t_t=t["full"] + t_s))
    return TimingReport(mode=mode_name, n_parts=part_info.n_parts, n_shared_nodes=part_info.n_interface,
                        n_nodes=problem.n_nodes, n_elements=problem.mesh.n_elements,
                        n_steps=n_steps, repeats=repeats, dt=dt,
                        device=describe_devices(runner.devices), n_devices=len(runner.devices),
                        rows=tuple(rows), t_step=t_step, t_step_nosync=t_step_nosync,
                        setup_s=setup_s, loadavg=os.getloadavg())


def _baselines(syncs) -> dict:
    """{label: exchange} of the synchronized baselines of :func:`speedup_breakdown`: each an
    exchange or a registered name that synchronizes every step (ProblemError naming the
    fix)."""
    try:
        strategies = [sync_strategy(m) for m in syncs]
    except ConfigError as exc:
        raise ProblemError(f"syncs: {exc}") from None
    if not strategies or not all(m.synchronizes_every_step for m in strategies):
        raise ProblemError(f"syncs must be exchanges that synchronize every step, e.g. 'psum' and/or 'ppermute' "
                           f"(deep halos go in halo_depths=), got {syncs!r}")
    return {m.name: m for m in strategies}


def _part_prediction_times(predictor, n_parts: int, history: int, n_dof: int, device, repeats: int):
    """(n_parts,) wall time [s] of each part's batched refill prediction alone on ``device``
    (the cost of a call removed)."""
    predict, call = kernels.part_prediction(), kernels.no_prediction()
    out = []
    for p in range(n_parts):
        own = jax.device_put(jax.tree_util.tree_map(lambda x: np.asarray(x)[p], predictor), device)
        buf = jax.device_put(np.zeros((history, n_dof)), device)
        t = best_times({"predict": (predict, (own, buf)), "call": (call, (buf,))}, repeats)
        out.append(max(t["predict"] - t["call"], 0.0))
    return tuple(out)


def speedup_breakdown(problem, partitions, predictor=None, *, mode: Mode | ForceModel = "preassembled",
                      syncs=("psum", "ppermute"), n_cycles: int = 1, repeats: int = 10,
                      stage_repeats: int = 50, dt=None, prediction_repeats: int | None = None,
                      halo_depths: tuple = ()) -> SpeedupReport:
    """Time the synchronized solver (each of ``syncs``) and the synchronization-avoiding
    solver (paper Algorithm 3's predicted phase) in one run, and the stages of both.

    The whole SPMD programs -- synchronized with each method, without synchronization,
    and synchronization-avoiding, all advancing ``n_cycles`` refill cycles of n_s n_f
    steps -- are timed round-robin (the best of ``repeats`` calls each, the cost of a
    call removed), so that a drift of the machine's load hits all alike; zeta is the
    ratio of the best synchronized program to the avoiding one. Each part's batched
    refill prediction is timed alone on one device (t_d per prediction; per step over
    the n_s n_f steps it serves), and so is one prediction of all parts at once in the
    SPMD program (the t_d the program pays). The per-part stages t_e, t_m, t_s, t_o come from
    :func:`timing_breakdown` with the faster synchronization.

    Args:
        problem: a :class:`jaxsync.Problem`.
        partitions: int n_parts (METIS, seed 0) or a :class:`jaxsync.Partition`.
        predictor: a :class:`jaxsync.surrogate.Surrogate` (trained or not) or
            :class:`~jaxsync.solve.coupling.OraclePredictor`; default: untrained replicas of the
            paper's architecture (n_H = 100, 2 layers, n_p = n_f = 20) at the paper's stride
            n_s = 80 (:meth:`jaxsync.surrogate.Surrogate.initialized`; another stride:
            ``Surrogate.initialized(partition, n_s)``): the cost does not depend on the
            weights.
        mode: ``"preassembled"`` or ``"recompute"``, or a force model (as
            :func:`timing_breakdown`).
        syncs: exchanges to time for the baseline (the faster one is kept):
            :class:`jaxsync.Psum` and/or :class:`jaxsync.Ppermute`, or any exchange that
            synchronizes every step, or registered names; the first one's devices run
            every program. The report keys them by their ``name``.
        n_cycles, repeats: refill cycles per timed call, timed calls per program.
        stage_repeats: ``repeats`` of the per-part stage timing.
        prediction_repeats: timed calls of each part's prediction alone (default
            max(repeats, 20); a refill of the vessel's n_s = 1000 takes about a second).
        halo_depths: depths k of deep halos (:mod:`jaxsync.parallel.exchange`, the exact
            communication-avoiding scheme) to time in the same round-robin, each a divisor
            of the timed steps n_cycles n_s n_f (``t_step_halo`` of the report).

    Returns:
        :class:`jaxsync.perf.reports.SpeedupReport`.
    """
    require_float64("speedup_breakdown")
    strategies = _baselines(syncs)
    syncs = tuple(strategies)
    _check_counts(n_cycles=n_cycles, repeats=repeats)
    part_info = _partition_of(problem, partitions)
    if part_info.n_parts < 2:
        raise ProblemError("the synchronization-avoiding solver needs at least 2 parts")
    if predictor is None:
        from ..surrogate._model import Surrogate

        predictor = Surrogate.initialized(part_info, 80)
    n_s, n_p, n_f = predictor.n_s, predictor.n_past, predictor.n_future
    cycle_steps, history = n_s * n_f, n_s * n_p
    n_steps = n_cycles * cycle_steps
    dt = float(problem.dt if dt is None else dt)
    if hasattr(predictor, "for_problem"):  # surrogates with load input read the problem's load signals
        predictor = predictor.for_problem(problem, dt)
    system, d0, dm1 = _start(problem, dt, mode)
    n_dof, _ = shared_dof_layout(part_info)

    first = DistributedParts(problem, part_info, strategies[syncs[0]], mode=mode)
    devices = first.devices  # the first exchange's devices run every program
    runners = {label: DistributedRunner(problem, system, first if label == syncs[0] else
                                        DistributedParts(problem, part_info, m, mode=mode, devices=devices),
                                        save_every=n_steps) for label, m in strategies.items()}
    runner = runners[syncs[0]]
    dist_state = runner.from_global(SolverState(d0, dm1, 0))
    online = PredictedPhase(runner, predictor, save_every=cycle_steps)
    buffer = runner.put(np.zeros((part_info.n_parts, history, n_dof)))
    calls = {f"sync:{m}": (kernels.distributed_step(r, n_steps, True), (r.parts, dist_state))
             for m, r in runners.items()}
    calls["nosync"] = (kernels.distributed_step(runner, n_steps, False), (runner.parts, dist_state))
    calls["avoid"] = (online.prepare(dist_state, buffer, n_cycles, cycle_steps),
                      (runner.parts, online.predictor, dist_state, buffer, online.step_counter(0)))
    for k in halo_depths:
        if n_steps % Halo(k).depth:
            raise ProblemError(f"halo depth {k} does not divide the {n_steps} timed steps "
                               f"(n_cycles n_s n_f): use a divisor of {n_steps}")
        halo = DistributedRunner(problem, system, DistributedParts(problem, part_info, Halo(k), mode=mode,
                                                                   devices=devices), save_every=n_steps)
        calls[f"halo:{k}"] = (kernels.distributed_step(halo, n_steps, True),
                              (halo.parts, halo.from_global(SolverState(d0, dm1, 0))))
    calls["call"] = (kernels.distributed_no_step(runner), (runner.parts, dist_state))
    calls["predict"] = (kernels.prediction_program(runner.device_mesh), (online.predictor, buffer))
    whole = per_step_times(best_times(calls, repeats), n_steps)
    t_prediction_spmd = whole.pop("predict") * n_steps
    t_step_sync = {m: whole[f"sync:{m}"] for m in syncs}
    t_step_halo = {int(k): whole[f"halo:{k}"] for k in halo_depths}
    best = min(t_step_sync, key=t_step_sync.get)
    t_prediction = _part_prediction_times(predictor, part_info.n_parts, history, n_dof,
                                          runner.devices[0],
                                          max(repeats, 20) if prediction_repeats is None else prediction_repeats)

    synchronized = timing_breakdown(problem, part_info, mode=mode, repeats=stage_repeats, dt=dt,
                                    sync=strategies[best], devices=devices)
    # every part's prediction runs at the same time in the program: each pays the SPMD time
    t_d = t_prediction_spmd / cycle_steps
    rows = tuple(dataclasses.replace(r, t_s=0.0, t_d=t_d, t_t=r.t_local + t_d)
                 for r in synchronized.rows)
    avoiding = dataclasses.replace(synchronized, rows=rows, t_step=whole["avoid"],
                                   t_step_nosync=whole["nosync"])
    arch = getattr(predictor, "arch", None)
    return SpeedupReport(synchronized=synchronized, avoiding=avoiding, sync=best,
                         t_step_sync=t_step_sync, t_step_nosync=whole["nosync"],
                         t_step_avoiding=whole["avoid"], t_prediction=t_prediction,
                         t_prediction_spmd=t_prediction_spmd,
                         n_s=int(n_s), n_past=int(n_p), n_future=int(n_f),
                         architecture=arch.to_dict() if arch is not None else {},
                         n_steps=n_steps, repeats=repeats, t_step_halo=t_step_halo)
