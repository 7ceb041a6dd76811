"""The one prepared accelerator check: every measured row of jaxsync on one GPU, in one run.

``python benchmarks/bench_gpu.py`` on a machine with a GPU (``--platform cpu --quick`` is
its dry run on the CPU, run by the tests; on a machine without the platform it says so
and exits with status 3). Float64 unless a row says otherwise. Sections, in order (each
one's rows are written to ``--out`` as soon as the section finishes, and after every row,
atomically, so that a run cut short keeps what it measured; ``--sections`` runs some):

1. ``copy``: the device's copy bandwidth (read + write bytes per second of ``x <- s x``
   over a 1 GiB float64 array, many passes in one call): the 100 % of the other rows.
2. ``stepper``: the linear explicit step (:func:`jaxsync.fem.build_system` and
   :func:`~jaxsync.fem.advance`, the node-blocked ELL mat-vec in ``lax.scan``) on
   cantilever beams of 14 823, 51 207, 265 923, 867 783 and 1 114 047 dofs, float64 blocks
   and float32 blocks (``Preassembled(blocks_dtype="float32")``): us per step, GB/s of the
   compulsory traffic (the operator's arrays and the state vectors once per step) and %
   of the copy bandwidth. On the smallest and the largest beam also the same steps as a
   ``lax.scan`` of the package's own :func:`~jaxsync.fem.step` with ``unroll=k``,
   k = 1, 4, 8 (``advance`` itself runs ``STEP_UNROLL`` = 2 steps per iteration), each
   checked to give the displacements of ``advance`` to round-off: the per-step floor of
   small meshes and its remedy measured in the same run.
3. ``hyperelastic``: the total-Lagrangian internal force
   (:meth:`jaxsync.fem.forces.HyperelasticForce.matvec` of
   :class:`~jaxsync.fem.forces.TotalLagrangian`), P1 neo-Hookean on beams of
   86 400 and 480 000 tetrahedra and P1 HGO (two helical fibre families) on 86 400, at a
   deformed state: elements per second against the bandwidth bound of the bytes an
   element moves (node ids, shape data, the gather of 4 x 3 displacements and the
   scatter of 12 forces: :func:`jaxsync.perf.roofline.hyperelastic_element_cost`, 312
   bytes for neo-Hookean P1) at the measured copy bandwidth.
4. ``vessel``: the paper-size coronary tree (:func:`jaxsync.coronary_mesh` at the demo's
   ``"paper"`` target, 335 000 tetrahedra, about 273 576 dofs; the demo's mass scaling to
   2.5 times the CFL step): the synchronized step on one device, and as 11 parts sharing
   the device (the distributed SPMD program, :class:`jaxsync.solve.executors.DistributedRunner`)
   with the psum of the interface forces and without any exchange; the 11-part run is
   checked against the one-device run.
5. ``training``: LSTM training (:func:`jaxsync.surrogate.train_replicas`, seconds per
   epoch, compilation apart) at the cantilever demo's size (2 replicas, n_H 50, n_B 10,
   n_s 150, 1e5 steps), at the paper's n_H 100 (n_B 5, n_s 80) and at the paper-size
   vessel's (11 replicas of its parts' shared dofs, n_H 32, n_B 10, n_s 1000, 1e6 steps);
   the histories are synthetic (speed does not depend on the values).
6. ``ensemble``: 512 coarse cantilevers (312 dofs) under different loads advanced as one
   batched program (the program of :func:`jaxsync.ensemble`: ``vmap`` of ``advance`` over
   the runs' load vectors and states): us per batched step and run-steps per second,
   checked against :func:`jaxsync.ensemble` on its first members; the same 512 members each
   with its own Young's modulus (0.8-1.2 times the base's) and load, set up in one
   vectorised pass (``jaxsync.ensemble(problem, n, members=jaxsync.Members(...))``: host
   setup per member, its batched step, its stiffest member against that member's own
   :func:`jaxsync.simulate`); and the host setup time
   per member of :func:`jaxsync.ensemble` (its wall time less compilation and run, over
   16 members).

Timing. Every timed call runs long enough to measure the step rather than the launch: at
least ``--min-call-ms`` (50 ms on an accelerator), the steps per call chosen from an
estimate and raised (one recompilation) when a call came out shorter; each call is
timed in round-robin rounds with the other variants of its row after an untimed first
call, the best round kept (:func:`jaxsync.perf.measure.sample_times`). ``steps_per_call``
and ``call_ms`` are in every row.

Host work. The meshes, their assembly (scikit-fem), the initial states and the vessel's
gmsh mesh are prepared on the host in ``--workers`` background processes (CPU JAX; one
per input, started at once) while the device measures; a row waits for its inputs
(``wait_s``). Host CPU time, measured on a busy 2-core machine: the 1.1M-dof beam about
105 s (assembly 85 s), the 868k-dof beam 80 s, the 266k-dof beam 25 s, the vessel 60 s
(gmsh 24 s): in parallel they are ready about 110 s after the start, while the device is
on the smaller beams. The beams step at half the CFL step (no eigenvalue solve on the
host; the speed of a step does not depend on dt).

Budget. Each section has a time budget (``--budget SECTION=SECONDS``; defaults copy 20,
stepper 200, hyperelastic 45, vessel 90, training 120, ensemble 45) and the run a limit
(``--time-limit``, 420 s): a row does not start once its section's budget or the limit is
spent (it is listed under ``skipped``); no row takes a minute. Estimated wall time of the
full run on one H200, compilation included, from the sizes and the rates measured there
before (step 12 us at 15k dofs, 229 us at 868k, 115 us on the vessel; neo-Hookean 0.65e9
elements/s; 4.7e7 ensemble run-steps/s) and XLA:GPU compilation of 1-2 s per stepper
program, 20-30 s per training loop:

    start-up (CUDA, imports, workers)    10 s
    copy                                  5 s
    stepper                             120 s  (16 programs; waits for the 1.1M-dof beam)
    hyperelastic                         15 s
    vessel                               50 s  (the 11-part layout on the host: 25 s)
    training                             90 s  (3 compilations, 20 epochs each)
    ensemble                             25 s  (jaxsync.ensemble's setup of 16 runs: 10 s)
    total                              ~315 s  (5.3 minutes; the limit keeps it under 8)

Run it on the GPU machine as (from the repository root, the package installed)::

    python benchmarks/bench_gpu.py --out benchmarks/results/gpu.json

Writes ``--out`` (default ``benchmarks/results/gpu.json``) and prints a table per section.
Nothing in it is GPU-specific code: the point is that the same programs run there.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import os
import platform
import sys
import time
import traceback

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the workers import this module

SECTIONS = ("copy", "stepper", "hyperelastic", "vessel", "training", "ensemble")

BUDGETS_S = {"copy": 20, "stepper": 200, "hyperelastic": 45, "vessel": 90, "training": 120, "ensemble": 45}
"""Seconds each section may start rows in (the full run; ``--quick`` has no budgets)."""

TIME_LIMIT_S = 420.0
"""No row starts after this (the longest rows take well under a minute: the run ends within 8)."""

FLOOR_TARGET_US = 4.0
BANDWIDTH_TARGET_PERCENT = 80.0

UNROLLS = (1, 4, 8)

MASS_SCALING_BETA = 2.5  # the demo's vessel step over its CFL step (jaxsync.app.demo)

DT_FACTOR = 0.5
"""The beams step at half the paper's CFL step (:func:`jaxsync.cfl_dt`): stable, without
the exact bound's eigenvalue solve on the host (minutes at 1M dofs); the speed of a step
does not depend on dt."""


@dataclasses.dataclass(frozen=True)
class Sizes:
    """Every size of a run (:data:`FULL` or :data:`QUICK`)."""

    beams: tuple          # stepper beams (box_beam divisions)
    unroll_beams: tuple   # beams with the unrolled variants
    hyper_beams: tuple    # (divisions, laws)
    vessel_target: int    # tetrahedra of the coronary tree
    n_parts: int
    training: tuple       # (name, replicas from, n_hidden, n_layers, batch_size, n_s, n_steps, n_past, n_future)
    epochs: int
    epochs_per_call: int
    members: int          # ensemble runs, batched
    setup_members: int    # runs of the jaxsync.ensemble call (host setup per member)
    copy_bytes: int
    min_call_s: float
    repeats: int
    step_floor_s: float   # the per-step estimate's floor (steps per call from it)


FULL = Sizes(
    beams=((60, 8, 8), (100, 12, 12), (200, 20, 20), (300, 30, 30), (340, 32, 32)),
    unroll_beams=((60, 8, 8), (340, 32, 32)),
    hyper_beams=(((100, 12, 12), ("NeoHookean", "HolzapfelGasserOgden")), ((200, 20, 20), ("NeoHookean",))),
    vessel_target=335_000, n_parts=11,
    training=(("demo", "cantilever", 50, 2, 10, 150, 100_000, 20, 20),
              ("paper-nH100", "cantilever", 100, 2, 5, 80, 100_000, 20, 20),
              ("vessel-paper", "vessel", 32, 2, 10, 1000, 1_000_000, 20, 20)),
    epochs=20, epochs_per_call=10, members=512, setup_members=16,
    copy_bytes=1 << 30, min_call_s=0.05, repeats=5, step_floor_s=4e-6)

QUICK = Sizes(
    beams=((25, 1, 1),),
    unroll_beams=((25, 1, 1),),
    hyper_beams=(((25, 1, 1), ("NeoHookean", "HolzapfelGasserOgden")),),
    vessel_target=3_500, n_parts=3,
    # the first two alike: the package's training runner is compiled once for both
    training=(("demo", "cantilever", 4, 1, 4, 10, 600, 3, 3),
              ("paper-nH100", "cantilever", 4, 1, 4, 10, 600, 3, 3),
              ("vessel-paper", "vessel", 4, 1, 4, 10, 600, 3, 3)),
    epochs=2, epochs_per_call=1, members=8, setup_members=1,
    copy_bytes=8 << 20, min_call_s=0.0005, repeats=2, step_floor_s=2e-6)

ROW_KEYS = {
    "copy": ("bytes", "passes_per_call", "call_ms", "GB_per_s"),
    "stepper": ("case", "dofs", "blocks", "variant", "unroll", "us_per_step", "us_per_step_median", "bytes_per_step",
                "GB_per_s", "percent_of_copy", "steps_per_call", "call_ms"),
    "hyperelastic": ("case", "law", "elements", "us_per_force", "elements_per_s", "bytes_per_element",
                     "GB_per_s", "bound_elements_per_s", "percent_of_bound", "forces_per_call", "call_ms"),
    "vessel": ("case", "dofs", "program", "n_parts", "us_per_step", "steps_per_call", "call_ms"),
    "training": ("case", "replicas", "n_hidden", "batch_size", "n_dof_max", "steps_per_epoch", "seconds_per_epoch",
                 "ms_per_gradient_step", "compile_s", "epochs_per_call"),
    "ensemble": ("members", "dofs", "us_per_batched_step", "run_steps_per_s", "steps_per_call", "call_ms",
                 "setup_s_per_member", "setup_members", "max_rel_diff_vs_ensemble"),
}
"""The keys of every row of a section (what the tests check)."""


def beam_name(divisions) -> str:
    return "beam-" + "x".join(str(d) for d in divisions)


# ----------------------------------------------------------------------------------------
# Host preparation, in background processes (CPU JAX): module-level functions, pickled.

def _worker_init():
    """A worker computes on the host's CPU: it must not take the accelerator."""
    os.environ["JAX_PLATFORMS"] = "cpu"
    os.environ["CUDA_VISIBLE_DEVICES"] = ""


def _numpy(tree):
    import jax
    import numpy as np

    return jax.tree_util.tree_map(np.asarray, tree)


def deformed_state(points, seed=0):
    """(n_nodes, 3) a homogeneous stretch (+2 %, -1 %, +1 %) plus a random field of 1e-4 of
    the body's size [cm] (as benchmarks/bench_hyperelastic.py)."""
    import numpy as np

    x = np.asarray(points) - np.asarray(points).mean(axis=0)
    size = float(np.ptp(x, axis=0).max())
    noise = np.random.default_rng(seed).standard_normal(x.shape)
    return x * np.array([0.02, -0.01, 0.01]) + 1e-4 * size * noise


def hyperelastic_law(name, linear, mesh):
    """The law ``name`` that linearises to ``linear`` (HGO: its ground matrix, two helical
    fibre families at +/- 40 degrees around the beam's axis)."""
    import jaxsync

    if name == "HolzapfelGasserOgden":
        centres = mesh.points[mesh.tets].mean(axis=1)
        fibres = jaxsync.helical_fibres(centres, axis=(1.0, 0.0, 0.0), angle=40.0, origin=centres.mean(axis=0))
        return jaxsync.HolzapfelGasserOgden(mu=linear.mu, k1=linear.mu, k2=0.8393,
                                            kappa_bulk=linear.lam + 2.0 * linear.mu / 3.0,
                                            rho=linear.rho, fibres=fibres)
    return getattr(jaxsync, name)(linear.E, linear.nu, linear.rho)


def prepare_beam(divisions, stepper: bool, laws: tuple) -> dict:
    """A cantilever beam's systems (float64 and float32 blocks) and initial state, and its
    hyperelastic operators, as numpy pytrees."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxsync
    from jaxsync.fem import build_system, initial_state
    from jaxsync.fem.forces import Preassembled, TotalLagrangian

    start = time.perf_counter()
    problem = jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, tuple(divisions)))
    dt = DT_FACTOR * float(jaxsync.cfl_dt(problem))
    out = {"divisions": tuple(divisions), "dofs": problem.n_dofs, "nodes": problem.n_nodes,
           "elements": problem.mesh.n_elements, "dt": dt}
    if stepper:
        systems = {blocks: build_system(problem, dt, Preassembled(blocks_dtype=blocks))
                   for blocks in ("float64", "float32")}
        # compiled as one program (op by op, its first call compiles some 80 small programs)
        out["state"] = _numpy(jax.jit(functools.partial(initial_state, problem))(systems["float64"]))
        out["systems"] = {k: _numpy(v) for k, v in systems.items()}
    if laws:
        out["u"] = deformed_state(problem.mesh.points)
        out["operators"] = {law: _numpy(TotalLagrangian().operator(
            problem.replace(material=hyperelastic_law(law, problem.material, problem.mesh)))) for law in laws}
    out["host_s"] = time.perf_counter() - start
    return out


def vessel_mesh(target: int, path: str | None):
    """The coronary tree of ``target`` tetrahedra: read from ``path`` (npz: ``points``,
    ``tets`` and ``facet_<name>`` arrays) when that file exists, else generated with gmsh
    (and written there, atomically, when a path is given)."""
    import numpy as np

    import jaxsync

    if path and os.path.exists(path):
        with np.load(path) as z:
            facets = {k[len("facet_"):]: z[k] for k in z.files if k.startswith("facet_")}
            return jaxsync.Mesh(points=z["points"], tets=z["tets"], facet_sets=facets), "read " + path
    mesh = jaxsync.coronary_mesh(target_elements=target)
    if path:
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        tmp = f"{path}.partial-{os.getpid()}.npz"
        np.savez(tmp, points=mesh.points, tets=mesh.tets, **{f"facet_{k}": v for k, v in mesh.facet_sets.items()})
        os.replace(tmp, path)
    return mesh, "gmsh"


def prepare_vessel(target: int, n_parts: int, path: str | None = None) -> dict:
    """The coronary tree of ``target`` tetrahedra (:func:`vessel_mesh`), mass-scaled as the
    demo's vessel: the problem, its system and initial state (numpy), the partition into
    ``n_parts``."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jaxsync
    from jaxsync.fem import build_system, initial_state

    start = time.perf_counter()
    mesh, source = vessel_mesh(target, path)
    mesh_s = time.perf_counter() - start
    problem = jaxsync.coronary(mesh)
    # the demo's vessel_problem scales to beta times problem.dt; the CFL step here, without
    # the exact bound's eigenvalue solve (it is the CFL step on the coronary tree)
    dt = MASS_SCALING_BETA * float(jaxsync.cfl_dt(problem))
    scaled, added = jaxsync.mass_scaling(problem, dt_target=dt, warn_above_percent=None)
    system = build_system(scaled, dt)
    state = _numpy(jax.jit(functools.partial(initial_state, scaled))(system))
    part = jaxsync.partition(scaled.mesh, n_parts)
    return {"problem": scaled, "system": _numpy(system), "state": state, "partition": part, "dt": dt,
            "added_mass_percent": float(added), "dofs": scaled.n_dofs, "elements": mesh.n_elements,
            "shared_dofs": [3 * p.n_shared for p in part.parts], "mesh_s": mesh_s, "mesh_source": source,
            "host_s": time.perf_counter() - start}


class Prepared:
    """The host inputs, computed in background processes (``workers`` > 0) or here when
    first asked for (0)."""

    def __init__(self, workers: int):
        self.workers = workers
        self.pool = None
        self.jobs = {}
        if workers > 0:
            import concurrent.futures
            import multiprocessing

            self.pool = concurrent.futures.ProcessPoolExecutor(
                max_workers=workers, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init)

    def submit(self, key, fn, *args):
        self.jobs[key] = self.pool.submit(fn, *args) if self.pool is not None else (fn, args)

    def get(self, key):
        """(result, seconds waited for it)."""
        start = time.perf_counter()
        job = self.jobs[key]
        if isinstance(job, tuple):  # here, through pickle as from a worker
            import pickle

            fn, args = job
            try:
                self.jobs[key] = job = _Done(pickle.loads(pickle.dumps(fn(*args))))
            except Exception as exc:  # raised again to whoever asks
                self.jobs[key] = job = _Done(None, exc)
        return job.result(), time.perf_counter() - start

    def close(self):
        """Stop the workers: inputs still being prepared (of rows skipped) are not waited for."""
        if self.pool is None:
            return
        processes = list(getattr(self.pool, "_processes", {}).values())  # the pool's own, started here
        busy = any(not job.done() for job in self.jobs.values() if hasattr(job, "done"))
        self.pool.shutdown(wait=False, cancel_futures=True)
        if busy:
            for process in processes:
                if process.is_alive():
                    process.terminate()


class _Done:
    """A job done here: its value or its exception (as a future's ``result``)."""

    def __init__(self, value, error=None):
        self.value, self.error = value, error

    def result(self):
        if self.error is not None:
            raise self.error
        return self.value


# ----------------------------------------------------------------------------------------
# Timing.

class Run:
    """The run's state: the result dict, the clock, the budgets, the output file."""

    def __init__(self, args, sizes: Sizes, result: dict):
        self.args, self.sizes, self.result = args, sizes, result
        self.start = time.perf_counter()
        self.section = None
        self.section_start = None
        self.budgets = dict(BUDGETS_S)
        for item in args.budget:
            name, _, seconds = item.partition("=")
            if name not in SECTIONS:
                raise SystemExit(f"--budget {item}: unknown section {name!r}; choose from {', '.join(SECTIONS)}")
            self.budgets[name] = float(seconds)

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def begin(self, name):
        self.section, self.section_start, self.section_cpu = name, time.perf_counter(), time.process_time()
        self.result["sections"][name] = {"rows": [], "skipped": [], "errors": [], "budget_s": self.budget(name)}

    def budget(self, name):
        return None if self.args.quick else self.budgets[name]

    def may_start(self, what) -> bool:
        """Whether a row ``what`` may start (else it is listed as skipped)."""
        if self.args.quick:
            return True
        spent = time.perf_counter() - self.section_start
        if spent > self.budgets[self.section] or self.elapsed() > self.args.time_limit:
            self.result["sections"][self.section]["skipped"].append(
                f"{what}: section budget {self.budgets[self.section]:.0f} s or run limit {self.args.time_limit:.0f} s "
                f"spent ({spent:.0f} s in the section, {self.elapsed():.0f} s in all)")
            return False
        return True

    def add(self, rows):
        self.result["sections"][self.section]["rows"].extend(rows)
        self.write()

    def error(self, what, exc):
        text = f"{what}: {type(exc).__name__}: {exc}"
        print(f"  ERROR {text}", flush=True)
        traceback.print_exc()
        self.result["sections"][self.section]["errors"].append(text)
        self.write()

    def end(self):
        section = self.result["sections"][self.section]
        section["seconds"] = time.perf_counter() - self.section_start
        section["cpu_s"] = time.process_time() - self.section_cpu  # this process's, all its threads
        self.result["elapsed_s"] = self.elapsed()
        self.write()

    def write(self):
        from jaxsync.io import atomic_json

        self.result["elapsed_s"] = self.elapsed()
        atomic_json(self.args.out, self.result)


def timed(make_calls, units, run: Run, multiple: int = 8):
    """Time the calls of ``make_calls(n)`` (``{name: (fn, args)}``, each doing ``n`` units
    of work) round-robin, the best of ``repeats`` rounds, with ``n`` from the estimate
    ``units`` (enough for 1.5 x the minimum call) raised once when the shortest best call
    came out below ``--min-call-ms`` (not with ``--quick``). Returns (n, {name: best s},
    {name: median s})."""
    import numpy as np

    from jaxsync.perf.measure import sample_times

    sizes = run.sizes
    min_call = run.args.min_call_ms / 1e3
    n = steps_for(units, multiple)
    attempts = 1 if run.args.quick else 2  # the dry run: tiny calls, no recompilation
    for attempt in range(attempts):
        samples = sample_times(make_calls(n), sizes.repeats)
        best = {k: float(v.min()) for k, v in samples.items()}
        shortest = min(best.values())
        if shortest >= min_call or attempt == attempts - 1:
            break
        n = int(math.ceil(n * 1.5 * min_call / max(shortest, 1e-9) / multiple)) * multiple
    return n, best, {k: float(np.median(v)) for k, v in samples.items()}


def steps_for(units: float, multiple: int = 8) -> int:
    """``units`` rounded up to a multiple of ``multiple`` (the first count :func:`timed` tries)."""
    return max(multiple, int(math.ceil(units / multiple)) * multiple)


def units_for(seconds_per_unit: float, run: Run) -> float:
    """Units of work per call for 1.5 x the minimum call at the estimated rate."""
    return 1.5 * (run.args.min_call_ms / 1e3) / max(seconds_per_unit, 1e-12)


def operator_bytes(tree) -> int:
    """Bytes of a pytree's arrays (every leaf, as stored)."""
    import jax
    import numpy as np

    return int(sum(np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(tree)))


def vector_bytes(n_nodes) -> int:
    """Bytes of a step's state vectors: d, prev, new, mass, load, fixed values; the mask
    (as benchmarks/bench_stepper.py counts them)."""
    return n_nodes * 3 * 8 * 6 + n_nodes * 3


def print_table(title, rows, columns):
    """``columns``: (key, header, format) triples."""
    print(f"\n{title}")
    if not rows:
        print("  (no rows)")
        return
    cells = [[header for _, header, _ in columns]]
    for r in rows:
        cells.append([("" if r.get(key) is None else format(r[key], fmt)) for key, _, fmt in columns])
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    for row in cells:
        print("  " + "  ".join(c.rjust(w) for c, w in zip(row, widths)))
    sys.stdout.flush()


def max_rel_diff(a, b) -> float:
    import numpy as np

    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    scale = float(np.abs(a).max())
    return float(np.abs(a - b).max() / scale) if scale > 0 else float(np.abs(a - b).max())


# ----------------------------------------------------------------------------------------
# Sections.

def section_copy(run: Run, device):
    import jax
    import jax.numpy as jnp

    @functools.partial(jax.jit, static_argnums=2)
    def passes(x, scale, n):
        return jax.lax.fori_loop(0, n, lambda i, y: y * scale, x)

    n_bytes = run.sizes.copy_bytes
    x = jax.device_put(jnp.ones(n_bytes // 8), device)
    scale = jax.device_put(jnp.ones(()), device)
    rate = 1e12 if device.platform != "cpu" else 5e9  # a guess, for the passes per call
    n, best, median = timed(lambda k: {"copy": (passes, (x, scale, k))}, units_for(2 * n_bytes / rate, run), run,
                            multiple=1)
    t = best["copy"]
    row = {"bytes": n_bytes, "passes_per_call": n, "call_ms": 1e3 * t, "GB_per_s": 2 * n_bytes * n / t / 1e9,
           "GB_per_s_median": 2 * n_bytes * n / median["copy"] / 1e9}
    run.result["copy_GB_per_s"] = row["GB_per_s"]
    run.add([row])
    print_table("copy bandwidth (read + write)", [row], [("bytes", "bytes", ".3g"), ("passes_per_call", "passes", "d"),
                                                         ("call_ms", "call ms", ".1f"), ("GB_per_s", "GB/s", ".1f")])


def _copy_rate(run: Run, device) -> float:
    """The measured copy bandwidth [B/s], or a guess for the platform."""
    measured = run.result.get("copy_GB_per_s")
    if measured:
        return 1e9 * measured
    return 3e12 if device.platform != "cpu" else 1e10


def section_stepper(run: Run, device, prepared: Prepared):
    import jax

    from jaxsync.fem import STEP_UNROLL, advance, step

    advance_jit = jax.jit(advance, static_argnums=(2, 3))

    def scan_steps(system, state, n_steps, unroll):
        """``n_steps`` of the package's step in a lax.scan of ``unroll`` steps per iteration."""
        def body(s, _):
            return step(system, s), None

        return jax.lax.scan(body, state, None, length=n_steps, unroll=unroll)[0]

    scan_jit = jax.jit(scan_steps, static_argnums=(2, 3))
    copy_rate = _copy_rate(run, device)
    columns = [("case", "case", "s"), ("dofs", "dofs", "d"), ("blocks", "blocks", "s"), ("variant", "variant", "s"),
               ("us_per_step", "us/step", ".2f"), ("us_per_step_median", "median", ".2f"),
               ("bytes_per_step", "bytes/step", ".3g"), ("GB_per_s", "GB/s", ".1f"),
               ("percent_of_copy", "% copy", ".1f"), ("steps_per_call", "steps/call", "d"),
               ("call_ms", "call ms", ".1f"), ("max_rel_diff_vs_advance", "diff vs advance", ".1e")]
    for divisions in run.sizes.beams:
        name = beam_name(divisions)
        if not run.may_start(name):
            continue
        try:
            beam, waited = prepared.get(("beam", tuple(divisions)))
            systems = {k: jax.device_put(v, device) for k, v in beam["systems"].items()}
            state = jax.device_put(beam["state"], device)
            nbytes = {k: operator_bytes(s.stiffness) + vector_bytes(beam["nodes"]) for k, s in systems.items()}
            calls = {}

            def make_calls(n):
                calls = {f"advance-{k}": (advance_jit, (s, state, 1, n)) for k, s in systems.items()}
                if tuple(divisions) in run.sizes.unroll_beams:
                    calls.update({f"unroll{k}": (scan_jit, (systems["float64"], state, n, k)) for k in UNROLLS})
                return calls

            estimate = max(run.sizes.step_floor_s, nbytes["float64"] / (0.8 * copy_rate))  # optimistic: long calls
            n, best, median = timed(make_calls, units_for(estimate, run), run)
            calls = make_calls(n)
            reference = jax.device_get(calls["advance-float64"][0](*calls["advance-float64"][1])[0].displacement)
            rows = []
            for key, seconds in best.items():
                blocks = key.split("-")[1] if key.startswith("advance") else "float64"
                unroll = STEP_UNROLL if key.startswith("advance") else int(key[len("unroll"):])
                t = seconds / n
                row = {"case": name, "dofs": beam["dofs"], "nodes": beam["nodes"], "elements": beam["elements"],
                       "blocks": blocks, "variant": "advance" if key.startswith("advance") else f"scan-unroll-{unroll}",
                       "unroll": unroll, "us_per_step": 1e6 * t, "us_per_step_median": 1e6 * median[key] / n,
                       "bytes_per_step": nbytes[blocks], "GB_per_s": nbytes[blocks] / t / 1e9,
                       "percent_of_copy": 100.0 * nbytes[blocks] / t / copy_rate, "steps_per_call": n,
                       "call_ms": 1e3 * seconds, "host_s": beam["host_s"], "wait_s": waited}
                if not key.startswith("advance"):
                    fn, fargs = calls[key]
                    row["max_rel_diff_vs_advance"] = max_rel_diff(reference, jax.device_get(fn(*fargs).displacement))
                rows.append(row)
            run.add(rows)
            print(f"{name}: {beam['dofs']} dofs, {n} steps per call (host {beam['host_s']:.0f} s, waited "
                  f"{waited:.0f} s; {run.elapsed():.0f} s)", flush=True)
        except Exception as exc:  # a prepared run keeps going: the row's error is recorded
            run.error(name, exc)
    print_table("linear step (build_system / advance)", run.result["sections"]["stepper"]["rows"], columns)


def section_hyperelastic(run: Run, device, prepared: Prepared):
    import jax
    import numpy as np

    from jaxsync.perf.roofline import hyperelastic_element_cost

    @functools.partial(jax.jit, static_argnums=3)
    def forces(op, u, scale, reps):
        """``reps`` dependent products x <- u + scale f(x) in one call (scale = 0 at run
        time, which XLA cannot fold away): the time of a product without a call's cost."""
        return jax.lax.fori_loop(0, reps, lambda i, x: u + scale * op.matvec(x), u)

    copy_rate = _copy_rate(run, device)
    rows = []
    for divisions, laws in run.sizes.hyper_beams:
        name = beam_name(divisions)
        if not run.may_start(name):
            continue
        try:
            beam, waited = prepared.get(("beam", tuple(divisions)))
            u = jax.device_put(beam["u"], device)
            scale = jax.device_put(np.zeros(()), device)
            ops = {law: jax.device_put(beam["operators"][law], device) for law in laws}
            m, n_nodes = beam["elements"], beam["nodes"]
            moved = {}
            for law in laws:
                cost = hyperelastic_element_cost(law, 4, 1)
                moved[law] = cost["element_bytes"] + cost["gather_bytes"]  # what an element moves
            estimate = max(20 * run.sizes.step_floor_s, 5 * moved["NeoHookean"] * m / (0.5 * copy_rate))
            reps, best, median = timed(lambda k: {law: (forces, (ops[law], u, scale, k)) for law in laws},
                                       units_for(estimate, run), run, multiple=1)
            for law in laws:
                t = best[law] / reps
                cost = hyperelastic_element_cost(law, 4, 1)
                compulsory = cost["element_bytes"] + cost["node_bytes"] * n_nodes / m
                bound = copy_rate / moved[law]
                rows.append({"case": name, "law": law, "elements": m, "nodes": n_nodes, "us_per_force": 1e6 * t,
                             "us_per_force_median": 1e6 * median[law] / reps, "elements_per_s": m / t,
                             "bytes_per_element": moved[law], "compulsory_bytes_per_element": compulsory,
                             "GB_per_s": moved[law] * m / t / 1e9, "bound_elements_per_s": bound,
                             "percent_of_bound": 100.0 * (m / t) / bound, "forces_per_call": reps,
                             "call_ms": 1e3 * best[law], "wait_s": waited})
            run.add(rows[-len(laws):])
        except Exception as exc:
            run.error(name, exc)
    print_table("hyperelastic element kernel (TotalLagrangian force)", rows,
                [("case", "case", "s"), ("law", "law", "s"), ("elements", "elements", "d"),
                 ("us_per_force", "us/force", ".1f"), ("elements_per_s", "elem/s", ".3g"),
                 ("bytes_per_element", "B/elem", ".0f"), ("GB_per_s", "GB/s", ".1f"),
                 ("bound_elements_per_s", "bound elem/s", ".3g"), ("percent_of_bound", "% bound", ".1f"),
                 ("forces_per_call", "forces/call", "d"), ("call_ms", "call ms", ".1f")])


def section_vessel(run: Run, device, prepared: Prepared):
    import jax

    import jaxsync
    from jaxsync.fem import SolverState, advance
    from jaxsync.solve.executors import DistributedRunner

    name = f"vessel-{run.sizes.vessel_target}"
    if not run.may_start(name):
        return
    try:
        vessel, waited = prepared.get("vessel")
        system = jax.device_put(vessel["system"], device)
        state = jax.device_put(vessel["state"], device)
        advance_jit = jax.jit(advance, static_argnums=(2, 3))
        start = time.perf_counter()
        n_parts = run.sizes.n_parts
        runner = DistributedRunner(vessel["problem"], system, vessel["partition"], save_every=1,
                                   sync=jaxsync.Psum([device]))
        parts_state = runner.from_global(SolverState(
            vessel["state"].displacement, vessel["state"].previous, 0))
        layout_s = time.perf_counter() - start
        programs = {}

        def make_calls(n):
            for sync in (True, False):
                if (n, sync) not in programs:
                    programs[n, sync] = runner.program(1, save_every=n, synchronize=sync)
            return {"one device": (advance_jit, (system, state, 1, n)),
                    f"{n_parts} parts, psum": (programs[n, True], (runner.parts, parts_state)),
                    f"{n_parts} parts, no exchange": (programs[n, False], (runner.parts, parts_state))}

        nbytes = operator_bytes(system.stiffness) + vector_bytes(system.mass.shape[0])
        estimate = max(run.sizes.step_floor_s, nbytes / (0.5 * _copy_rate(run, device)))
        n, best, median = timed(make_calls, units_for(estimate, run), run)
        calls = make_calls(n)
        single = jax.device_get(calls["one device"][0](*calls["one device"][1])[0].displacement)
        fn, fargs = calls[f"{n_parts} parts, psum"]
        parts = runner.to_global(fn(*fargs)[0]).displacement
        rows = []
        for program, seconds in best.items():
            rows.append({"case": name, "dofs": vessel["dofs"], "elements": vessel["elements"], "program": program,
                         "n_parts": 1 if program == "one device" else n_parts, "us_per_step": 1e6 * seconds / n,
                         "us_per_step_median": 1e6 * median[program] / n, "steps_per_call": n,
                         "call_ms": 1e3 * seconds, "bytes_per_step": nbytes if program == "one device" else None})
        rows[1]["max_rel_diff_vs_one_device"] = max_rel_diff(single, parts)
        rows[1]["exchange_us_per_step"] = max(rows[1]["us_per_step"] - rows[2]["us_per_step"], 0.0)
        run.result["sections"]["vessel"].update(
            {"dt": vessel["dt"], "added_mass_percent": vessel["added_mass_percent"], "host_s": vessel["host_s"],
             "mesh_s": vessel["mesh_s"], "mesh_source": vessel["mesh_source"], "layout_s": layout_s, "wait_s": waited,
             "shared_dofs": vessel["shared_dofs"]})
        run.add(rows)
        print_table(f"vessel ({vessel['dofs']} dofs, {vessel['elements']} tets; host "
                    f"{vessel['host_s']:.0f} s, {n_parts}-part layout {layout_s:.0f} s)", rows,
                    [("program", "program", "s"), ("us_per_step", "us/step", ".2f"),
                     ("us_per_step_median", "median", ".2f"), ("steps_per_call", "steps/call", "d"),
                     ("call_ms", "call ms", ".1f"), ("exchange_us_per_step", "exchange us", ".2f"),
                     ("max_rel_diff_vs_one_device", "diff vs 1 device", ".1e")])
    except Exception as exc:
        run.error(name, exc)


def synthetic_history(n_samples: int, n_dof: int, seed: int):
    """(n_samples, n_dof) damped oscillations (as benchmarks/bench_training.py)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    t = np.arange(n_samples)[:, None] * 0.02
    w = 2 * np.pi * rng.uniform(0.4, 3.0, size=(1, n_dof))
    amp = rng.uniform(0.01, 0.08, size=(1, n_dof))
    return amp * (1.0 - np.exp(-0.25 * t) * np.cos(w * t))


def section_training(run: Run, device, prepared: Prepared):
    import jax

    import jaxsync
    from jaxsync.surrogate import LSTMArchitecture, TrainConfig, build_dataset, stack_replicas, train_replicas

    rows = []
    cantilever = None
    for name, source, n_hidden, n_layers, batch, n_s, n_steps, n_past, n_future in run.sizes.training:
        if not run.may_start(name):
            continue
        try:
            waited = 0.0
            if source == "vessel":
                vessel, waited = prepared.get("vessel")
                dofs = vessel["shared_dofs"]
            else:
                if cantilever is None:
                    part = jaxsync.partition(jaxsync.cantilever().mesh, 2)
                    cantilever = [3 * p.n_shared for p in part.parts]
                dofs = cantilever
            n_samples = n_steps // n_s  # the sampled history: what the windows are made of
            data = stack_replicas([build_dataset([synthetic_history(n_samples, d, seed=p)], 1, n_past, n_future,
                                                 train_fraction=0.5) for p, d in enumerate(dofs)])
            arch = LSTMArchitecture(n_dof=data.n_dof_max, n_hidden=n_hidden, n_layers=n_layers, n_past=n_past,
                                    n_future=n_future)
            config = TrainConfig(batch_size=batch, eta0=5e-4, gamma=0.9995, n_epochs=run.sizes.epochs,
                                 epochs_per_call=run.sizes.epochs_per_call, patience=None)
            with jax.default_device(device):
                result = train_replicas(data, arch, config, jax.random.key(0), progress=False, devices=1)
            rows.append({"case": name, "replicas": len(dofs), "n_hidden": n_hidden, "n_layers": n_layers,
                         "batch_size": batch, "n_s": n_s, "n_steps": n_steps, "n_dof_max": data.n_dof_max,
                         "dof_counts": list(dofs), "train_windows": int(data.x_train.shape[1]),
                         "steps_per_epoch": result.steps_per_epoch, "epochs": run.sizes.epochs,
                         "epochs_per_call": run.sizes.epochs_per_call,
                         "seconds_per_epoch": result.seconds_per_epoch,
                         "ms_per_gradient_step": 1e3 * result.seconds_per_epoch / max(result.steps_per_epoch, 1),
                         "call_ms": 1e3 * result.seconds_per_epoch * run.sizes.epochs_per_call,
                         "compile_s": result.compile_seconds, "wait_s": waited})
            run.add(rows[-1:])
        except Exception as exc:
            run.error(name, exc)
    print_table("LSTM training (train_replicas)", rows,
                [("case", "case", "s"), ("replicas", "replicas", "d"), ("n_hidden", "n_H", "d"),
                 ("batch_size", "n_B", "d"), ("n_dof_max", "dofs", "d"), ("steps_per_epoch", "steps/epoch", "d"),
                 ("seconds_per_epoch", "s/epoch", ".4f"), ("ms_per_gradient_step", "ms/step", ".3f"),
                 ("call_ms", "call ms", ".0f"), ("compile_s", "compile s", ".1f")])


def section_ensemble(run: Run, device):
    import dataclasses as dc

    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxsync
    from jaxsync.fem import ExplicitSystem, advance, build_system, initial_state

    name = f"ensemble-{run.sizes.members}"
    if not run.may_start(name):
        return
    try:
        members, setup_members = run.sizes.members, run.sizes.setup_members
        base = jaxsync.cantilever()
        dt = float(base.dt)
        forces = np.linspace(0.3, 0.7, members)  # f_z of every run [dyn/cm^3]
        problems = [jaxsync.cantilever(base.mesh, body_force=(0.0, 0.0, -f)) for f in forces[:setup_members]]
        reference = build_system(base, dt)
        # the runs differ in their load vectors only: f_z / 0.5 times the base's (linear in f_z)
        factors = jnp.asarray(forces / 0.5)
        loads = factors[:, None, None, None] * reference.load_vectors[None]
        axes = ExplicitSystem(**{f.name: None for f in dc.fields(ExplicitSystem)})
        axes = dc.replace(axes, load_vectors=0)

        def batched(system, states, n):
            return jax.vmap(lambda s, st: advance(s, st, 1, n)[0], in_axes=(axes, 0))(system, states)

        batched_jit = jax.jit(batched, static_argnums=2)
        rate = 0.5 * _copy_rate(run, device)
        units = units_for(max(run.sizes.step_floor_s, members * vector_bytes(base.n_nodes) / rate), run)
        n_check = steps_for(units)  # the steps timed first: the ensemble runs as many
        with jax.default_device(device):
            start = time.perf_counter()
            runs = jaxsync.ensemble(problems, n_check, dt=dt, save=n_check,
                                    executor=jaxsync.HostExecutor(progress=False, chunk_steps=n_check))
            wall = time.perf_counter() - start
            # the start is linear in the loads (rest, d(-1) = dt^2 / 2 a0 with M a0 = f(0)): the
            # base's, scaled (the comparison with jaxsync.ensemble below checks it)
            first = initial_state(base, reference)
            states = jax.tree_util.tree_map(
                lambda x: x[None] * factors.reshape((-1,) + (1,) * jnp.ndim(x)).astype(x.dtype)
                if jnp.issubdtype(x.dtype, jnp.floating) else jnp.broadcast_to(x, (members,) + jnp.shape(x)), first)
            system = jax.device_put(dc.replace(reference, load_vectors=loads), device)
            states = jax.device_put(states, device)
            n, best, median = timed(lambda k: {"batched": (batched_jit, (system, states, k))}, units, run)
            check = np.asarray(jax.device_get(batched_jit(system, states, n_check).displacement))
            # every member its own Young's modulus and load, set up in one vectorised pass
            moduli = base.material.E * np.linspace(0.8, 1.2, members)
            spread = jaxsync.Members(material={"E": moduli}, load_scale=np.asarray(factors))
            start = time.perf_counter()
            varied = jaxsync.ensemble(base, n_check, members=spread, dt=0.75 * dt, save=n_check,
                                      executor=jaxsync.HostExecutor(progress=False, chunk_steps=n_check))
            varied_wall = time.perf_counter() - start
            last = members - 1  # the stiffest member, against its own run
            alone = jaxsync.simulate(spread.problem(base, last), n_check, dt=0.75 * dt, save=n_check,
                                     executor=jaxsync.HostExecutor(progress=False))
            varied_diff = max_rel_diff(varied[last].displacement[-1], np.asarray(alone.displacement[-1]))
        stats = runs[0].stats
        run_s = stats.us_per_step * 1e-6 * n_check
        setup_s = max(wall - stats.compile_seconds - run_s, 0.0)
        v_stats = varied[0].stats
        varied_setup_s = max(varied_wall - v_stats.compile_seconds - v_stats.us_per_step * 1e-6 * n_check, 0.0)
        diff = max(max_rel_diff(traj.displacement[-1], check[r]) for r, traj in enumerate(runs))
        t = best["batched"] / n
        row = {"members": members, "dofs": base.n_dofs, "us_per_batched_step": 1e6 * t,
               "us_per_batched_step_median": 1e6 * median["batched"] / n, "run_steps_per_s": members / t,
               "steps_per_call": n, "call_ms": 1e3 * best["batched"],
               "setup_s_per_member": setup_s / setup_members, "setup_members": setup_members,
               "ensemble_wall_s": wall, "ensemble_compile_s": stats.compile_seconds,
               "ensemble_us_per_batched_step": stats.us_per_step, "ensemble_steps": n_check,
               "max_rel_diff_vs_ensemble": diff,
               "members_setup_s_per_member": varied_setup_s / members,
               "members_us_per_batched_step": v_stats.us_per_step,
               "members_compile_s": v_stats.compile_seconds, "members_max_rel_diff_vs_own_run": varied_diff}
        run.add([row])
        print_table(f"ensemble of {members} coarse cantilevers (batched advance)", [row],
                    [("members", "runs", "d"), ("dofs", "dofs", "d"), ("us_per_batched_step", "us/step", ".2f"),
                     ("run_steps_per_s", "run-steps/s", ".3g"), ("steps_per_call", "steps/call", "d"),
                     ("call_ms", "call ms", ".1f"), ("setup_s_per_member", "setup s/run", ".3f"),
                     ("max_rel_diff_vs_ensemble", "diff vs ensemble", ".1e"),
                     ("members_setup_s_per_member", "E varying: setup s/run", ".4f"),
                     ("members_us_per_batched_step", "us/step", ".1f"),
                     ("members_max_rel_diff_vs_own_run", "diff vs own run", ".1e")])
    except Exception as exc:
        run.error(name, exc)


# ----------------------------------------------------------------------------------------

def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--platform", default="gpu", help="JAX platform to check (default: gpu; cpu for a dry run)")
    parser.add_argument("--quick", action="store_true", help="every section at tiny sizes: the dry run")
    parser.add_argument("--sections", default=",".join(SECTIONS),
                        help=f"comma-separated sections to run, in the run's order (default: {','.join(SECTIONS)})")
    parser.add_argument("--budget", action="append", default=[], metavar="SECTION=SECONDS",
                        help="a section's time budget (rows are not started after it); defaults: "
                             + ", ".join(f"{k} {v:g}" for k, v in BUDGETS_S.items()))
    parser.add_argument("--time-limit", type=float, default=TIME_LIMIT_S,
                        help="seconds after which no row starts (default: %(default)s)")
    parser.add_argument("--min-call-ms", type=float, default=None,
                        help="shortest timed call [ms] (default: 50; --quick 2)")
    parser.add_argument("--workers", type=int, default=None,
                        help="background processes preparing the host inputs (default: one per input, at most "
                             "the cores less one; --quick 0: in this process, when first needed)")
    parser.add_argument("--vessel-mesh", default=None, metavar="NPZ",
                        help="the vessel's mesh (points, tets, facet_<name> arrays): read when the file exists, "
                             "else generated with gmsh and written there (default: generated, not kept)")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results",
                                                      "gpu.json"))
    args = parser.parse_args(argv)
    sections = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        parser.error(f"unknown sections {unknown}; choose from {', '.join(SECTIONS)}")
    sections = [s for s in SECTIONS if s in sections]
    sizes = QUICK if args.quick else FULL
    if args.min_call_ms is None:
        args.min_call_ms = 1e3 * sizes.min_call_s

    import jax

    jax.config.update("jax_enable_x64", True)
    try:
        devices = jax.devices(args.platform)
    except RuntimeError as exc:
        print(f"no {args.platform} devices here ({exc}); run on a machine with one, or pass --platform cpu "
              "for a dry run on the CPU")
        return 3
    from jaxsync.perf.measure import describe_devices

    device = devices[0]
    result = {"benchmark": "gpu", "platform": args.platform, "devices": describe_devices(devices),
              "device_kind": device.device_kind, "n_devices": len(devices), "jax": jax.__version__,
              "python": platform.python_version(), "host": platform.platform(), "host_cores": os.cpu_count(),
              "quick": bool(args.quick), "sections_run": sections, "min_call_ms": args.min_call_ms,
              "float64": True, "sections": {}}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    print(f"{result['devices']}, jax {jax.__version__}; sections {', '.join(sections)}", flush=True)

    # the host inputs, prepared in the background from the start
    jobs = []
    hyper = {tuple(d): laws for d, laws in sizes.hyper_beams} if "hyperelastic" in sections else {}
    stepper = {tuple(d) for d in sizes.beams} if "stepper" in sections else set()
    for divisions in [tuple(d) for d in sizes.beams] + [d for d in hyper if d not in stepper]:
        if divisions in stepper or divisions in hyper:
            jobs.append((("beam", divisions), prepare_beam, divisions, divisions in stepper, hyper.get(divisions, ())))
    if "vessel" in sections or "training" in sections:
        jobs.append(("vessel", prepare_vessel, sizes.vessel_target, sizes.n_parts, args.vessel_mesh))
    workers = args.workers
    if workers is None:
        workers = 0 if args.quick else max(1, min(len(jobs), (os.cpu_count() or 2) - 1))
    prepared = Prepared(workers if jobs else 0)
    for key, fn, *fargs in jobs:  # in the order the sections need them
        prepared.submit(key, fn, *fargs)
    result["workers"] = prepared.workers

    run = Run(args, sizes, result)
    try:
        with jax.default_device(device):
            for name in sections:
                run.begin(name)
                print(f"\n== {name} ({run.elapsed():.0f} s)", flush=True)
                try:
                    if name == "copy":
                        section_copy(run, device)
                    elif name == "stepper":
                        section_stepper(run, device, prepared)
                    elif name == "hyperelastic":
                        section_hyperelastic(run, device, prepared)
                    elif name == "vessel":
                        section_vessel(run, device, prepared)
                    elif name == "training":
                        section_training(run, device, prepared)
                    else:
                        section_ensemble(run, device)
                except Exception as exc:
                    run.error(name, exc)
                run.end()
    finally:
        prepared.close()
    run.result["summary"] = summary(run.result)
    run.write()
    print("\nsummary:")
    for key, value in run.result["summary"].items():
        print(f"  {key}: {value}")
    print(f"wrote {args.out} ({run.elapsed():.0f} s)")
    return 0


def summary(result) -> dict:
    """The numbers the accelerator work is steered by, against its targets (a per-step
    floor of at most 4 us on the smallest beam; at least 80 % of the copy bandwidth at 1M
    dofs or more)."""
    out = {"targets": {"floor_us_per_step": FLOOR_TARGET_US, "percent_of_copy_at_1M_dofs": BANDWIDTH_TARGET_PERCENT}}
    rows = result["sections"].get("stepper", {}).get("rows", [])
    steps = [r for r in rows if r["variant"] == "advance"]
    if steps:
        small, large = min(r["dofs"] for r in steps), max(r["dofs"] for r in steps)
        out["floor_us_per_step"] = {r["blocks"]: r["us_per_step"] for r in steps if r["dofs"] == small}
        out["floor_dofs"] = small
        out["floor_met"] = min(out["floor_us_per_step"].values()) <= FLOOR_TARGET_US
        out["largest_dofs"] = large
        out["largest_percent_of_copy"] = {r["blocks"]: r["percent_of_copy"] for r in steps if r["dofs"] == large}
        if large >= 1_000_000:
            out["bandwidth_met"] = max(out["largest_percent_of_copy"].values()) >= BANDWIDTH_TARGET_PERCENT
        out["unroll_us_per_step"] = {f"{r['dofs']} dofs, unroll {r['unroll']}": r["us_per_step"]
                                     for r in rows if r["variant"] != "advance"}
    if "copy_GB_per_s" in result:
        out["copy_GB_per_s"] = result["copy_GB_per_s"]
    return out


if __name__ == "__main__":
    sys.exit(main())
