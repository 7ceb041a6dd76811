"""GPU readiness: the stepper, the distributed programs and zeta on accelerator devices.

One prepared run for a machine with a GPU (``python benchmarks/bench_gpu.py``); on a
machine without one it says so and exits with status 3 unless ``--platform cpu`` is
given (what the tests run, to keep the script working). It checks, on the devices of the
chosen platform:

1. the explicit stepper (node-blocked ELL mat-vec, ``lax.scan``) against the SciPy CSR
   loop on the host, at 312, 14 823, 51 207 and 265 923 dofs (``--quick``: the first
   two), us per step and achieved GB/s of the compulsory traffic;
2. the SPMD programs unchanged: the cantilever on 2 parts with ``psum``, ``ppermute`` and
   deep halos (k = 4) equal to the single-device run to round-off (on one GPU the 2 parts
   share it, a vmapped axis; on several, one each);
3. the synchronization-avoiding program and zeta (:func:`jaxsync.perf.timing.speedup_breakdown`)
   for the paper's LSTM, the default LSTM and the linear surrogate, with deep halos.

Writes ``--out`` (default ``benchmarks/results/gpu.json``) and prints a table. Nothing in it
is GPU-specific code: the point is that the same programs run there.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import jaxsync

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # bench_stepper's SciPy loop

SIZES = ((25, 1, 1), (60, 8, 8), (100, 12, 12), (200, 20, 20))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--platform", default="gpu", help="JAX platform to check (default: gpu; cpu for a dry run)")
    parser.add_argument("--quick", action="store_true",
                        help="the two smaller meshes, fewer repeats, the linear surrogate only at n_s 15")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results",
                                                      "gpu.json"))
    args = parser.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    try:
        devices = jax.devices(args.platform)
    except RuntimeError as exc:
        print(f"no {args.platform} devices here ({exc}); run on a machine with one, or pass --platform cpu "
              "for a dry run on the CPU")
        return 3
    import numpy as np
    from bench_stepper import bytes_per_step, scipy_loop

    from jaxsync.fem.stepper import advance, build_system, initial_state
    from jaxsync.perf.measure import best_times, describe_devices
    from jaxsync.perf.timing import speedup_breakdown
    from jaxsync.surrogate import Surrogate

    result = {"benchmark": "gpu readiness", "platform": args.platform, "devices": describe_devices(devices),
              "n_devices": len(devices), "jax": jax.__version__, "python": platform.python_version(),
              "stepper": [], "distributed": [], "speedup": []}
    repeats = 5 if args.quick else 15
    advance_jit = jax.jit(advance, static_argnums=(2, 3))
    for divisions in SIZES[:2] if args.quick else SIZES:
        problem = jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, divisions))
        n_steps = max(10, int(2e5 // problem.mesh.n_dofs))
        system = jax.device_put(build_system(problem, problem.dt), devices[0])
        state = jax.device_put(initial_state(problem, system), devices[0])
        times = best_times({"scipy-csr": scipy_loop(problem, float(problem.dt), n_steps),
                            "jax": (advance_jit, (system, state, 1, n_steps))}, repeats)
        nbytes = bytes_per_step(problem.mesh.n_nodes, problem.operators.block_ell[0].shape[1])
        t_jax, t_scipy = times["jax"] / n_steps, times["scipy-csr"] / n_steps
        result["stepper"].append({"dofs": problem.mesh.n_dofs, "us_per_step": 1e6 * t_jax,
                                  "scipy_us_per_step": 1e6 * t_scipy, "GB_per_s": nbytes / t_jax / 1e9,
                                  "vs_scipy": t_scipy / t_jax})

    problem = jaxsync.cantilever()
    part = jaxsync.partition(problem.mesh, 2)
    on = devices[:2] if len(devices) >= 2 else devices[:1]
    single = jaxsync.simulate(problem, 2000, save=100, executor=jaxsync.HostExecutor(progress=False))
    scale = np.abs(single.displacement).max()
    for strategy, extra in ((jaxsync.Psum(on), {}), (jaxsync.Ppermute(on), {}), (jaxsync.Halo(4, on),
                                                                                 {"halo_depth": 4})):
        start = time.perf_counter()
        run = jaxsync.simulate(problem, 2000, save=100, partitions=part, sync=strategy,
                               executor=jaxsync.HostExecutor(progress=False))
        result["distributed"].append({"sync": strategy.name, **extra, "n_devices": len(on),
                                      "max_rel_diff_vs_single": float(np.abs(run.displacement - single.displacement
                                                                             ).max() / scale),
                                      "seconds": time.perf_counter() - start})

    surrogates = {"lstm-paper": Surrogate.initialized(part, 80, n_hidden=100),
                  "lstm-default": Surrogate.initialized(part, 150, n_hidden=50),
                  "linear": Surrogate.initialized(part, 150, model="linear")}
    if args.quick:  # a dry run: one surrogate (the programs are the same), shorter refill cycles
        surrogates = {"linear": Surrogate.initialized(part, 15, model="linear")}
    for name, predictor in surrogates.items():
        report = speedup_breakdown(problem, part, predictor, syncs=(jaxsync.Psum(on), jaxsync.Ppermute(on)),
                                   repeats=3 if args.quick else 10, stage_repeats=3 if args.quick else 20,
                                   halo_depths=(1, 4))
        result["speedup"].append({"surrogate": name, "zeta": report.zeta, "sync": report.sync,
                                  "t_step_sync_us": {k: 1e6 * v for k, v in report.t_step_sync.items()},
                                  "t_step_avoiding_us": 1e6 * report.t_step_avoiding, "t_d_us": 1e6 * report.t_d,
                                  "zeta_halo": report.zeta_halo})

    print(f"{result['devices']} ({len(devices)} {args.platform} devices), jax {jax.__version__}")
    for r in result["stepper"]:
        print(f"stepper {r['dofs']:>7} dofs: {r['us_per_step']:9.1f} us/step ({r['GB_per_s']:6.1f} GB/s), "
              f"SciPy on the host {r['scipy_us_per_step']:9.1f} ({r['vs_scipy']:.2f}x)")
    for r in result["distributed"]:
        print(f"2 parts on {r['n_devices']} device(s), {r['sync']}: max relative difference from one device "
              f"{r['max_rel_diff_vs_single']:.1e}")
    for r in result["speedup"]:
        print(f"zeta {r['surrogate']:<12} {r['zeta']:.2f} (t_d {r['t_d_us']:.2f} us); deep halos "
              + ", ".join(f"k={k} {z:.2f}" for k, z in r["zeta_halo"].items()))
    from jaxsync.io import atomic_json

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    atomic_json(args.out, result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
