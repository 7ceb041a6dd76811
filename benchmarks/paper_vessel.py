"""The paper's coronary experiment (Tong & Schiavazzi 2022, sections 5.2 and 6) on the
generated coronary tree: 11 parts, pulsatile lumen pressure, mass scaling to 2.5 times
the CFL step, 11 surrogates, error control, es and es_hat over time.

Two modes:

* ``--mode run`` (default at ``--size small``): the whole pipeline, ``jaxsync demo --case
  vessel`` (:func:`jaxsync.app.demo.run_demo`): figures in ``<out>/report/`` (the
  displacement of a non-shared node of every part, e_l2, es and es_hat, the mass-scaling
  comparison of paper figure 19) and ``paper_vessel_<size>.json`` with the paper's
  targets evaluated.
* ``--mode measure`` (default at ``--size paper``, where the whole run takes days on a
  laptop): everything that sets the paper-size cost, measured on the paper-size mesh,
  and the whole run projected from it: mesh generation, mass scaling, partition, memory,
  the synchronized distributed step over ``--prefix-steps`` steps, the single-device step
  at the CFL step (the mass-scaling check), the whole SPMD programs synchronized and
  synchronization-avoiding (:func:`jaxsync.perf.timing.speedup_breakdown` with untrained
  replicas of the demo's architecture: a network costs the same trained or not), one
  refill prediction, the training epoch of the 11 replicas at the paper's data size, and
  the cost-model projection to 11 real processors.

Usage:
    python benchmarks/paper_vessel.py [--size small|paper|N] [--mode run|measure]
        [--prefix-steps 400] [--from-summary jaxsync-demo/summary.json]
        [--out benchmarks/results/paper_vessel]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import time

N_PARTS = 11

if __name__ == "__main__":
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + f" --xla_force_host_platform_device_count={N_PARTS}").strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxsync  # noqa: E402
from jaxsync.app.demo import demo_defaults, format_summary, run_demo, vessel_problem  # noqa: E402
from jaxsync.fem.forces import Preassembled  # noqa: E402
from jaxsync.io import atomic_json  # noqa: E402


def peak_rss_gib() -> float:
    """Peak resident memory of this process so far [GiB] (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20


def machine() -> dict:
    return {"platform": platform.platform(), "cores": os.cpu_count(), "jax": jax.__version__,
            "python": sys.version.split()[0], "load_average": os.getloadavg()[0],
            "devices": f"{jax.device_count()} x {jax.devices()[0].device_kind}"}


def targets(summary: dict) -> dict:
    """The paper vessel's targets, evaluated on a run's summary."""
    m = summary["mass_scaling"]
    q = summary.get("es_hat_tracking") or {}
    interior = summary.get("interior_max_relative_error")
    rows = [r for r in summary["node_errors"] if not r["shared"]]
    oos = summary.get("out_of_sample") or {}
    oos_interior = oos.get("interior_max_relative_error")
    return {
        "train_until_step": summary.get("train_until_step"),
        "out_of_sample_interior_max_relative_error": oos_interior,
        "out_of_sample_monitored_relative_max_error": oos.get("monitored_relative_max_error"),
        "out_of_sample_within_5_percent": (oos_interior is not None and oos_interior <= 0.05
                                           and (oos.get("monitored_relative_max_error") or 0.0) <= 0.05
                                           and len(rows) == summary["n_parts"]),
        "dt_ratio": m["dt_scaled"] / m["dt_cfl"], "added_mass_percent": m["added_mass_percent"],
        "mass_scaling_relative_difference": m["relative_difference"],
        "parts_with_an_interior_node": len(rows), "n_parts": summary["n_parts"],
        "interior_max_relative_error": interior,
        "interior_within_5_percent": interior is not None and interior <= 0.05 and len(rows) == summary["n_parts"],
        "l2_error_max_cm": summary["l2_error_max"],
        "es_max_cm": summary.get("es_max"), "es_hat_max_cm": summary.get("es_hat_max"),
        "es_es_hat_log_correlation": q.get("log_correlation"),
        "resync_tolerance": summary.get("resync_tolerance"),
        "n_resynchronizations": summary.get("n_resynchronizations"),
        "zeta_emulated": summary["zeta"],
        "zeta_projected": {r["interconnect"]["name"]: r["zeta"] for r in summary["projection"]["rows"]},
    }


def run(args) -> dict:
    if args.from_summary:  # a finished ``jaxsync demo --case vessel``: its figures and summary
        import shutil

        with open(args.from_summary) as f:
            summary = json.load(f)
        figures = os.path.join(os.path.dirname(os.path.abspath(args.from_summary)), "report")
        out = os.path.join(args.out, str(summary.get("size", args.size)))
        os.makedirs(out, exist_ok=True)
        for name in sorted(os.listdir(figures)):
            if name.endswith(".png"):
                shutil.copyfile(os.path.join(figures, name), os.path.join(out, name))
    else:
        out = os.path.join(args.out, str(args.size))
        summary = run_demo(out, case="vessel", size=args.size, seed=args.seed, progress=not args.no_progress,
                           force=True)  # a benchmark rerun replaces its own results
    print(format_summary(summary))
    return {"experiment": "paper coronary (section 5.2), generated tree", "mode": "run", "size": args.size,
            "targets": targets(summary), "summary": summary}


def measure(args) -> dict:
    """The paper-size costs, measured, and the whole run projected from them."""
    from jaxsync.perf.timing import speedup_breakdown
    from jaxsync.surrogate import (
        DEFAULT_REFILL_SAMPLES,
        Surrogate,
        TrainConfig,
        build_dataset,
        stack_replicas,
        train_replicas,
    )
    from jaxsync.surrogate.models import LSTMArchitecture

    d = demo_defaults("vessel", args.size)
    record: dict = {"experiment": "paper coronary (section 5.2), generated tree", "mode": "measure",
                    "size": args.size, "defaults": dict(d.__dict__)}
    t0 = time.perf_counter()
    problem_cfl, problem, added = vessel_problem(args.size)
    mesh = problem.mesh
    record["mesh"] = {"n_elements": int(mesh.n_elements), "n_nodes": int(mesh.n_nodes), "n_dofs": 3 * mesh.n_nodes,
                      "seconds": time.perf_counter() - t0, "paper": {"n_elements": 373_435, "n_dofs": 250_659}}
    record["mass_scaling"] = {"dt_cfl": problem_cfl.dt, "dt_scaled": problem.dt, "added_mass_percent": added,
                              "paper": {"dt_cfl": 2.02e-6, "dt_scaled": 5e-6, "added_mass_percent": 21.13}}
    print(f"mesh: {mesh.n_elements} tets, {3 * mesh.n_nodes} dofs ({record['mesh']['seconds']:.1f} s); "
          f"dt {problem_cfl.dt:.3e} -> {problem.dt:.3e} s, +{added:.2f} % mass", flush=True)

    t0 = time.perf_counter()
    parts = jaxsync.partition(mesh, N_PARTS, seed=args.seed)
    shared = np.array([p.n_shared for p in parts.parts])
    record["partition"] = {"seconds": time.perf_counter() - t0, "n_interface": int(parts.n_interface),
                           "shared_nodes_per_part_mean": float(shared.mean()),
                           "shared_dofs_per_part_max": int(3 * shared.max()),
                           "paper": {"shared_nodes_per_part": 262, "shared_dofs_per_part": 786}}
    print(parts.summary(), flush=True)

    n = int(args.prefix_steps)
    # timed steps: the fused product, which the long run takes (a prefix this short would compile the compact one)
    fused = Preassembled(product="fused")
    sync = jaxsync.simulate(problem, n, partitions=parts, save=n, mode=fused,
                            executor=jaxsync.HostExecutor(progress=not args.no_progress))
    single = jaxsync.simulate(problem_cfl, n, save=n, mode=fused,
                              executor=jaxsync.HostExecutor(progress=not args.no_progress))
    record["steps"] = {"prefix_steps": n,
                       "us_per_step_synchronized_11_emulated": sync.stats.us_per_step,
                       "compile_seconds_synchronized": sync.stats.compile_seconds,
                       "us_per_step_single_device_cfl": single.stats.us_per_step}
    print(f"synchronized, {N_PARTS} emulated devices: {sync.stats.us_per_step:.0f} us/step; single device "
          f"(CFL step): {single.stats.us_per_step:.0f} us/step", flush=True)

    # whole programs: one refill cycle of a short stride (the per-step cost of the solver
    # does not depend on n_s; the prediction's share is rescaled to the run's n_s below)
    n_s_timed = 5
    predictor = Surrogate.initialized(parts, n_s_timed, n_hidden=d.n_hidden, n_layers=d.n_layers,
                                      n_past=d.n_past, n_future=d.n_future)
    timing = speedup_breakdown(problem, parts, predictor, repeats=2, stage_repeats=2, prediction_repeats=3)
    # the refill at the run's n_s: n_s applications batched, timed alone for the widest part
    # at both strides; the SPMD prediction of all parts is scaled by their ratio
    widest = int(np.argmax([p.n_shared for p in parts.parts]))
    n_dof = predictor.n_dof

    def refill_seconds(n_s, samples=None):
        """One refill of the widest part: every one of the n_s applications (``samples``
        None: the rate gpu_projection.py reads), or the smooth refill's ``samples``."""
        one = Surrogate.initialized(parts, n_s, n_hidden=d.n_hidden, n_layers=d.n_layers, n_past=d.n_past,
                                    n_future=d.n_future).with_refill_samples(samples).part(widest)
        buffer = np.zeros((n_s * d.n_past, n_dof))
        predict = jax.jit(lambda s, b: s.predict(b, 0))
        predict(one, buffer).block_until_ready()
        best = np.inf
        for _ in range(3):
            start = time.perf_counter()
            predict(one, buffer).block_until_ready()
            best = min(best, time.perf_counter() - start)
        return best

    alone = {n_s_timed: refill_seconds(n_s_timed), d.n_s: refill_seconds(d.n_s)}
    # what the run does: the default smooth refill (DEFAULT_REFILL_SAMPLES network calls)
    default_alone = refill_seconds(d.n_s, DEFAULT_REFILL_SAMPLES)
    t_pred = timing.t_prediction_spmd  # n_s_timed = 5 <= the default samples: every application
    t_pred_run = t_pred * default_alone / alone[n_s_timed]
    us_avoid = 1e6 * (timing.t_step_avoiding - t_pred / (n_s_timed * d.n_future) + t_pred_run / (d.n_s * d.n_future))
    from jaxsync.perf import costmodel

    # one part per processor: its local work and its own refill at the run's n_s
    projection = costmodel.project(timing.synchronized.max_average.t_local, default_alone / (d.n_s * d.n_future),
                                   costmodel.communication_pattern(parts))
    record["programs"] = {"us_per_step": {k: 1e6 * v for k, v in timing.t_step_sync.items()},
                          "us_per_step_nosync": 1e6 * timing.t_step_nosync,
                          "us_per_step_avoiding_at_timed_n_s": 1e6 * timing.t_step_avoiding,
                          "us_per_step_avoiding_at_run_n_s": us_avoid,
                          "prediction_ms_all_parts": 1e3 * t_pred,
                          "refill_seconds_widest_part_alone": {str(k): v for k, v in alone.items()},
                          "refill_seconds_widest_part_alone_default": default_alone,
                          "refill_samples_default": DEFAULT_REFILL_SAMPLES,
                          "prediction_s_all_parts_at_run_n_s": t_pred_run,
                          "prediction_ms_one_part_alone": 1e3 * max(timing.t_prediction),
                          "t_s_us": 1e6 * timing.t_s, "zeta_emulated": timing.zeta,
                          "zeta_emulated_at_run_n_s": 1e6 * timing.t_step_synchronized / us_avoid,
                          "projection": projection.to_dict()}
    print(timing.table(), flush=True)
    print(projection.table(), flush=True)

    # training: the 11 replicas on data of the paper's size (n_steps / n_s samples, the
    # first half used), synthetic smooth histories of each part's width
    rows = d.n_steps // d.n_s + 1
    t = np.linspace(0.0, d.n_steps * problem.dt, rows)[:, None]
    rng = np.random.default_rng(args.seed)
    datasets = []
    for p in parts.parts:
        width = 3 * p.n_shared
        shape = rng.standard_normal(width)[None]
        datasets.append(build_dataset([shape * np.sin(2 * np.pi * t / 0.833) * np.minimum(t, 1.0)], 1,
                                      d.n_past, d.n_future, train_fraction=d.train_fraction))
    data = stack_replicas(datasets)
    arch = LSTMArchitecture(n_dof=data.n_dof_max, n_hidden=d.n_hidden, n_layers=d.n_layers, n_past=d.n_past,
                            n_future=d.n_future)
    epochs = 4
    result = train_replicas(data, arch, TrainConfig(batch_size=d.batch_size, n_epochs=epochs, epochs_per_call=2,
                                                    patience=None),
                            jax.random.key(args.seed), progress=False)
    record["training"] = {"n_dof_max": data.n_dof_max, "n_train_windows": int(data.x_train.shape[1]),
                          "seconds_per_epoch": result.seconds_per_epoch, "compile_seconds": result.compile_seconds,
                          "epochs_default": d.epochs}
    print(f"training: {N_PARTS} replicas of {data.n_dof_max} dofs, {data.x_train.shape[1]} windows each: "
          f"{result.seconds_per_epoch:.2f} s per epoch", flush=True)

    # the whole run projected: mass-scaling check, reference, training, online run
    n_cri = d.n_s * d.n_past
    us_sync = float(sync.stats.us_per_step)
    window = 0.05
    seconds = {
        "mesh_and_partition": record["mesh"]["seconds"] + record["partition"]["seconds"],
        "mass_scaling_check": (window / problem_cfl.dt) * single.stats.us_per_step * 1e-6 * (1 + 1 / 2.5),
        "synchronized_reference": d.n_steps * us_sync * 1e-6,
        "training": d.epochs * result.seconds_per_epoch,
        "online": (n_cri * us_sync + (d.n_steps - n_cri) * us_avoid) * 1e-6,
    }
    seconds["total"] = sum(seconds.values())
    saves = d.n_steps // d.n_s + 1
    memory = {"trajectory_snapshots_gib": 2 * saves * 3 * mesh.n_nodes * 8 / 2 ** 30,
              "synchronized_phase_shared_history_gib": n_cri * 3 * int(shared.sum()) * 8 / 2 ** 30,
              "every_step_shared_history_avoided_gib": d.n_steps * 3 * int(shared.sum()) * 8 / 2 ** 30,
              "refill_history_on_devices_gib": N_PARTS * n_cri * data.n_dof_max * 8 / 2 ** 30,
              "peak_rss_measured_gib": peak_rss_gib()}
    record["projection_of_the_whole_run"] = {"seconds": seconds, "hours": seconds["total"] / 3600,
                                             "memory": memory,
                                             "assumes": "the measured per-step costs hold over the run; the "
                                                        "online run without re-synchronizations"}
    print(f"projected whole run at this size: {seconds['total'] / 3600:.1f} h "
          + ", ".join(f"{k} {v / 3600:.2f} h" for k, v in seconds.items() if k != "total")
          + f"; memory: peak RSS so far {memory['peak_rss_measured_gib']:.2f} GiB, snapshots "
          f"{memory['trajectory_snapshots_gib']:.2f} GiB", flush=True)
    return record


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="small", help="small, paper, or a target tetrahedron count")
    parser.add_argument("--mode", choices=("run", "measure"), default=None,
                        help="run the whole pipeline, or measure the costs and project (default: run at "
                             "small, measure otherwise)")
    parser.add_argument("--prefix-steps", type=int, default=400, help="measure mode: steps of the timed runs")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--from-summary", default=None,
                        help="run mode: evaluate the summary.json of a finished `jaxsync demo --case vessel` "
                             "(and copy its figures) instead of running the pipeline again")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "paper_vessel"))
    args = parser.parse_args(argv)
    mode = args.mode or ("run" if args.size == "small" else "measure")
    started = time.perf_counter()
    record = run(args) if mode == "run" else measure(args)
    record["wall_seconds"] = time.perf_counter() - started
    record["peak_rss_gib"] = peak_rss_gib()
    record["machine"] = machine()
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, f"paper_vessel_{args.size}_{mode}.json")
    atomic_json(path, record)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
