"""Explicit stepper: microseconds per step, bytes moved and achieved bandwidth.

For the default coarse cantilever (312 dofs), beams of 14 823, 51 207, 92 928 and
265 923 dofs (structured: node degree 13-14 on average, 15 at most) and the generated
coronary tree (:func:`jaxsync.coronary_mesh`, the paper's vessel problem with its pulsatile
lumen pressure) at about 91k and 270k dofs (unstructured: mean degree 11.8-12.7, largest
25-26), and on quadratic tetrahedra (``element="P2"``) at about 98k dofs; ``--quick``
keeps the cantilever, the 15k- and 93k-dof beams and the 91k-dof vessel. Side by side in the same run:

- ``scipy-csr``: a SciPy CSR loop doing the same full update (K d, the loads with their
  time functions, damping, Dirichlet values);
- ``jax-1dev``: jaxsync's compiled stepper on one device with the default stiffness
  (``Preassembled()``: rows grouped by node degree, :class:`jaxsync.fem.GroupedEll`);
- ``jax-1dev-f32``: the same with the float32 blocks option
  (``Preassembled(blocks_dtype="float32")``);
- ``jax-1dev-ell``: the previous layout, one block ELL as wide as the largest degree
  (``Preassembled(layout="ell")``), kept for comparison;
- ``jax-2dev`` (and ``jax-2dev-f32``): the problem split into 2 parts over 2 (emulated
  CPU) devices with ``shard_map`` and a psum of the interface forces: how jaxsync uses
  both cores;
- ``jax-einsum`` and ``jax-bcoo`` (beams only, not with ``--quick``): alternative layouts
  kept for the record (the einsum over (n, w, 3, 3) blocks that XLA lowers to a batched
  dot, and ``jax.experimental.sparse`` BCOO), to show why the layout was chosen.

Bytes moved per step (compulsory traffic of the preassembled update): the stiffness arrays
as stored (blocks, column and row indices; for SciPy its CSR arrays) once, and the state
vectors d(n), d(n-1), d(n+1), lumped mass, load vector and Dirichlet arrays once each; the
gathers of d(n) are assumed to hit cache. Achieved bandwidth = bytes / time, compared with
this machine's copy bandwidth (numpy ``copyto`` of 400 MB: read + write bytes per second),
measured in the same run. All the calls of a case are timed in rounds in which each is
called once, in turn, after an untimed first call of each, and the best round kept
(:func:`jaxsync.perf.measure.best_times`, the harness of all jaxsync timings): a drift of
the machine's load hits all alike; the median round is recorded too. The alternative
layouts are timed apart. ``ns/dof`` is the step's time per degree of freedom: the vessel's
against the beam's of the same size says what the unstructured mesh costs.

Usage: python benchmarks/bench_stepper.py [--quick] [--out benchmarks/results/stepper.json]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                           + " --xla_force_host_platform_device_count=2").strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxsync  # noqa: E402
from jaxsync.fem import advance, build_system, initial_state  # noqa: E402
from jaxsync.fem.forces import Preassembled  # noqa: E402
from jaxsync.perf.measure import copy_bandwidth, sample_times  # noqa: E402

# the single-device solver's compiled chunk: (system, state, n_saves, save_every)
advance_jit = jax.jit(advance, static_argnums=(2, 3))

MODES = {"": Preassembled(), "-f32": Preassembled(blocks_dtype="float32"), "-ell": Preassembled(layout="ell")}


def bytes_per_step(n_nodes, width):
    """Bytes of a step with one block ELL of ``width`` slots per row (the ``"ell"``
    layout) and the state vectors."""
    matrix = n_nodes * width * (9 * 8 + 4)
    return matrix + vector_bytes(n_nodes)


def vector_bytes(n_nodes):
    return n_nodes * 3 * 8 * 6 + n_nodes * 3  # d, prev, new, mass, load, fixed values; mask


def operator_bytes(stiffness) -> int:
    """Bytes of a stiffness operator's arrays (every leaf of the pytree, as stored)."""
    return int(sum(np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(stiffness)))


def time_factors(problem, dt, n_steps):
    """(n_loads, n_steps) values of the loads' time functions at the steps' times."""
    _, times = problem.load_vectors()
    t = jnp.arange(n_steps) * dt
    return np.stack([np.asarray(jax.vmap(g)(t), dtype=float) for g in times]) if times else np.zeros((0, n_steps))


def scipy_loop(problem, dt, n_steps):
    """The same update with SciPy CSR: a call of ``n_steps`` steps, ``(fn, args)``. The
    loads' time functions are evaluated before the loop (a table per step)."""
    m = problem.material
    K = problem.operators.stiffness(m.lam, m.mu).tocsr()
    mass = np.repeat(np.asarray(problem.lumped_mass()), 3)
    vectors, _ = problem.load_vectors()
    loads = [np.asarray(v).ravel() for v in vectors]
    factors = time_factors(problem, dt, n_steps)
    fixed, values = problem.dirichlet_dofs()
    alpha = float(problem.damping)
    a = 0.5 * alpha * dt

    def run():
        d = np.zeros(K.shape[0])
        prev = np.zeros(K.shape[0])
        for n in range(n_steps):
            f = factors[0, n] * loads[0]
            for k in range(1, len(loads)):
                f = f + factors[k, n] * loads[k]
            new = (dt * dt * (f - K @ d) / mass + 2 * d - (1 - a) * prev) / (1 + a)
            new[fixed] = values
            prev, d = d, new

    return run, ()


def csr_bytes(problem):
    m = problem.material
    K = problem.operators.stiffness(m.lam, m.mu).tocsr()
    return K.data.nbytes + K.indices.nbytes + K.indptr.nbytes


def jax_single(problem, dt, n_steps, mode=None):
    system = build_system(problem, dt, MODES[""] if mode is None else mode)
    state = initial_state(problem, system)
    return (advance_jit, (system, state, 1, n_steps)), operator_bytes(system.stiffness)


def jax_two_devices(problem, dt, n_steps, mode=None):
    from jaxsync.solve.executors import DistributedRunner

    mode = MODES[""] if mode is None else mode
    system = build_system(problem, dt, mode)
    state = initial_state(problem, system)
    runner = DistributedRunner(problem, system, 2, save_every=n_steps, mode=mode)
    # the larger part's stiffness (both are padded to it)
    per_part = operator_bytes(runner.parts.system.stiffness) // 2
    return (runner.program(1), (runner.parts, runner.from_global(state))), per_part


def jax_alternative(problem, dt, n_steps, layout):
    """The same step with another mat-vec layout (for the record)."""
    from jaxsync.pytree import pytree_dataclass

    system = build_system(problem, dt, MODES["-ell"])
    state = initial_state(problem, system)
    cols, blocks = np.asarray(system.stiffness.columns), np.asarray(system.stiffness.blocks)
    if layout == "einsum":
        @pytree_dataclass
        class EinsumEll:
            columns: jax.Array
            blocks: jax.Array

            def matvec(self, u):
                return jnp.einsum("rwij,rwj->ri", self.blocks, u[self.columns])

        op = EinsumEll(jnp.asarray(cols), jnp.asarray(blocks.transpose(0, 2, 1, 3)))
    else:
        from jax.experimental import sparse as jsparse

        m = problem.material
        K = problem.operators.stiffness(m.lam, m.mu).tocoo()

        @pytree_dataclass
        class Bcoo:
            matrix: jsparse.BCOO

            def matvec(self, u):
                return (self.matrix @ u.reshape(-1)).reshape(u.shape)

        op = Bcoo(jsparse.BCOO.from_scipy_sparse(K))
    import dataclasses

    system = dataclasses.replace(system, stiffness=op)
    return advance_jit, (system, state, 1, n_steps)


def vessel_problem(target_elements, element="P1"):
    return jaxsync.coronary(jaxsync.coronary_mesh(target_elements=target_elements)).replace(element=element)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="only the cantilever, the 15k- and 93k-dof beams and the 91k-dof vessel")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "stepper.json"))
    args = parser.parse_args(argv)

    # (name, problem factory, steps per call, repeats, in --quick). The calls of a case
    # are timed round-robin (the best of ``repeats`` rounds), so that a drift of the
    # machine hits all alike: timed one after another with 3 repeats, the 14 823-dof beam
    # read 0.78-0.87x SciPy, round-robin with 30 repeats 1.00-1.25x.
    def beam(divisions):
        return lambda: jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, divisions))

    cases = [("cantilever-coarse", beam((25, 1, 1)), 2000, 15, True),
             ("beam-15k-dofs", beam((60, 8, 8)), 100, 25, True),
             ("beam-51k-dofs", beam((100, 12, 12)), 40, 15, False),
             ("beam-93k-dofs", beam((120, 15, 15)), 20, 15, True),
             ("vessel-91k-dofs", lambda: vessel_problem(100_000), 20, 15, True),
             ("beam-266k-dofs", beam((200, 20, 20)), 10, 9, False),
             ("vessel-269k-dofs", lambda: vessel_problem(330_000), 10, 9, False),
             ("vessel-p2-98k-dofs", lambda: vessel_problem(15_000, "P2"), 20, 15, False)]
    bandwidth = copy_bandwidth() / 1e9  # GB/s
    rows = []
    for name, make, n_steps, repeats, quick in cases:
        if args.quick and not quick:
            continue
        problem = make()
        dt = problem.dt
        n_dofs = problem.n_dofs
        vectors = vector_bytes(problem.n_nodes)
        calls = {"scipy-csr": scipy_loop(problem, dt, n_steps)}
        nbytes = {"scipy-csr": csr_bytes(problem) + vectors}
        for suffix in ("", "-f32", "-ell"):
            calls[f"jax-1dev{suffix}"], op = jax_single(problem, dt, n_steps, MODES[suffix])
            nbytes[f"jax-1dev{suffix}"] = op + vectors
        for suffix in ("", "-f32"):
            calls[f"jax-2dev{suffix}"], op = jax_two_devices(problem, dt, n_steps, MODES[suffix])
            nbytes[f"jax-2dev{suffix}"] = 2 * op + vectors
        samples = {impl: t / n_steps for impl, t in sample_times(calls, repeats).items()}
        # the slow alternative layouts apart: their large temporaries would evict the others'
        # working sets between rounds
        if not args.quick and name.startswith(("beam", "cantilever")):
            for layout in ("einsum", "bcoo"):
                fn, fargs = jax_alternative(problem, dt, n_steps, layout)
                samples[f"jax-{layout}"] = sample_times({layout: (fn, fargs)}, max(3, repeats // 3))[layout] / n_steps
                nbytes[f"jax-{layout}"] = nbytes["jax-1dev-ell"]
        scipy_best = samples["scipy-csr"].min()
        widths = getattr(build_system(problem, dt).stiffness, "widths", None)
        for impl, seconds in samples.items():
            best = float(seconds.min())
            rows.append({"case": name, "dofs": n_dofs, "impl": impl,
                         "us_per_step": 1e6 * best, "us_per_step_median": 1e6 * float(np.median(seconds)),
                         "ns_per_dof": 1e9 * best / n_dofs, "bytes_per_step": nbytes[impl],
                         "GB_per_s": nbytes[impl] / best / 1e9, "speedup_vs_scipy": float(scipy_best / best),
                         "group_widths": list(widths) if widths is not None else None})
        print(f"{name}: done (load {os.getloadavg()[0]:.2f})", flush=True)
    print(f"copy bandwidth (read + write): {bandwidth:.1f} GB/s; devices: "
          f"{len(jax.devices())} x {jax.devices()[0].platform} (emulated), {os.cpu_count()} cores; "
          f"load {os.getloadavg()[0]:.2f}")
    print(f"{'case':<18} {'dofs':>7} {'impl':<13} {'us/step':>10} {'median':>10} {'ns/dof':>7} "
          f"{'MB/step':>8} {'GB/s':>6} {'vs scipy':>9}")
    for r in rows:
        print(f"{r['case']:<18} {r['dofs']:>7} {r['impl']:<13} {r['us_per_step']:>10.1f} "
              f"{r['us_per_step_median']:>10.1f} {r['ns_per_dof']:>7.2f} {r['bytes_per_step'] / 1e6:>8.2f} "
              f"{r['GB_per_s']:>6.2f} {r['speedup_vs_scipy']:>8.2f}x")
    per_dof = {(r["case"], r["impl"]): r["ns_per_dof"] for r in rows}
    for vessel, same_size in (("vessel-91k-dofs", "beam-93k-dofs"), ("vessel-269k-dofs", "beam-266k-dofs")):
        for impl in ("jax-1dev", "jax-1dev-f32", "jax-2dev"):
            if (vessel, impl) in per_dof and (same_size, impl) in per_dof:
                print(f"{vessel} / {same_size} per dof, {impl}: "
                      f"{per_dof[vessel, impl] / per_dof[same_size, impl]:.2f}")
    result = {"benchmark": "stepper", "copy_bandwidth_GB_per_s": bandwidth, "rows": rows,
              "machine": {"platform": platform.platform(), "cores": os.cpu_count(),
                          "python": sys.version.split()[0], "jax": jax.__version__,
                          "load_average": os.getloadavg()[0],
                          "devices": f"{len(jax.devices())} emulated CPU devices"}}
    from jaxsync.io import atomic_json

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    atomic_json(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
