"""Explicit stepper: microseconds per step, bytes moved and achieved bandwidth.

For the default coarse cantilever (312 dofs) and beams of 14 823, 51 207 and 265 923 dofs
(the middle ones about a part of the paper's vessel on 11 parts; ``--quick`` leaves out the
largest), side by side in the same run:

- ``scipy-csr``: a SciPy CSR loop doing the same update (K d, loads, damping, Dirichlet);
- ``jax-1dev``: jaxsync's compiled stepper (node-blocked ELL, ``lax.scan``) on one device;
- ``jax-2dev``: the same problem split into 2 parts over 2 (emulated CPU) devices with
  ``shard_map`` and a psum of the interface forces: this is how jaxsync uses both cores;
- ``jax-einsum`` and ``jax-bcoo``: alternative layouts kept for the record (the einsum
  over (n, w, 3, 3) blocks that XLA lowers to a batched dot, and
  ``jax.experimental.sparse`` BCOO), to show why the layout was chosen.

Bytes moved per step (compulsory traffic of the preassembled update): the stiffness
blocks and column indices once, and the state vectors d(n), d(n-1), d(n+1), lumped mass,
load vector and Dirichlet arrays once each; the gathers of d(n) are assumed to hit cache.
Achieved bandwidth = bytes / time, compared with this machine's copy bandwidth
(numpy ``copyto`` of 400 MB: read + write bytes per second), measured in the same run.
SciPy and jaxsync (1 and 2 devices) are timed in rounds in which each is called once, in
turn, after an untimed first call of each, and the best round kept
(:func:`jaxsync.perf.measure.best_times`, the harness of all jaxsync timings): a drift of
the machine's load hits all alike. The alternative layouts are timed apart.

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
from jaxsync.fem.stepper import advance, build_system, initial_state  # noqa: E402
from jaxsync.perf.measure import best_times, copy_bandwidth  # noqa: E402

# the single-device solver's compiled chunk: (system, state, n_saves, save_every)
advance_jit = jax.jit(advance, static_argnums=(2, 3))


def bytes_per_step(n_nodes, width):
    matrix = n_nodes * width * (9 * 8 + 4)
    vectors = n_nodes * 3 * 8 * 6 + n_nodes * 3  # d, prev, new, mass, load, fixed values; mask
    return matrix + vectors


def scipy_loop(problem, dt, n_steps):
    """The same update with SciPy CSR: a call of ``n_steps`` steps, ``(fn, args)``."""
    m = problem.material
    K = problem.operators.stiffness(m.lam, m.mu)
    mass = np.repeat(np.asarray(problem.lumped_mass()), 3)
    vectors, times = problem.load_vectors()
    load = np.asarray(vectors[0]).ravel()
    t_ramp = float(times[0].t_end)
    fixed, values = problem.dirichlet_dofs()
    alpha = float(problem.damping)
    a = 0.5 * alpha * dt

    def run():
        d = np.zeros(K.shape[0])
        prev = np.zeros(K.shape[0])
        for n in range(n_steps):
            f = min(n * dt / t_ramp, 1.0) * load  # the cantilever's ramp, in NumPy
            new = (dt * dt * (f - K @ d) / mass + 2 * d - (1 - a) * prev) / (1 + a)
            new[fixed] = values
            prev, d = d, new

    return run, ()


def jax_single(problem, dt, n_steps):
    system = build_system(problem, dt)
    state = initial_state(problem, system)
    return advance_jit, (system, state, 1, n_steps)


def jax_two_devices(problem, dt, n_steps):
    from jaxsync.solve.distributed import DistributedRunner

    system = build_system(problem, dt)
    state = initial_state(problem, system)
    runner = DistributedRunner(problem, system, 2, save_every=n_steps)
    return runner.program(1), (runner.parts, runner.from_global(state))


def jax_alternative(problem, dt, n_steps, layout):
    """The same step with another mat-vec layout (for the record)."""
    from jaxsync.pytree import pytree_dataclass

    system = build_system(problem, dt)
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


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="leave out the 266k-dof case")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "stepper.json"))
    args = parser.parse_args(argv)

    # (name, divisions, steps per call, repeats). SciPy and jaxsync are timed round-robin
    # (jaxsync.perf.measure.best_times: the best of ``repeats`` rounds), so that a drift of
    # the machine hits both alike: timed one after another with 3 repeats, the 14 823-dof
    # case read 0.78-0.87x SciPy, round-robin with 30 repeats 1.00-1.25x.
    cases = [("cantilever-coarse", (25, 1, 1), 2000, 15),
             ("beam-15k-dofs", (60, 8, 8), 100, 30),
             ("beam-51k-dofs", (100, 12, 12), 40, 15)]
    if not args.quick:
        cases.append(("beam-266k-dofs", (200, 20, 20), 10, 7))
    bandwidth = copy_bandwidth() / 1e9  # GB/s
    rows = []
    for name, divisions, n_steps, repeats in cases:
        mesh = jaxsync.box_beam(25.0, 1.0, 1.0, divisions)
        problem = jaxsync.cantilever(mesh)
        dt = problem.dt
        width = problem.operators.block_ell[0].shape[1]
        nbytes = bytes_per_step(mesh.n_nodes, width)
        calls = {"scipy-csr": scipy_loop(problem, dt, n_steps),
                 "jax-1dev": jax_single(problem, dt, n_steps),
                 "jax-2dev": jax_two_devices(problem, dt, n_steps)}
        timings = {impl: t / n_steps for impl, t in best_times(calls, repeats).items()}
        # the slow alternative layouts apart: their large temporaries would evict the others'
        # working sets between rounds
        for layout in ("einsum", "bcoo"):
            fn, fargs = jax_alternative(problem, dt, n_steps, layout)
            timings[f"jax-{layout}"] = best_times({layout: (fn, fargs)}, max(3, repeats // 3))[layout] / n_steps
        for impl, seconds in timings.items():
            rows.append({"case": name, "dofs": mesh.n_dofs, "impl": impl,
                         "us_per_step": 1e6 * seconds, "bytes_per_step": nbytes,
                         "GB_per_s": nbytes / seconds / 1e9,
                         "speedup_vs_scipy": timings["scipy-csr"] / seconds})
    print(f"copy bandwidth (read + write): {bandwidth:.1f} GB/s; devices: "
          f"{len(jax.devices())} x {jax.devices()[0].platform} (emulated), {os.cpu_count()} cores; "
          f"load {os.getloadavg()[0]:.2f}")
    print(f"{'case':<20} {'dofs':>8} {'impl':<12} {'us/step':>11} {'MB/step':>9} {'GB/s':>7} "
          f"{'of copy':>8} {'vs scipy':>9}")
    for r in rows:
        print(f"{r['case']:<20} {r['dofs']:>8} {r['impl']:<12} {r['us_per_step']:>11.1f} "
              f"{r['bytes_per_step'] / 1e6:>9.2f} {r['GB_per_s']:>7.2f} "
              f"{r['GB_per_s'] / bandwidth:>7.0%} {r['speedup_vs_scipy']:>8.2f}x")
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
