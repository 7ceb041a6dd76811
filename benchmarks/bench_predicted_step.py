"""What a predicted step costs on the vessel: the surrogate's share (t_d) of the
synchronized step, and what the step pays besides the surrogate.

The demo's vessel (:func:`jaxsync.app.demo.vessel_problem`, the generated coronary tree
mass-scaled, the paper's pulsatile pressure) split into 11 METIS parts on the 2 CPU
devices this machine has (the parts of a device run vmapped), n_s = 1000, n_p = n_f = 20
(the demo's sampling). For each surrogate, :func:`jaxsync.perf.timing.speedup_breakdown`
times in one round-robin the synchronized program (psum), the same program without
synchronization, and the synchronization-avoiding program (n_s n_f steps with the
predicted shared-node displacements written into every step, and one batched refill
prediction of all parts), and the refill prediction alone in the SPMD program (t_d: its
time over the n_s n_f steps it serves). The table gives:

- ``t_sync``, ``t_nosync``, ``t_avoid``: us per step of the three programs;
- ``t_d``: us per step of the prediction, and ``t_d / t_sync``;
- ``rest``: t_avoid - t_nosync - t_d, what a predicted step costs beyond a step without
  synchronization and its share of the prediction (the write of the predictions into the
  step);
- ``zeta`` = t_sync / t_avoid on these devices.

Surrogates (untrained replicas: a network's cost does not depend on its weights,
:meth:`jaxsync.surrogate.Surrogate.initialized`), each with the default smooth refill
(:data:`jaxsync.surrogate.DEFAULT_REFILL_SAMPLES` network applications per refill,
column ``calls``): ``lstm``, the vessel demo's network (n_H 32, 2 layers) with a linear
highway of ``--highway-rank`` directions; ``lstm-all``, the same network evaluating all
n_s applications per refill (``refill_samples=None``, the exact block means);
``lstm-bare``, the LSTM without the highway; ``linear``, the linear map of
``--linear-rank`` directions. The ranks stand for what a fit keeps (the ridge drops the directions it
suppresses; a trained surrogate file says its own rank).

Devices are emulated: two XLA host devices on two cores, so a psum is a meeting of
threads, not a message; the share t_d / t_sync is what a machine like this one pays, and
the cost model (:mod:`jaxsync.perf.costmodel`, ``gpu_projection.py``) carries t_d to
other interconnects.

Usage: python benchmarks/bench_predicted_step.py [--quick] [--surrogates lstm lstm-all lstm-bare linear]
       [--highway-rank 108] [--linear-rank 108] [--repeats 5]
       [--out benchmarks/results/predicted_step.json]
``--quick``: the coarse cantilever on 2 parts, n_s = 10, one repeat (what the tests run).
"""

from __future__ import annotations

import argparse
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import jax  # noqa: E402

import jaxsync  # noqa: E402

jaxsync.parallel.devices.request_cpu_devices(2)
jax.config.update("jax_enable_x64", True)

import experiments  # noqa: E402  (machine())

from jaxsync.io import atomic_json  # noqa: E402
from jaxsync.perf.timing import speedup_breakdown  # noqa: E402
from jaxsync.surrogate import Surrogate  # noqa: E402

DEFAULT_OUT = os.path.join(HERE, "results", "predicted_step.json")
SURROGATES = ("lstm", "lstm-all", "lstm-bare", "linear")


def case(quick: bool):
    """(name, problem, partition, n_s)."""
    if quick:
        problem = jaxsync.cantilever()
        return "cantilever", problem, jaxsync.partition(problem.mesh, 2, seed=0), 10
    from jaxsync.app.demo import vessel_problem

    problem = vessel_problem("small")[1]
    return "vessel", problem, jaxsync.partition(problem.mesh, 11, seed=0), 1000


def surrogate(kind: str, partition, n_s: int, highway_rank: int, linear_rank: int) -> Surrogate:
    if kind == "linear":
        return Surrogate.initialized(partition, n_s, model="linear", rank=linear_rank)
    lstm = Surrogate.initialized(partition, n_s, n_hidden=32, n_layers=2,
                                 highway_rank=0 if kind == "lstm-bare" else highway_rank)
    return lstm.with_refill_samples(None) if kind == "lstm-all" else lstm


def measure(problem, partition, predictor, repeats: int) -> dict:
    report = speedup_breakdown(problem, partition, predictor, syncs=("psum",), repeats=repeats,
                               stage_repeats=max(2, repeats // 2), prediction_repeats=max(2, repeats // 2))
    us = 1e6
    t_sync, t_nosync, t_avoid = report.t_step_sync["psum"], report.t_step_nosync, report.t_step_avoiding
    t_d = report.t_prediction_spmd / (predictor.n_s * predictor.n_future)
    return {"t_sync_us": t_sync * us, "t_nosync_us": t_nosync * us, "t_avoid_us": t_avoid * us, "t_d_us": t_d * us,
            "t_d_over_t_sync": t_d / t_sync, "rest_us": (t_avoid - t_nosync - t_d) * us, "zeta": t_sync / t_avoid,
            "timed_steps": report.n_steps, "repeats": repeats}


def table(rows: list[dict]) -> str:
    lines = ["| surrogate | rank | calls | t_sync | t_nosync | t_avoid | t_d | t_d / t_sync | rest | zeta |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['surrogate']} | {r['rank']} | {r['refill_calls']} | {r['t_sync_us']:.1f} | "
                     f"{r['t_nosync_us']:.1f} | "
                     f"{r['t_avoid_us']:.1f} | {r['t_d_us']:.1f} | {100 * r['t_d_over_t_sync']:.0f} % | "
                     f"{r['rest_us']:.1f} | {r['zeta']:.2f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="the cantilever, n_s = 10, one repeat")
    parser.add_argument("--surrogates", nargs="+", choices=SURROGATES, default=list(SURROGATES))
    parser.add_argument("--highway-rank", type=int, default=108,
                        help="the LSTM's highway directions (default: what the vessel demo's fit keeps)")
    parser.add_argument("--linear-rank", type=int, default=108, help="the linear map's directions")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per program (default 5; --quick 1)")
    parser.add_argument("--out", default=DEFAULT_OUT, help="result JSON (default %(default)s)")
    args = parser.parse_args(argv)
    repeats = args.repeats or (1 if args.quick else 5)
    name, problem, partition, n_s = case(args.quick)
    rows = []
    for kind in args.surrogates:
        rank = {"lstm-bare": 0, "linear": args.linear_rank}.get(kind, args.highway_rank)
        predictor = surrogate(kind, partition, n_s, args.highway_rank, args.linear_rank)
        row = {"surrogate": kind, "rank": rank, "refill_calls": predictor.refill_calls,
               **measure(problem, partition, predictor, repeats)}
        rows.append(row)
        print(f"{kind}: t_d {row['t_d_us']:.1f} us = {100 * row['t_d_over_t_sync']:.0f} % of the synchronized "
              f"step, zeta {row['zeta']:.2f}", flush=True)
    text = table(rows)
    header = (f"{name}: {problem.n_dofs} dofs, {partition.n_parts} parts on {len(jax.devices())} CPU devices, "
              f"{len(partition.shared_nodes)} shared nodes, n_s = {n_s}, n_p = n_f = 20; us per step")
    print(header)
    print(text)
    command = "python benchmarks/bench_predicted_step.py" + (" --quick" if args.quick else "")
    atomic_json(args.out, {"case": name, "n_dofs": int(problem.n_dofs), "n_parts": int(partition.n_parts),
                           "n_devices": len(jax.devices()), "n_shared_nodes": int(len(partition.shared_nodes)),
                           "n_s": n_s, "rows": rows, "header": header, "table": text,
                           "machine": experiments.machine(), "command": command})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
