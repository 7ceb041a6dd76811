"""Error control on a vessel nothing was tuned for: a bifurcating gmsh vessel
(:func:`jaxsync.vessel_mesh`, ``branch=True``) under the paper's pulsatile coronary pressure
(the packaged ``jaxsync/data/coronary.toml``), 4 parts, run through the command line
exactly as a user would, with the library's training defaults.

The pipeline, each step one ``jaxsync`` command:

1. ``jaxsync simulate coronary.toml --mesh vessel.msh --parts 4``: the synchronized run
   (the full field and the shared nodes kept every ``n_s`` steps);
2. ``jaxsync train``: one surrogate per part on the first half of the run, every option
   at its default (``--model lstm``, the default; and ``--model linear``, the baseline);
3. ``jaxsync predict --resync-tolerance 1%``: the synchronization-avoiding run under the
   default error control (the estimate), for each surrogate.

Then, from the two trajectories and independently of the solver's own bookkeeping: the
share of the steps after n_cri that were predicted, and the largest error of any node
of the mesh (the Euclidean norm of its displacement error) over the run and over the
steps after the training half (out of sample), against the tolerance in cm that the run
held. Targets: at least 80 % predicted, the largest nodal error within 2x the tolerance.

Usage:
    python benchmarks/untuned_vessel.py [--size 0.07] [--steps 501000] [--parts 4]
        [--models lstm linear] [--tolerance 1%] [--out benchmarks/results/untuned_vessel]

Prints a table and writes ``<out>/untuned_vessel.json`` (every command line and its
wall time, the mesh, and each model's counts and errors).
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import subprocess
import sys
import time

import numpy as np

CONFIG = os.path.join(os.path.dirname(__file__), os.pardir, "jaxsync", "data", "coronary.toml")
TARGET_PREDICTED = 0.8
TARGET_ERROR_MULTIPLE = 2.0


def command(args: list[str], log: list, cwd: str) -> float:
    """Run one ``jaxsync`` command in ``cwd``; record it and its wall time [s]."""
    line = ["jaxsync", *args]
    print("$ " + " ".join(line), flush=True)
    start = time.perf_counter()
    beside = os.path.join(os.path.dirname(sys.executable), "jaxsync")  # this environment's command
    subprocess.run([beside if os.path.exists(beside) else "jaxsync", *args], cwd=cwd, check=True)
    seconds = time.perf_counter() - start
    log.append({"command": " ".join(line), "seconds": seconds})
    return seconds


def held_tolerance_cm(tolerance: str, surrogate_path: str, reference, stats) -> float | None:
    """The tolerance [cm] ``jaxsync predict --resync-tolerance tolerance`` held the run to:
    a length as given, a percentage of the shared amplitude the surrogate file records
    (:func:`jaxsync.cli.predict.trained_amplitude`, the rule predict applies),
    whether or not any cycle was rejected; the largest the run recorded at its
    re-synchronizations where it followed the amplitude it observed."""
    import dataclasses

    from jaxsync.cli.predict import trained_amplitude
    from jaxsync.solve import ResyncTolerance
    from jaxsync.surrogate import load_surrogate

    held = ResyncTolerance.parse(tolerance)
    if held.relative is not None and held.amplitude is None:
        amplitude = trained_amplitude(load_surrogate(surrogate_path), reference)
        if amplitude is None:  # the run followed its observed amplitude
            return max(float(t) for t in stats.tolerance_cm) if stats.tolerance_cm else None
        held = dataclasses.replace(held, amplitude=amplitude)
    cm = float(held.cm(0.0))
    recorded = [float(t) for t in (stats.tolerance_cm or ())]
    assert all(abs(t - cm) <= 1e-12 * cm for t in recorded), (cm, recorded)  # the run held this one
    return cm


def nodal_errors(ref, onl, train_until_step: int) -> dict:
    """The largest nodal error [cm] of the online run ``onl`` against the reference ``ref``
    (:class:`jaxsync.Trajectory`), over every saved snapshot after n_cri and over those
    after ``train_until_step``."""
    steps_ref = np.rint(np.asarray(ref.times) / float(ref.dt)).astype(int)
    steps_onl = np.rint(np.asarray(onl.times) / float(onl.dt)).astype(int)
    common, i_ref, i_onl = np.intersect1d(steps_ref, steps_onl, return_indices=True)
    error = np.linalg.norm(np.asarray(onl.displacement)[i_onl] - np.asarray(ref.displacement)[i_ref], axis=-1)
    worst = error.max(axis=1)  # (n_common,) the worst node at each snapshot
    n_cri = int(onl.stats.n_cri)
    after_cri, after_training = common > n_cri, common > train_until_step
    amplitude = float(np.linalg.norm(np.asarray(ref.displacement), axis=-1).max())
    return {"snapshots_compared": int(common.size), "amplitude_cm": amplitude,
            "max_nodal_error_cm": float(worst[after_cri].max()) if after_cri.any() else 0.0,
            "max_nodal_error_out_of_sample_cm": (float(worst[after_training].max())
                                                  if after_training.any() else None)}


def run_model(model: str, args, workdir: str, log: list, n_steps: int, mesh: str, reference) -> dict:
    surrogate_dir = f"surrogate_{model}"
    train = ["train", "sync.h5", "-o", surrogate_dir, "--model", model, "--n-s", str(args.n_s), "--seed",
             str(args.seed), "--force"]
    if args.no_progress:
        train.append("--no-progress")
    train_seconds = command(train, log, workdir)
    online = f"online_{model}.h5"
    predict = ["predict", "sync.h5", os.path.join(surrogate_dir, "surrogate.h5"), "--config", CONFIG,
               "--mesh", mesh, "--resync-tolerance", args.tolerance, "-o", online, "--force"]
    if args.no_progress:
        predict.append("--no-progress")
    predict_seconds = command(predict, log, workdir)

    import jaxsync

    trajectory = jaxsync.Trajectory.load(os.path.join(workdir, online))
    stats = trajectory.stats
    after = int(stats.n_steps) - int(stats.n_cri)
    tolerance_cm = held_tolerance_cm(args.tolerance, os.path.join(workdir, surrogate_dir, "surrogate.h5"),
                                     reference, stats)
    train_until = n_steps // 2
    errors = nodal_errors(reference, trajectory, train_until)
    row = {"model": model, "n_steps": int(stats.n_steps), "n_cri": int(stats.n_cri),
           "n_predicted": int(stats.n_predicted_steps), "n_synchronized": int(stats.n_synchronized_steps),
           "predicted_fraction_after_n_cri": int(stats.n_predicted_steps) / after if after else 0.0,
           "n_resynchronizations": int(stats.n_resynchronizations or 0), "tolerance_cm": tolerance_cm,
           "train_seconds": train_seconds, "predict_seconds": predict_seconds,
           "us_per_step_predicted": stats.us_per_step_predicted,
           "us_per_step_synchronized": stats.us_per_step_synchronized, **errors}
    if tolerance_cm:
        row["error_over_tolerance"] = errors["max_nodal_error_cm"] / tolerance_cm
        oos = errors["max_nodal_error_out_of_sample_cm"]
        row["error_over_tolerance_out_of_sample"] = None if oos is None else oos / tolerance_cm
        row["meets_target"] = bool(row["predicted_fraction_after_n_cri"] >= TARGET_PREDICTED
                                   and row["error_over_tolerance"] <= TARGET_ERROR_MULTIPLE)
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=float, default=0.07, help="gmsh target element size [cm] (default 0.07)")
    parser.add_argument("--steps", type=int, default=501_000,
                        help="steps of the run, rounded up to a multiple of 20 n_s (default 501000)")
    parser.add_argument("--parts", type=int, default=4)
    parser.add_argument("--n-s", type=int, default=150, help="the sampling stride the surrogates are trained at "
                                                                "(default: the library's, 150)")
    parser.add_argument("--models", nargs="+", default=["lstm", "linear"])
    parser.add_argument("--tolerance", default="1%")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--keep", action="store_true", help="keep the run's files in <out>/run")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "untuned_vessel"))
    args = parser.parse_args(argv)

    import jax

    import jaxsync
    from jaxsync.io import atomic_json

    cycle = 20 * args.n_s  # n_p n_s = n_f n_s at the library's n_p = n_f = 20
    if args.steps % cycle:
        args.steps += cycle - args.steps % cycle
        print(f"--steps rounded up to {args.steps}, a multiple of n_f n_s = {cycle}", flush=True)
    out = os.path.abspath(args.out)
    workdir = os.path.join(out, "run")
    os.makedirs(workdir, exist_ok=True)
    started = time.perf_counter()
    mesh_path = os.path.join(workdir, "vessel.msh")
    if os.path.exists(mesh_path):
        os.remove(mesh_path)
    mesh = jaxsync.vessel_mesh(mesh_path, branch=True, size=args.size)
    log: list = []
    # the full field and the shared nodes every n_s steps: all that training and the comparison read
    simulate = ["simulate", CONFIG, "--mesh", mesh_path, "--parts", str(args.parts), "--steps", str(args.steps),
                "--save-every", str(args.n_s), "--shared-every", str(args.n_s), "--seed", str(args.seed),
                "-o", "sync.h5", "--force"]
    if args.no_progress:
        simulate.append("--no-progress")
    command(simulate, log, workdir)
    reference = jaxsync.Trajectory.load(os.path.join(workdir, "sync.h5"))
    rows = [run_model(model, args, workdir, log, args.steps, mesh_path, reference) for model in args.models]

    record = {"experiment": "error control on an untuned vessel (bifurcating gmsh vessel, coronary pressure)",
              "mesh": {"generator": f"jaxsync.vessel_mesh(branch=True, size={args.size:g})",
                       "n_elements": int(mesh.n_elements), "n_nodes": int(mesh.n_nodes)},
              "n_parts": args.parts, "n_steps": args.steps, "dt": float(reference.dt),
              "us_per_step_synchronized": reference.stats.us_per_step, "tolerance": args.tolerance,
              "targets": {"predicted_fraction_at_least": TARGET_PREDICTED,
                          "max_nodal_error_over_tolerance_at_most": TARGET_ERROR_MULTIPLE},
              "models": rows, "commands": log, "wall_seconds": time.perf_counter() - started,
              "machine": {"platform": platform.platform(), "cores": os.cpu_count(), "jax": jax.__version__,
                          "python": sys.version.split()[0],
                          "load_average": list(os.getloadavg())}}
    print(f"\nuntuned vessel: {mesh.n_elements} tets, {3 * mesh.n_nodes} dofs, {args.parts} parts, "
          f"{args.steps} steps (dt {float(reference.dt):.3g} s), control at {args.tolerance}")
    print(f"{'model':8} {'predicted':>10} {'resyncs':>8} {'tol [cm]':>10} {'err/tol':>8} {'oos err/tol':>12} "
          f"{'target':>7}")
    for r in rows:
        print(f"{r['model']:8} {100 * r['predicted_fraction_after_n_cri']:9.1f}% {r['n_resynchronizations']:8d} "
              f"{r['tolerance_cm'] or float('nan'):10.3g} {r.get('error_over_tolerance', float('nan')):8.2f} "
              f"{r.get('error_over_tolerance_out_of_sample') or float('nan'):12.2f} "
              f"{'met' if r.get('meets_target') else 'missed':>7}")
    path = os.path.join(out, "untuned_vessel.json")
    atomic_json(path, record)
    print(f"wrote {path}")
    if not args.keep:
        shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
