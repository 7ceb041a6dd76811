"""Stiffness blocks in float32: how far the trajectory moves from float64.

``Preassembled(blocks_dtype="float32")`` stores K's off-diagonal blocks in single precision
(each row's diagonal block stays float64, minus the sum of the rounded ones) while the
state and every sum stay float64. Each case runs twice, float64 and float32 blocks, over
the same steps, and records the largest displacement error over the largest displacement
(overall, at the quarters of the run and at its end):

- ``cantilever``: the paper's coarse cantilever (312 dofs), loaded from rest;
- ``vessel-8k``: the coronary problem (pulsatile lumen pressure) on an 8k-dof tree;
- ``vessel-91k``: the same on the 91k-dof tree of the stepper benchmark;
- ``vessel-rough``: a 3.5k-tet tree started from random initial displacement and velocity
  under a constant body force, little damping: every mode rings for the whole run, the
  worst case for the rounding.

Usage: python benchmarks/bench_float32.py [--steps 100000] [--case NAME ...] [--quick]
    [--out benchmarks/results/float32.json]

``--quick``: the cantilever and the rough vessel over 2 000 steps (the test's settings).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import experiments  # noqa: E402  (machine())
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxsync  # noqa: E402
from jaxsync.fem.forces import Preassembled  # noqa: E402
from jaxsync.io import atomic_json  # noqa: E402

DEFAULT_OUT = os.path.join(HERE, "results", "float32.json")


def rough_vessel():
    tree = jaxsync.coronary_mesh(target_elements=3500)
    rng = np.random.default_rng(6)
    return jaxsync.Problem(tree, jaxsync.LinearElastic(6.26e6, 0.4, 1.0),
                           dirichlet=(jaxsync.Dirichlet("inlet"), jaxsync.Dirichlet("outlet")),
                           loads=(jaxsync.BodyForce((2.0e3, -1.0e3, 5.0e2), jaxsync.Constant()),), damping=0.5,
                           initial_displacement=1e-4 * rng.standard_normal((tree.n_nodes, 3)),
                           initial_velocity=1e-2 * rng.standard_normal((tree.n_nodes, 3)))


CASES = {
    "cantilever": jaxsync.cantilever,
    "vessel-8k": lambda: jaxsync.coronary(jaxsync.coronary_mesh(target_elements=8000)),
    "vessel-91k": lambda: jaxsync.coronary(jaxsync.coronary_mesh(target_elements=100_000)),
    "vessel-rough": rough_vessel,
}


def measure(name: str, n_steps: int) -> dict:
    problem = CASES[name]()
    quiet = jaxsync.HostExecutor(progress=False)
    n_saves = min(100, n_steps)
    every = n_steps // n_saves
    runs, seconds = {}, {}
    for dtype in ("float64", "float32"):
        start = time.perf_counter()
        runs[dtype] = np.asarray(jaxsync.simulate(problem, every * n_saves, save=every, executor=quiet,
                                                  mode=Preassembled(blocks_dtype=dtype)).displacement)
        seconds[dtype] = time.perf_counter() - start
    error = np.abs(runs["float32"] - runs["float64"]).reshape(n_saves + 1, -1).max(axis=1)
    scale = np.abs(runs["float64"]).reshape(n_saves + 1, -1).max(axis=1)
    return {"case": name, "dofs": problem.n_dofs, "steps": every * n_saves, "dt": float(problem.dt),
            "error": float(error.max() / scale.max()),
            "at_quarters": [float(error[k * n_saves // 4] / scale.max()) for k in (1, 2, 3, 4)],
            "final_relative": float(error[-1] / scale[-1]), "seconds": seconds}


def table(rows: list[dict]) -> str:
    lines = ["| case | dofs | steps | error / max displacement | at 1/4, 1/2, 3/4, end |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['dofs']} | {r['steps']} | {r['error']:.2e} | "
                     + ", ".join(f"{q:.1e}" for q in r["at_quarters"]) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=None, help="steps per run (default 100000; --quick 2000)")
    parser.add_argument("--case", nargs="+", choices=list(CASES), default=None, help="cases (default: all)")
    parser.add_argument("--quick", action="store_true", help="the cantilever and the rough vessel, 2000 steps")
    parser.add_argument("--out", default=DEFAULT_OUT, help="result JSON (default %(default)s)")
    args = parser.parse_args(argv)
    cases = args.case or (["cantilever", "vessel-rough"] if args.quick else list(CASES))
    n_steps = args.steps or (2000 if args.quick else 100_000)
    rows = []
    for name in cases:
        rows.append(measure(name, n_steps))
        print(f"{name}: {rows[-1]['error']:.2e}", flush=True)
    text = table(rows)
    print(text)
    atomic_json(args.out, {"rows": rows, "quick": args.quick, "table": text, "machine": experiments.machine(),
                           "command": "python benchmarks/bench_float32.py" + (" --quick" if args.quick else "")})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
