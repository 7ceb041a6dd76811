"""The end-to-end demonstration behind ``jaxsync demo``.

On the built-in coarse cantilever split into parts: (1) a synchronized distributed run
saved at every step, (2) training of one LSTM surrogate per part on the first half of it
(:func:`jaxsync.surrogate.train_surrogates`, as ``jaxsync train``), (3) the
synchronization-avoiding run from n_cri = n_s n_p on (98 400 of 1e5 steps predicted, as
in the paper), (4) the report (figures, ``summary.json``). The defaults follow the
paper's sampling (n_s = 80, n_p = n_f = 20, 1e5 steps) with a smaller network
(n_H = 32) and a short schedule (300 epochs), which finishes in about 2-3 minutes on a
2-core laptop; every size is an argument. The full field is saved every ``save_every``
steps (default n_s) and each part's shared nodes at every step (the training data), so
the files stay small (a few MB instead of 380 MB).
"""

from __future__ import annotations

import os
import time

import numpy as np

from ..surrogate.lstm import LSTMArchitecture
from ..surrogate.train import TrainConfig

__all__ = ["run_demo", "SUMMARY_KEYS"]

SUMMARY_KEYS = ("n_steps", "n_synchronized", "n_predicted", "tip_max_abs_error",
                "tip_max_abs_displacement", "l2_error_final", "us_per_step_synchronized",
                "us_per_step_predicted", "speedup", "zeta", "t_s_us", "t_d_us", "n_devices",
                "device_kind")


def run_demo(out: str, *, n_steps: int = 100000, n_parts: int = 2, n_s: int = 80,
             n_past: int = LSTMArchitecture.n_past, n_future: int = LSTMArchitecture.n_future,
             n_hidden: int = LSTMArchitecture.n_hidden, n_layers: int = LSTMArchitecture.n_layers,
             epochs: int = TrainConfig.n_epochs, batch_size: int = TrainConfig.batch_size,
             eta0: float = TrainConfig.eta0, gamma: float = TrainConfig.gamma, seed: int = 0,
             save_every: int | None = None, resync_tolerance=None, progress: bool = True,
             log=print) -> dict:
    """Run the pipeline; write everything into ``out`` and return the summary. The
    surrogate sizes and schedule default to those of
    :class:`~jaxsync.surrogate.lstm.LSTMArchitecture` and
    :class:`~jaxsync.surrogate.train.TrainConfig` (the laptop schedule).

    Files: ``synchronized.h5`` (reference every ``save_every`` steps, per-part shared
    histories every step),
    ``surrogate/`` (checkpoint, loss curves, training summary), ``online.h5`` (the
    synchronization-avoiding run), ``report/`` (figures) and ``summary.json``.
    """
    from .. import cantilever, partition, simulate
    from ..io import atomic_json
    from ..solve.syncavoid import describe_run, simulate_sync_avoiding
    from ..surrogate.fit import train_surrogates
    from .plots import write_report

    os.makedirs(out, exist_ok=True)
    problem = cantilever()
    parts = partition(problem.mesh, n_parts, seed=seed)
    log(parts.summary())
    started = time.perf_counter()

    from ..parallel.devices import device_summary

    save_every = n_s if save_every is None else int(save_every)
    devices = device_summary()
    log(f"[1/4] synchronized run: {n_steps} steps, dt = {problem.dt:.4e} s, on {devices['n_devices']} "
        f"{devices['device_kind']} device(s){' (emulated)' if devices['emulated'] else ''}")
    reference = simulate(problem, n_steps, partitions=parts, progress=progress, save_every=save_every,
                         shared_every=1)
    reference_path = os.path.join(out, "synchronized.h5")
    reference.save(reference_path)

    log(f"[2/4] training {n_parts} LSTM replicas (n_s={n_s}, n_p={n_past}, n_f={n_future}, "
        f"n_H={n_hidden}, {epochs} epochs)")
    trained = train_surrogates(
        reference_path, n_s=n_s, n_past=n_past, n_future=n_future, n_hidden=n_hidden, n_layers=n_layers,
        config=TrainConfig(batch_size=batch_size, eta0=eta0, gamma=gamma, n_epochs=epochs), seed=seed,
        emse_applications=0, out=os.path.join(out, "surrogate"), progress=progress)
    log(f"  {trained.result.n_epochs_run} epochs in {trained.train_seconds:.1f} s; validation MSE per part "
        + ", ".join(f"{v:.3e}" for v in trained.final_val_loss) + f"; wrote {trained.files['checkpoint']}")

    n_cri = n_s * n_past
    log(f"[3/4] synchronization-avoiding run: synchronized to step {n_cri}, then predicted"
        + (f", error control at es_hat <= {resync_tolerance}" if resync_tolerance is not None else ""))
    online = simulate_sync_avoiding(problem, n_steps, partitions=parts, surrogates=trained.checkpoint,
                                    n_cri=n_cri, progress=progress, save_every=save_every,
                                    resync_tolerance=resync_tolerance)
    online.save(os.path.join(out, "online.h5"))
    log("  " + describe_run(online))

    log("[4/4] timing (compiled programs, round-robin) and report")
    from ..perf.timing import speedup_breakdown

    timing = speedup_breakdown(problem, parts, trained.surrogate, repeats=3, stage_repeats=10)
    us_sync = float(reference.stats.us_per_step)
    us_pred = float(online.stats.us_per_step_predicted)
    extra = {"us_per_step_synchronized": us_sync, "us_per_step_predicted": us_pred,
             "speedup": us_sync / us_pred, "zeta": timing.zeta, "zeta_sync": timing.sync,
             "t_s_us": 1e6 * timing.t_s, "t_d_us": 1e6 * timing.t_d, "dt": problem.dt,
             "training_seconds": trained.train_seconds,
             "final_val_loss": trained.final_val_loss.tolist(),
             "n_devices": devices["n_devices"], "device_kind": devices["device_kind"],
             "devices_emulated": devices["emulated"],
             "compile_seconds": reference.stats.compile_seconds + online.stats.compile_seconds,
             "save_every": save_every,
             **{k: v for k, v in online.stats.to_dict().items()
                if k in ("n_synchronized_steps", "n_predicted_steps", "n_discarded_steps",
                         "n_resynchronizations")},
             "wall_seconds": time.perf_counter() - started}
    fixed_nodes = np.unique(problem.dirichlet_dofs()[0] // 3)
    summary = write_report(reference, online, parts, os.path.join(out, "report"),
                           fixed_nodes=fixed_nodes, extra=extra)
    summary["report"] = os.path.abspath(os.path.join(out, "report"))
    atomic_json(os.path.join(out, "summary.json"), summary)
    return summary


def format_summary(summary: dict) -> str:
    """The demo's summary table."""
    rows = [
        ("steps", f"{summary['n_steps']}"),
        ("synchronized / predicted", f"{summary['n_synchronized']} / {summary['n_predicted']}"),
        (f"node {summary.get('monitored_node', '')} z: max |error|",
         f"{summary['tip_max_abs_error']:.3e} cm "
         f"({100 * summary['tip_max_abs_error'] / summary['tip_max_abs_displacement']:.2f} % of its largest "
         "amplitude; the monitored node that moves most)"),
        (f"node {summary.get('monitored_node', '')} z: largest |d|", f"{summary['tip_max_abs_displacement']:.3e} cm"),
        ("e_l2 at the end", f"{summary['l2_error_final']:.3e} cm"),
        ("devices", f"{summary['n_devices']} x {summary['device_kind']}"
                    + (" (emulated in one process, sharing the CPU cores)" if summary.get("devices_emulated") else "")),
        ("time per step, synchronized", f"{summary['us_per_step_synchronized']:.1f} us"),
        ("time per step, predicted", f"{summary['us_per_step_predicted']:.1f} us"),
        ("speed-up, end to end", f"{summary['speedup']:.2f}x (compiled chunks; compilation "
                                 f"{summary.get('compile_seconds', 0.0):.1f} s not included)"),
        ("zeta, compiled steps", f"{summary['zeta']:.2f}x against the {summary.get('zeta_sync', '')} "
                                 f"baseline (jaxsync.perf.timing.speedup_breakdown): synchronization "
                                 f"{summary['t_s_us']:.1f} us/step, surrogate {summary['t_d_us']:.1f} us/step"),
        ("figures", summary.get("report", "")),
    ]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{width}}  {v}" for k, v in rows)


