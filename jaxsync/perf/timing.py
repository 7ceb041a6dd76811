"""Per-part, per-step timing breakdown of the distributed explicit solver (paper section 7).

Quantities, all in seconds per step (tables print microseconds):

    t_e  element quantities. ``"recompute"`` mode: forming the element geometry, strains,
         stresses and element force vectors (:func:`jaxsync.fem.element_force.element_forces`,
         including the gather of the element displacements): the internal force minus
         t_m. ``"preassembled"`` mode: 0 per step; K is assembled once before the run,
         and that one-off cost is reported apart as ``TimingReport.setup_s`` (the wall
         time of building the part systems), never amortized into t_e.
    t_m  the product K d. ``"preassembled"``: the node-blocked ELL mat-vec.
         ``"recompute"``: the assembly of the product, i.e. the scatter-add of the
         (n_elements, 4, 3) element forces (times the padding weight) into the nodes,
         timed on its own.
    t_s  synchronization: scatter of the shared-node forces into the interface vector,
         psum over the parts, gather back (``jaxsync.parallel.exchange.synchronize_forces``).
    t_d  surrogate (synchronization-avoiding solver only): one batched refill prediction
         of all parts at once in the SPMD program, divided by the n_s n_f steps it
         serves (:func:`speedup_breakdown`; a part's network alone is also reported).
    t_o  everything else in a step: external force, central-difference update,
         Dirichlet values, and the loop itself (carry, counter).
    t_t  total: the part's own step without synchronization, measured, plus t_s (or,
         synchronization-avoiding, plus t_d).
    r_*  = t_* / t_t. r_e + r_m + r_s + r_o equals 1 up to measurement error, because
         t_e, t_m and t_o are measured separately from the whole local step.

"Max-average" (paper): each quantity is averaged per step over a run, and the part with
the largest t_t is reported (:func:`max_average`). Speed-up zeta = t_t / t_t' of the
synchronized and the synchronization-avoiding programs, both timed whole, round-robin,
in one run (:func:`speedup_breakdown`, :class:`SpeedupReport`).

Method. Inside one compiled SPMD step there is nowhere to put a timer between stages, so
each stage is timed as a separately compiled *variant* of the stepper with the same loop
structure (``lax.scan`` over ``n_steps`` steps, the same :class:`SolverState` carry),
built from the solver's public pieces (:func:`jaxsync.solve.solver.step`, ``advance``,
``central_difference``, ``apply_dirichlet``). Each variant is compiled and run once
(warm-up), then timed ``repeats`` times round-robin with ``block_until_ready`` (so slow
drifts of the machine's load hit all variants alike), and the best repeat is kept. A
variant ``T_call`` that does no step at all measures the cost of a call (dispatch,
argument handling); it is subtracted from every variant's time before dividing by
``n_steps``. On a shared machine, short calls (about 1 ms: small ``n_steps``) and many
repeats work best: the best repeat is then a call that the OS did not interrupt.
Per part, on one device and at the part's own (unpadded) size:

    T_full   :func:`jaxsync.solve.solver.step` without synchronization: the real local step.
    T_other  the step with the internal force replaced by zero.
    T_force  the step with the internal force K d multiplied by c = 0 passed at run
             time (XLA cannot fold it away): the internal force computed inside the real
             update loop, as XLA fuses it there, but not acting on the result.
    T_scat   (recompute) d <- d + c segment_sum(weight (F + c d_0)) for a given array F
             of element forces: the scatter alone (c d_0 keeps it inside the loop).
    T_empty  d <- d + c d(n-1): the loop, the carry and one axpy, no work.

    internal force:  t_e + t_m = T_force - T_other  (what it adds to the real step)
    recompute:       t_m = T_scat - T_empty (at most t_e + t_m), t_e = the rest
    preassembled:    t_m = T_force - T_other, t_e = 0
    t_o = T_other,  t_local = T_full     (each T per step, with T_call removed).

Why the internal force is timed inside the update loop: XLA fuses the mat-vec and the
update into one loop, and there the mat-vec costs 10-15 % more than as a kernel of its
own (measured on this machine: the mat-vec alone plus the update alone came to 0.90-0.92
of the real step at 234 to 4949 nodes; benchmarks/bench_stepper.py times the kernels).
Timed inside the loop, the stages add up to the real step (``r_sum`` within a few %).

The synchronization cannot be timed on one device: the padded SPMD program of all parts
(``jax.shard_map`` over the devices, parts of one device vmapped, exactly as in
:class:`jaxsync.solve.distributed.DistributedRunner`) is timed with and without
``synchronize_forces``, and t_s = T_dist(sync) - T_dist(no sync) is given to every part (the
psum is collective; every part waits for it). With one part there is nothing to
synchronize (no shared nodes) and t_s = 0 without measuring. Both distributed timings
are in the report (``t_step``, ``t_step_nosync``): t_step is the real per-step cost of
the whole program.

Limits. Differences of variants assume that stage costs add (the ``r_sum`` of a row
shows how far they do; on this kind of machine, unloaded, within 10 %). In recompute mode the real step may overlap the scatter
with the element computation; the split of the internal force into t_e and t_m is the
convention above (scatter timed alone), their sum is measured. Stage times are clipped
at 0 when noise makes a difference negative. Per-part numbers are measured at each part's own
size, while the SPMD program pads every part to the largest, so there every part costs
about as much as the largest. With emulated CPU devices
(``--xla_force_host_platform_device_count``) all "devices" share the machine's cores:
t_step is then close to the sum of the parts' work divided by the core count rather than
the largest part's, and t_s includes the cost of the device threads meeting at a barrier
every step on oversubscribed cores, so it overstates what separate machines would pay.
Timings from a loaded machine vary; ``TimingReport.loadavg`` records the load.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import CheckpointError, ProblemError

__all__ = ["PartTiming", "TimingReport", "timing_breakdown", "max_average", "STAGES",
           "SpeedupReport", "speedup_breakdown"]

STAGES = ("t_e", "t_m", "t_s", "t_d", "t_o")  # the additive stages of t_t


@dataclasses.dataclass(frozen=True)
class PartTiming:
    """Per-step times of one part [s] (see the module docstring for the definitions).

    Attributes:
        part: part index p.
        n_nodes: local nodes of the part.
        n_elements: elements of the part.
        n_shared: shared nodes of the part.
        t_e, t_m, t_s, t_o: stage times per step [s].
        t_local: the part's whole step without synchronization, measured [s].
        t_t: total per step, t_local + t_s + t_d [s].
        t_d: surrogate cost per step [s] (synchronization-avoiding solver: one batched
            refill prediction divided by the n_s n_f steps it serves; 0 otherwise).
    """

    part: int
    n_nodes: int
    n_elements: int
    n_shared: int
    t_e: float
    t_m: float
    t_s: float
    t_o: float
    t_local: float
    t_t: float
    t_d: float = 0.0

    def __post_init__(self):
        for name in (*STAGES, "t_local", "t_t"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ProblemError(f"PartTiming.{name} must be a finite time >= 0 s, got {value!r}")

    def ratio(self, name: str) -> float:
        """r_* = t_* / t_t for ``name`` in ``t_e, t_m, t_s, t_d, t_o`` (0 when t_t is 0)."""
        if name not in STAGES:
            raise ProblemError(f"ratio of {name!r}: use one of {STAGES}")
        return getattr(self, name) / self.t_t if self.t_t > 0 else 0.0

    @property
    def ratios(self) -> dict:
        """{"r_e": ..., "r_m": ..., "r_s": ..., "r_d": ..., "r_o": ...}."""
        return {"r" + name[1:]: self.ratio(name) for name in STAGES}

    @property
    def r_sum(self) -> float:
        """(t_e + t_m + t_s + t_d + t_o) / t_t: 1 when the separately measured stages add up."""
        return sum(self.ratios.values())


def max_average(rows) -> PartTiming:
    """The paper's "max-average" row: of per-step averages, the part with the largest t_t
    (the first such part on ties)."""
    rows = tuple(rows)
    if not rows:
        raise ProblemError("max_average needs at least one PartTiming row")
    return max(rows, key=lambda r: r.t_t)


@dataclasses.dataclass(frozen=True)
class TimingReport:
    """Timing breakdown of one configuration (one mesh, partition and mode).

    Attributes:
        mode: ``"preassembled"`` or ``"recompute"``.
        n_parts: n_c.
        n_shared_nodes: N_a, the number of shared (interface) nodes of the partition.
        n_nodes, n_elements: size of the mesh.
        n_steps: steps per timed call; repeats: timed calls per variant (best kept).
        dt: time step [s].
        device: description of the devices (platform, count, whether emulated).
        n_devices: devices the distributed program ran on.
        rows: one :class:`PartTiming` per part, in part order.
        t_step: measured per-step time of the whole synchronized SPMD program [s]
            (for one part: the single-part local step).
        t_step_nosync: the same program without synchronization [s].
        setup_s: one-off wall time to build the per-part systems (assembly) [s].
        loadavg: ``os.getloadavg()`` (1, 5, 15 min) when the timing ended.
    """

    mode: str
    n_parts: int
    n_shared_nodes: int
    n_nodes: int
    n_elements: int
    n_steps: int
    repeats: int
    dt: float
    device: str
    n_devices: int
    rows: tuple
    t_step: float
    t_step_nosync: float
    setup_s: float
    loadavg: tuple = ()

    def __post_init__(self):
        rows = tuple(r if isinstance(r, PartTiming) else PartTiming(**r) for r in self.rows)
        object.__setattr__(self, "rows", rows)
        object.__setattr__(self, "loadavg", tuple(float(x) for x in self.loadavg))
        if len(rows) != self.n_parts:
            raise ProblemError(f"TimingReport has {len(rows)} rows for n_parts={self.n_parts}")

    @property
    def max_average(self) -> PartTiming:
        """The row of the part with the largest t_t (paper's max-average)."""
        return max_average(self.rows)

    def table(self) -> str:
        """A printable table in microseconds per step: one line per part, then the
        max-average line and the measured whole-program step."""
        head = (f"Timing breakdown, mode={self.mode}: n_c={self.n_parts} parts, "
                f"N_a={self.n_shared_nodes} shared nodes, mesh {self.n_nodes} nodes / "
                f"{self.n_elements} tetrahedra; {self.n_steps} steps x best of {self.repeats}; "
                f"{self.device}")
        cols = (f"{'part':>7} {'nodes':>7} {'elems':>7} {'shared':>6} "
                f"{'t_e':>9} {'t_m':>9} {'t_s':>9} {'t_d':>9} {'t_o':>9} {'t_t':>9}  "
                f"{'r_e':>5} {'r_m':>5} {'r_s':>5} {'r_d':>5} {'r_o':>5} {'sum':>5}")
        lines = [head, "times in us per step", cols]

        def line(label, r):
            ratios = r.ratios
            return (f"{label:>7} {r.n_nodes:>7} {r.n_elements:>7} {r.n_shared:>6} "
                    + " ".join(f"{1e6 * getattr(r, k):>9.2f}" for k in (*STAGES, "t_t"))
                    + "  " + " ".join(f"{v:>5.3f}" for v in ratios.values())
                    + f" {r.r_sum:>5.3f}")

        for r in self.rows:
            lines.append(line(str(r.part), r))
        top = self.max_average
        lines.append(line(f"max@{top.part}", top))
        lines.append(f"whole SPMD program: {1e6 * self.t_step:.2f} us/step synchronized, "
                     f"{1e6 * self.t_step_nosync:.2f} us/step without synchronization; "
                     f"setup (assembly) {self.setup_s:.3f} s; load average "
                     + ", ".join(f"{x:.2f}" for x in self.loadavg))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-ready dict: every field, rows as dicts with their ratios, and the
        max-average row under ``"max_average"``."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["rows"] = [dict(dataclasses.asdict(r), **r.ratios) for r in self.rows]
        out["loadavg"] = list(self.loadavg)
        top = self.max_average
        out["max_average"] = dict(dataclasses.asdict(top), **top.ratios)
        out["kind"] = "jaxsync-timing-report"
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "TimingReport":
        """Inverse of :meth:`to_dict` (derived entries are recomputed, not read)."""
        names = {f.name for f in dataclasses.fields(cls)}
        row_names = {f.name for f in dataclasses.fields(PartTiming)}
        try:
            fields = {k: v for k, v in data.items() if k in names}
            fields["rows"] = tuple(PartTiming(**{k: v for k, v in r.items() if k in row_names})
                                   for r in data["rows"])
            return cls(**fields)
        except (KeyError, TypeError) as exc:
            raise CheckpointError(f"not a jaxsync timing report: {exc}") from exc

    def save_json(self, path: str | os.PathLike) -> None:
        """Write :meth:`to_dict` as JSON; the file appears only when complete."""
        from ..trajectory import atomic_path

        with atomic_path(path) as tmp:
            with open(tmp, "w") as f:
                json.dump(self.to_dict(), f, indent=2)
                f.write("\n")

    @classmethod
    def load_json(cls, path: str | os.PathLike) -> "TimingReport":
        """Read a report written by :meth:`save_json`."""
        try:
            with open(path) as f:
                data = json.load(f)
        except (OSError, ValueError) as exc:
            raise CheckpointError(f"cannot read timing report {path}: {exc}") from exc
        if data.get("kind") != "jaxsync-timing-report":
            raise CheckpointError(f"{path} is not a jaxsync timing report")
        return cls.from_dict(data)


# ---------------------------------------------------------------------------------------
# Variants of the stepper: all carry a SolverState through lax.scan(length=n_steps).


def _scan(body, state, n_steps):
    # the solver's own loop structure (jaxsync.solve.solver.advance), so that every variant
    # pays the same loop costs as the real step
    from ..fem.stepper import STEP_UNROLL

    return jax.lax.scan(lambda s, _: (body(s), None), state, None, length=n_steps,
                        unroll=STEP_UNROLL)[0]


def _full(system, state, zero, n_steps):
    from ..fem.stepper import step

    return _scan(lambda s: step(system, s), state, n_steps)


def _other(system, state, zero, n_steps):
    from ..fem.stepper import SolverState, apply_dirichlet, central_difference

    def body(s):
        new = central_difference(system, s, jnp.zeros_like(s.displacement))
        return SolverState(apply_dirichlet(system, new), s.displacement, s.step + 1)

    return _scan(body, state, n_steps)


def _force(system, state, zero, n_steps):
    from ..fem.stepper import SolverState, apply_dirichlet, central_difference

    def body(s):
        internal = zero * system.stiffness.matvec(s.displacement)
        new = central_difference(system, s, internal)
        return SolverState(apply_dirichlet(system, new), s.displacement, s.step + 1)

    return _scan(body, state, n_steps)


def _scatter(system, state, zero, n_steps, forces):
    """Recompute mode: only the sum of given (n_elements, 4, 3) element forces into the
    nodes, as :meth:`jaxsync.fem.element_force.ElementStiffness.matvec` does it."""
    from ..fem.stepper import SolverState

    k = system.stiffness

    def body(s):
        element = (forces + zero * s.displacement[0, 0]) * k.weight[:, None, None]  # not loop-invariant
        nodal = jax.ops.segment_sum(element.reshape(-1, 3), k.tets.reshape(-1),
                                    num_segments=s.displacement.shape[0])
        return SolverState(s.displacement + zero * nodal, s.displacement, s.step + 1)

    return _scan(body, state, n_steps)


def _empty(system, state, zero, n_steps):
    from ..fem.stepper import SolverState

    def body(s):
        return SolverState(s.displacement + zero * s.previous, s.displacement, s.step + 1)

    return _scan(body, state, n_steps)


def _call(system, state, zero, n_steps):
    from ..fem.stepper import SolverState

    return SolverState(state.displacement + zero, state.previous, state.step)


_LOCAL_VARIANTS = {"full": _full, "other": _other, "force": _force, "scatter": _scatter,
                   "empty": _empty, "call": _call}


def _distributed_program(runner, n_steps: int, synchronize: bool | None):
    """The padded SPMD program of ``runner`` advancing ``n_steps`` steps with or without
    synchronization (``synchronize=None``: no step at all, the cost of a call)."""
    from jax.sharding import PartitionSpec as P

    from ..parallel.exchange import AXIS, LOCAL_AXIS

    if synchronize is not None:
        return runner.program(1, save_every=n_steps, synchronize=synchronize)

    def no_step(part, state):
        return _call(part.system, state, jnp.zeros(()), 0)

    body = jax.vmap(no_step, axis_name=LOCAL_AXIS)
    return jax.jit(jax.shard_map(body, mesh=runner.device_mesh, in_specs=(P(AXIS), P(AXIS)),
                                 out_specs=P(AXIS), check_vma=False))


def _best_times(calls: dict, repeats: int) -> dict:
    """{name: best wall time [s]} of ``calls`` {name: (fn, args)}: one warm-up call each
    (compilation), then ``repeats`` timed calls, round-robin over the variants."""
    for fn, args in calls.values():
        jax.block_until_ready(fn(*args))
    best = {name: np.inf for name in calls}
    for _ in range(repeats):
        for name, (fn, args) in calls.items():
            start = time.perf_counter()
            jax.block_until_ready(fn(*args))
            best[name] = min(best[name], time.perf_counter() - start)
    return best


def _per_step(best: dict, n_steps: int) -> dict:
    """Per-step times [s] from best call times: the cost of a call (dispatch, argument
    handling; the ``"call"`` variant) removed, then divided by ``n_steps``."""
    call = best.pop("call")
    return {name: max(t - call, 0.0) / n_steps for name, t in best.items()}


def _describe_devices(devices) -> str:
    from ..parallel.devices import device_summary

    info = device_summary(devices)
    text = f"{info['n_devices']} x {info['platform']} device ({info['device_kind']})"
    if info["emulated"]:
        text += f", emulated host devices sharing {os.cpu_count()} CPU cores"
    elif info["platform"] == "cpu" and jax.process_count() == 1:
        text += ": every part on this one device, so no synchronization cost is measured"
    return text


def timing_breakdown(problem, partitions=1, *, mode: str = "preassembled", n_steps: int | None = None,
                     repeats: int = 100, dt=None, devices=None, seed: int = 0,
                     sync: str = "psum") -> TimingReport:
    """Measure t_e, t_m, t_s, t_o and t_t per part and per step (method: module docstring).

    Args:
        problem: a :class:`jaxsync.Problem` (concrete, not traced).
        partitions: int n_parts (METIS, ``seed``) or a :class:`jaxsync.Partition`.
        mode: ``"preassembled"`` or ``"recompute"`` (paper Remark 2).
        n_steps: steps per timed call; about 1 ms per call is a good choice (the per-call
            cost is measured and removed, so short calls lose no accuracy). Default
            (None): 20000 / (nodes of the largest part), clipped to [5, 400].
        repeats: timed calls per variant after the warm-up; the best is kept. The time
            taken is about 5 * repeats * n_steps * (per-step cost) per part, plus the
            compilation of 5-6 small programs per part.
        dt: time step [s] of the timed steps, which start from the paper's initial
            state; default ``problem.dt`` (the speed does not depend on it).
        devices: devices for the distributed program (default as in
            :func:`jaxsync.simulate`); each part's own program runs on the first.
        seed: METIS seed when ``partitions`` is an int.
        sync: ``"psum"`` or ``"ppermute"``, the synchronization timed as t_s (see
            :class:`jaxsync.solve.distributed.DistributedRunner`).

    Returns:
        :class:`TimingReport`, times in seconds per step.

    Raises:
        ProblemError: bad ``mode``, ``n_steps`` or ``repeats``.
        PartitionError: a partition that cannot be made or does not fit the mesh.
    """
    from ..precision import require_float64

    require_float64("timing_breakdown")
    from ..solve.distributed import DistributedRunner
    from ..parallel.exchange import build_part_systems
    from ..fem.element_force import MODES
    from ..parallel.partition import Partition, partition as make_partition
    from ..fem.stepper import SolverState, build_system, initial_state

    if mode not in MODES:
        raise ProblemError(f"mode must be one of {MODES}, got {mode!r}")
    for name, value in (("n_steps", n_steps), ("repeats", repeats)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer))
                                  or value < 1):
            raise ProblemError(f"{name} must be a positive integer, got {value!r}")
    dt = float(problem.dt if dt is None else dt)
    part_info = partitions if isinstance(partitions, Partition) else make_partition(
        problem.mesh, partitions, seed=seed)
    if n_steps is None:
        n_steps = int(np.clip(round(20000 / max(p.n_local for p in part_info.parts)), 5, 400))
    n_steps, repeats = int(n_steps), int(repeats)
    system = build_system(problem, dt, mode)
    state = initial_state(problem, system)
    d0, dm1 = np.asarray(state.displacement), np.asarray(state.previous)

    # The distributed program (padded parts on all devices); also places the devices.
    runner = DistributedRunner(problem, system, part_info, save_every=n_steps, mode=mode,
                               devices=devices, sync=sync)
    local_device = runner.devices[0]
    zero = jax.device_put(jnp.zeros(()), local_device)

    # Each part alone, at its own size, on one device.
    setup_s = 0.0
    local_times = []
    for part in part_info.parts:
        start = time.perf_counter()
        stacked = build_part_systems(problem, system, dataclasses.replace(part_info, parts=(part,)), mode)
        setup_s += time.perf_counter() - start
        part_system = jax.device_put(jax.tree_util.tree_map(lambda x: np.asarray(x)[0], stacked.system),
                                     local_device)
        part_state = jax.device_put(SolverState(d0[part.nodes], dm1[part.nodes],
                                                jnp.asarray(0, dtype=jnp.int32)), local_device)
        names = ["full", "other", "force", "empty", "call"] + (["scatter"] if mode == "recompute" else [])
        calls = {name: (jax.jit(_LOCAL_VARIANTS[name], static_argnums=3),
                        (part_system, part_state, zero, n_steps)) for name in names}
        if mode == "recompute":
            forces = jax.device_put(jnp.ones((len(part.elements), 4, 3)), local_device)
            calls["scatter"] = (calls["scatter"][0], (part_system, part_state, zero, n_steps, forces))
        local_times.append(_per_step(_best_times(calls, repeats), n_steps))

    if part_info.n_parts > 1:
        dist_state = runner.from_global(SolverState(d0, dm1, 0))
        calls = {name: (_distributed_program(runner, n_steps, synchronize=sync), (runner.parts, dist_state))
                 for name, sync in (("sync", True), ("nosync", False), ("call", None))}
        dist = _per_step(_best_times(calls, repeats), n_steps)
        t_step, t_step_nosync = dist["sync"], dist["nosync"]
        t_s = max(t_step - t_step_nosync, 0.0)
    else:
        t_step = t_step_nosync = local_times[0]["full"]
        t_s = 0.0

    rows = []
    for part, t in zip(part_info.parts, local_times):
        t_force = max(t["force"] - t["other"], 0.0)
        t_m = min(max(t["scatter"] - t["empty"], 0.0), t_force) if mode == "recompute" else t_force
        rows.append(PartTiming(part=part.index, n_nodes=part.n_local, n_elements=len(part.elements),
                               n_shared=part.n_shared, t_e=t_force - t_m, t_m=t_m,
                               t_s=t_s, t_o=t["other"], t_local=t["full"], t_t=t["full"] + t_s))
    return TimingReport(mode=mode, n_parts=part_info.n_parts, n_shared_nodes=part_info.n_interface,
                        n_nodes=problem.mesh.n_nodes, n_elements=problem.mesh.n_elements,
                        n_steps=n_steps, repeats=repeats, dt=dt,
                        device=_describe_devices(runner.devices), n_devices=len(runner.devices),
                        rows=tuple(rows), t_step=t_step, t_step_nosync=t_step_nosync,
                        setup_s=setup_s, loadavg=os.getloadavg())


# ---------------------------------------------------------------------------------------
# Synchronized against synchronization-avoiding, in one run.


@dataclasses.dataclass(frozen=True)
class SpeedupReport:
    """The synchronized and the synchronization-avoiding solver measured in one run.

    Attributes:
        synchronized: per-part breakdown of the synchronized solver with the faster
            synchronization (``sync``); t_d = 0.
        avoiding: the same parts in the synchronization-avoiding solver: t_s = 0 and t_d
            the part's surrogate cost per step; t_e, t_m, t_o are those of the
            synchronized solver's local step (the predicted step also overwrites the
            shared dofs, a gather of n_shared values, inside ``t_step_avoiding``).
        sync: the synchronization of the baseline (the faster of those timed).
        t_step_sync: {sync method: measured per-step time of the whole synchronized SPMD
            program [s]} for every method timed.
        t_step_nosync: the same program without synchronization [s].
        t_step_avoiding: measured per-step time of the whole synchronization-avoiding
            SPMD program (n_s n_f solver steps and one batched refill prediction per part
            per cycle, no collective) [s].
        t_prediction: (n_parts,) wall time of one batched refill prediction of each part,
            alone on one device [s].
        t_prediction_spmd: wall time of one batched refill prediction of every part at
            once, in the SPMD program (parts on their devices) [s]: what the
            synchronization-avoiding program pays per cycle (on devices that share
            cores or memory, more than a part alone).
        n_s, n_past, n_future: the refill geometry; one prediction serves n_s n_future steps.
        architecture: the surrogate's architecture (dict), or {} for another predictor.
        n_steps: steps per timed call of the whole programs; repeats: timed calls (best kept).
    """

    synchronized: TimingReport
    avoiding: TimingReport
    sync: str
    t_step_sync: dict
    t_step_nosync: float
    t_step_avoiding: float
    t_prediction: tuple
    t_prediction_spmd: float
    n_s: int
    n_past: int
    n_future: int
    architecture: dict
    n_steps: int
    repeats: int

    @property
    def steps_per_prediction(self) -> int:
        return self.n_s * self.n_future

    @property
    def t_step_synchronized(self) -> float:
        """Whole-program step of the synchronized baseline at its best [s]."""
        return self.t_step_sync[self.sync]

    @property
    def zeta(self) -> float:
        """Speed-up t_t / t_t' of the whole programs, measured in the same run."""
        return self.t_step_synchronized / self.t_step_avoiding

    @property
    def t_s(self) -> float:
        """Synchronization cost per step of the baseline [s] (whole programs)."""
        return max(self.t_step_synchronized - self.t_step_nosync, 0.0)

    @property
    def t_d(self) -> float:
        """Surrogate cost per step [s]: one SPMD refill prediction of all parts amortized
        over the n_s n_f steps it serves."""
        return self.t_prediction_spmd / self.steps_per_prediction

    @property
    def surrogate_pays(self) -> bool:
        """True when the amortized surrogate cost is below the synchronization it replaces."""
        return self.t_d < self.t_s

    def table(self) -> str:
        lines = [self.synchronized.table(), "", "synchronization-avoiding:", self.avoiding.table(), ""]
        lines.append("whole programs, us per step (same run, best of "
                     f"{self.repeats} calls of {self.n_steps} steps):")
        for method, t in self.t_step_sync.items():
            mark = "  <- baseline" if method == self.sync else ""
            lines.append(f"  synchronized ({method}): {1e6 * t:9.2f}{mark}")
        lines.append(f"  no synchronization:      {1e6 * self.t_step_nosync:9.2f}")
        lines.append(f"  synchronization-avoiding: {1e6 * self.t_step_avoiding:8.2f}")
        lines.append(f"  t_s = {1e6 * self.t_s:.2f} us; surrogate: {1e3 * self.t_prediction_spmd:.3f} ms "
                     f"per prediction of all parts ({1e3 * max(self.t_prediction):.3f} ms for one "
                     f"part alone) = {1e6 * self.t_d:.2f} us per step over n_s n_f = "
                     f"{self.steps_per_prediction} steps; "
                     + ("below" if self.surrogate_pays else "NOT below")
                     + " the synchronization it replaces")
        lines.append(f"  zeta = t_t / t_t' = {self.zeta:.3f}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["synchronized"] = self.synchronized.to_dict()
        out["avoiding"] = self.avoiding.to_dict()
        out["t_prediction"] = list(self.t_prediction)
        for name in ("zeta", "t_s", "t_d", "steps_per_prediction", "t_step_synchronized",
                     "surrogate_pays"):
            out[name] = getattr(self, name)
        out["kind"] = "jaxsync-speedup-report"
        return out

    def save_json(self, path: str | os.PathLike) -> None:
        """Write :meth:`to_dict` as JSON; the file appears only when complete."""
        from ..trajectory import atomic_path

        with atomic_path(path) as tmp:
            with open(tmp, "w") as f:
                json.dump(self.to_dict(), f, indent=2)
                f.write("\n")


def speedup_breakdown(problem, partitions, predictor=None, *, mode: str = "preassembled",
                      syncs=("psum", "ppermute"), n_cycles: int = 1, repeats: int = 10,
                      stage_repeats: int = 50, n_s: int = 80, devices=None, seed: int = 0,
                      dt=None) -> SpeedupReport:
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
        partitions: int n_parts (METIS, ``seed``) or a :class:`jaxsync.Partition`.
        predictor: a :class:`jaxsync.solve.syncavoid.SurrogatePredictor` (trained or not) or
            :class:`~jaxsync.solve.syncavoid.OraclePredictor`; default: untrained replicas of the
            paper's architecture (n_H = 100, 2 layers, n_p = n_f = 20) at stride ``n_s``
            (:meth:`SurrogatePredictor.initialized`): the cost does not depend on the
            weights.
        mode: ``"preassembled"`` or ``"recompute"``.
        syncs: synchronizations to time for the baseline (the faster one is kept).
        n_cycles, repeats: refill cycles per timed call, timed calls per program.
        stage_repeats: ``repeats`` of the per-part stage timing.
        n_s: refill stride of the default predictor.

    Returns:
        :class:`SpeedupReport`.
    """
    from ..precision import require_float64

    require_float64("speedup_breakdown")
    from jax.sharding import PartitionSpec as P

    from ..solve.distributed import DistributedRunner
    from ..parallel.exchange import AXIS
    from ..parallel.partition import Partition, partition as make_partition
    from ..fem.stepper import SolverState, build_system, initial_state
    from ..solve.syncavoid import SurrogatePredictor, PredictedPhase, shared_dof_layout

    if not syncs or any(m not in ("psum", "ppermute") for m in syncs):
        raise ProblemError(f"syncs must name 'psum' and/or 'ppermute', got {syncs!r}")
    for name, value in (("n_cycles", n_cycles), ("repeats", repeats)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ProblemError(f"{name} must be a positive integer, got {value!r}")
    part_info = partitions if isinstance(partitions, Partition) else make_partition(
        problem.mesh, partitions, seed=seed)
    if part_info.n_parts < 2:
        raise ProblemError("the synchronization-avoiding solver needs at least 2 parts")
    if predictor is None:
        predictor = SurrogatePredictor.initialized(part_info, n_s, seed=seed)
    n_s, n_p, n_f = predictor.n_s, predictor.n_past, predictor.n_future
    cycle_steps, history = n_s * n_f, n_s * n_p
    n_steps = n_cycles * cycle_steps
    dt = float(problem.dt if dt is None else dt)
    system = build_system(problem, dt, mode)
    state = initial_state(problem, system)
    d0, dm1 = np.asarray(state.displacement), np.asarray(state.previous)
    n_dof, _ = shared_dof_layout(part_info)

    runners = {m: DistributedRunner(problem, system, part_info, save_every=n_steps, mode=mode,
                                    devices=devices, sync=m) for m in syncs}
    runner = runners[syncs[0]]
    dist_state = runner.from_global(SolverState(d0, dm1, 0))
    online = PredictedPhase(runner, predictor, save_every=cycle_steps)
    buffer = runner.put(np.zeros((part_info.n_parts, history, n_dof)))
    first = online.step_counter(0)
    calls = {f"sync:{m}": (r.program(1, save_every=n_steps), (r.parts, dist_state))
             for m, r in runners.items()}
    calls["nosync"] = (runner.program(1, save_every=n_steps, synchronize=False), (runner.parts, dist_state))
    calls["avoid"] = (online.prepare(dist_state, buffer, n_cycles, cycle_steps),
                      (runner.parts, online.predictor, dist_state, buffer, first))
    calls["call"] = (_distributed_program(runner, n_steps, synchronize=None), (runner.parts, dist_state))
    predict_all = jax.jit(jax.shard_map(jax.vmap(lambda pred, buf: pred.predict(buf, 0)),
                                        mesh=runner.device_mesh, in_specs=(P(AXIS), P(AXIS)),
                                        out_specs=P(AXIS), check_vma=False))
    calls["predict"] = (predict_all, (online.predictor, buffer))
    whole = _per_step(_best_times(calls, repeats), n_steps)
    t_prediction_spmd = whole.pop("predict") * n_steps
    t_step_sync = {m: whole[f"sync:{m}"] for m in syncs}
    best = min(t_step_sync, key=t_step_sync.get)

    # each part's batched refill prediction alone on one device
    device = runner.devices[0]
    predict = jax.jit(lambda pred, buf: pred.predict(buf, 0))
    t_prediction = []
    for p in range(part_info.n_parts):
        own = jax.device_put(jax.tree_util.tree_map(lambda x: np.asarray(x)[p], predictor), device)
        buf = jax.device_put(np.zeros((history, n_dof)), device)
        t = _best_times({"predict": (predict, (own, buf)),
                         "call": (jax.jit(lambda b: b + 0.0), (buf,))}, max(repeats, 20))
        t_prediction.append(max(t["predict"] - t["call"], 0.0))

    synchronized = timing_breakdown(problem, part_info, mode=mode, repeats=stage_repeats, dt=dt,
                                    devices=devices, sync=best)
    # every part's prediction runs at the same time in the program: each pays the SPMD time
    t_d = t_prediction_spmd / cycle_steps
    rows = tuple(dataclasses.replace(r, t_s=0.0, t_d=t_d, t_t=r.t_local + t_d)
                 for r in synchronized.rows)
    avoiding = dataclasses.replace(synchronized, rows=rows, t_step=whole["avoid"],
                                   t_step_nosync=whole["nosync"])
    arch = getattr(predictor, "arch", None)
    return SpeedupReport(synchronized=synchronized, avoiding=avoiding, sync=best,
                         t_step_sync=t_step_sync, t_step_nosync=whole["nosync"],
                         t_step_avoiding=whole["avoid"], t_prediction=tuple(t_prediction),
                         t_prediction_spmd=t_prediction_spmd,
                         n_s=int(n_s), n_past=int(n_p), n_future=int(n_f),
                         architecture=arch.to_dict() if arch is not None else {},
                         n_steps=n_steps, repeats=repeats)
