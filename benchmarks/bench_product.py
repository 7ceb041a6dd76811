"""The two forms of the stiffness product: compile time against step time.

``Preassembled(product=...)`` computes K u either ``"fused"`` (an unrolled sum over
(slot, column component) that XLA fuses with the gathers into one loop: the fastest step)
or ``"compact"`` (one gather of every neighbour and one reduction: a program of a few
operations whatever the row width, so it compiles faster, and a slower step because the
gathered array is materialized). ``product="auto"`` (the default of
:func:`jaxsync.simulate`) takes the compact form for runs of fewer than
``COMPACT_SLOT_STEPS`` stored slots times steps. This script measures both forms on a few
meshes, one device and two parts, and reports

- ``compile_s``: the seconds :func:`jaxsync.simulate` spent compiling (``stats``);
- ``wall_s``: the whole :func:`jaxsync.simulate` call of ``--steps`` steps (tracing,
  compiling, the initial state, the steps);
- ``us_per_step``: the compiled chunks' time per step;
- ``break_even_steps``: the run length at which the fused form's faster steps repay its
  longer setup, (wall_fused - wall_compact at ``--steps``) / (step_compact - step_fused)
  + ``--steps``, and the same in slot-steps (times the mesh's stored slots), to compare
  with ``COMPACT_SLOT_STEPS``.

Each form is run ``--repeats`` times in this process with JAX's caches cleared before each
call, alternating the forms; the best of each is kept.

Usage: python benchmarks/bench_product.py [--steps 2000] [--repeats 2] [--case NAME ...]
    [--quick] [--out benchmarks/results/product/product.json]

``--quick``: the cantilever on one device, 200 steps, one repeat (the test's settings).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

if "--xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()

import experiments  # noqa: E402  (machine())
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxsync  # noqa: E402
from jaxsync.fem.forces import COMPACT_SLOT_STEPS, Preassembled  # noqa: E402
from jaxsync.io import atomic_json  # noqa: E402

DEFAULT_OUT = os.path.join(HERE, "results", "product", "product.json")


def _beam(divisions):
    return jaxsync.cantilever(jaxsync.box_beam(25.0, 1.0, 1.0, divisions))


CASES = {
    "cantilever": jaxsync.cantilever,
    "beam-2k": lambda: _beam((40, 3, 3)),
    "tree-3.5k": lambda: jaxsync.coronary(jaxsync.coronary_mesh(target_elements=3500)),
}


def measure(problem, n_steps: int, product: str, parts: int | None) -> dict:
    """One :func:`jaxsync.simulate` call of ``n_steps`` steps with a fresh JAX cache."""
    jax.clear_caches()
    start = time.perf_counter()
    run = jaxsync.simulate(problem, n_steps, save=n_steps, partitions=parts, mode=Preassembled(product=product),
                           executor=jaxsync.HostExecutor(progress=False))
    jax.block_until_ready(run.displacement)
    return {"wall_s": time.perf_counter() - start, "compile_s": float(run.stats.compile_seconds),
            "us_per_step": float(run.stats.us_per_step)}


def case_rows(name: str, n_steps: int, repeats: int, part_counts) -> list[dict]:
    problem = CASES[name]()
    slots = int(np.prod(np.shape(problem.operators.block_ell[0])))
    rows = []
    for parts in part_counts:
        best = {}
        for _ in range(repeats):
            for product in ("fused", "compact"):
                m = measure(problem, n_steps, product, parts)
                best[product] = m if product not in best else {k: min(v, m[k]) for k, v in best[product].items()}
        fused, compact = best["fused"], best["compact"]
        penalty = compact["us_per_step"] - fused["us_per_step"]
        saving = fused["wall_s"] - compact["wall_s"]
        even = n_steps + 1e6 * saving / penalty if penalty > 0 and saving > 0 else None
        rows.append({"case": name, "parts": parts or 1, "n_nodes": problem.n_nodes, "slots": slots,
                     "n_steps": n_steps, "fused": fused, "compact": compact,
                     "break_even_steps": even, "break_even_slot_steps": None if even is None else even * slots})
    return rows


def print_table(rows) -> None:
    print(f"{'case':11} {'parts':>5} {'slots':>6} | {'compile s fused/compact':>24} | {'wall s fused/compact':>21} "
          f"| {'us/step fused/compact':>22} | {'break-even slot-steps':>21}")
    for r in rows:
        f, c = r["fused"], r["compact"]
        even = "-" if r["break_even_slot_steps"] is None else f"{r['break_even_slot_steps']:.2g}"
        print(f"{r['case']:11} {r['parts']:5d} {r['slots']:6d} | {f['compile_s']:11.2f} / {c['compile_s']:10.2f} | "
              f"{f['wall_s']:9.2f} / {c['wall_s']:9.2f} | {f['us_per_step']:10.1f} / {c['us_per_step']:9.1f} | "
              f"{even:>21}")
    print(f"product='auto' takes the compact form below {COMPACT_SLOT_STEPS:.2g} slot-steps")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--case", action="append", choices=sorted(CASES))
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    if args.quick:
        cases, steps, repeats, part_counts = ["cantilever"], 200, 1, (None,)
    else:
        cases, steps, repeats, part_counts = args.case or list(CASES), args.steps, args.repeats, (None, 2)
    rows = [row for name in cases for row in case_rows(name, steps, repeats, part_counts)]
    print_table(rows)
    record = {"machine": experiments.machine(), "compact_slot_steps": COMPACT_SLOT_STEPS, "rows": rows,
              "command": "python benchmarks/bench_product.py" + (" --quick" if args.quick else "")}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    atomic_json(args.out, record)
    print(f"written {args.out}")
    return record


if __name__ == "__main__":
    main()
