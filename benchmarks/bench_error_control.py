"""Error control (paper section 6 and beyond): does a re-synchronization tolerance ever make
a run worse, what does it cost, and how well does es_hat track es?

On the demo's case (coarse cantilever, 2 parts, 1e5 steps, the surrogate ``jaxsync demo``
trains), the synchronization-avoiding run is repeated without a tolerance and with
tolerances in cm and relative to the observed amplitude, each held by the default
indicator (es_hat and the estimated error) and by es_hat alone. For each: the
largest error over all nodes and saved steps against the synchronized run, e_l2 at the end,
the steps synchronized / predicted / recomputed, the re-synchronizations, the time per
predicted step, and how well es_hat tracks es (:func:`jaxsync.metrics.estimate_quality`).

Usage: python benchmarks/bench_error_control.py [--demo jaxsync-demo] [--steps 100000]
       [--tolerances none 1e-2 1e-3 ...] [--indicators estimate es_hat]
       [--out benchmarks/results/error_control.json]
(runs ``jaxsync demo`` into --demo first when its files are missing).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
import warnings

import jax

import jaxsync

jaxsync.parallel.devices.request_cpu_devices(2)  # one emulated device per part, before JAX starts
jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jaxsync.metrics import estimate_quality, l2_error, predictions_by_node, shared_node_errors  # noqa: E402
from jaxsync.parallel import partition_of  # noqa: E402
from jaxsync.solve import ResyncTolerance, simulate_sync_avoiding  # noqa: E402
from jaxsync.surrogate import load_surrogate  # noqa: E402

DEFAULT_TOLERANCES = ["none", "1e-2", "1e-3", "3e-4", "1e-4", "3e-5", "1e-5", "10%", "1%", "0.1%"]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demo", default="jaxsync-demo", help="folder of a jaxsync demo run")
    parser.add_argument("--steps", type=int, default=None, help="steps (default: the demo's)")
    parser.add_argument("--tolerances", nargs="+", default=DEFAULT_TOLERANCES)
    parser.add_argument("--indicators", nargs="+", default=["estimate", "es_hat"], choices=["estimate", "es_hat"],
                        help="what each tolerance holds (ResyncTolerance.indicator)")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results",
                                                       "error_control.json"))
    args = parser.parse_args(argv)
    reference_path = os.path.join(args.demo, "synchronized.h5")
    checkpoint = os.path.join(args.demo, "surrogate", "surrogate.h5")
    if not (os.path.exists(reference_path) and os.path.exists(checkpoint)):
        from jaxsync.app.demo import run_demo

        run_demo(args.demo, force=True)
    reference = jaxsync.Trajectory.load(reference_path)
    parts = partition_of(reference)
    problem = jaxsync.cantilever()
    n_steps = args.steps or int(round(reference.times[-1] / reference.dt))
    ckpt = load_surrogate(checkpoint)
    n_cri = ckpt.n_s * ckpt.arch.n_past
    every = reference.save_every
    truth = np.asarray(reference.displacement[:n_steps // every + 1])
    rows = []
    runs = [(tol, None) if tol == "none" else (tol, indicator) for tol in args.tolerances
            for indicator in (["-"] if tol == "none" else args.indicators)]
    for tol, indicator in runs:
        start = time.perf_counter()
        tolerance = None if tol == "none" else dataclasses.replace(ResyncTolerance.parse(tol), indicator=indicator)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RuntimeWarning)
            online = simulate_sync_avoiding(problem, n_steps, partitions=parts, surrogates=ckpt, n_cri=n_cri,
                                            save=every, executor=jaxsync.HostExecutor(progress=False),
                                            resync_tolerance=tolerance)
        wall = time.perf_counter() - start
        err = np.abs(online.displacement - truth)
        st = online.stats
        row = {"tolerance": tol, "indicator": indicator, "max_abs_error_cm": float(err.max()),
               "l2_error_final_cm": float(l2_error(truth, online.displacement)[-1]),
               "n_synchronized_steps": st.n_synchronized_steps,
               "n_predicted_steps": st.n_predicted_steps,
               "n_discarded_steps": (st.n_discarded_steps or 0),
               "n_resynchronizations": (st.n_resynchronizations or 0),
               "us_per_step_predicted": st.us_per_step_predicted,
               "us_per_step_synchronized": st.us_per_step_synchronized,
               "wall_seconds": wall, "warning": [str(w.message) for w in caught]}
        predictions, holds, steps = predictions_by_node(online, parts)
        if len(steps):
            errs = shared_node_errors(truth[steps][:, parts.shared_nodes], predictions, holds)
            row["es_hat_tracking"] = estimate_quality(errs.es, errs.es_hat).to_dict()
        rows.append(row)
        print(f"{tol:>6} {indicator or '':>8}: max |error| {row['max_abs_error_cm']:.3e} cm, synchronized "
              f"{row['n_synchronized_steps']}, predicted {row['n_predicted_steps']}, recomputed "
              f"{row['n_discarded_steps']}, re-synchronizations {row['n_resynchronizations']}, "
              f"{wall:.1f} s", flush=True)
    free = rows[0]["max_abs_error_cm"] if args.tolerances[0] == "none" else None
    print()
    print(f"{'tolerance':>9} {'indicator':>9} {'max|err| cm':>12} {'vs none':>8} {'synced':>7} {'predicted':>9} "
          f"{'recomputed':>10} {'resyncs':>7} {'us/pred':>8} {'es/es_hat med':>13} {'p95':>8}")
    for r in rows:
        tr = r.get("es_hat_tracking", {})
        ratio = f"{r['max_abs_error_cm'] / free:.3f}" if free else "-"
        print(f"{r['tolerance']:>9} {r['indicator'] or '':>9} {r['max_abs_error_cm']:>12.3e} {ratio:>8} "
              f"{r['n_synchronized_steps']:>7} "
              f"{r['n_predicted_steps']:>9} {r['n_discarded_steps']:>10} {r['n_resynchronizations']:>7} "
              f"{(r['us_per_step_predicted'] or 0):>8.1f} {tr.get('ratio_median', float('nan')):>13.3g} "
              f"{tr.get('ratio_p95', float('nan')):>8.3g}")
    from jaxsync.parallel.devices import device_summary

    result = {"case": "demo cantilever, 2 parts", "n_steps": n_steps, "n_cri": n_cri,
              "save_every": every, "surrogate": checkpoint, "machine": platform.machine(),
              "cpu_count": os.cpu_count(), **device_summary(), "date": time.strftime("%Y-%m-%d"),
              "rows": rows}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=2)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
