"""Training speed of the LSTM surrogates in the paper's coarse-cantilever configuration.

Configuration (paper section 5.1): two replicas (two parts), n_B = 5, n_H = 100, k = 2
bidirectional encoder layers, n_p = n_f = 20, n_s = 80, 1e5 steps of which the first half
(n_ts = 0.5) feed training, eta0 = 5e-4, gamma = 0.9995, eta_min = 5e-7 (13 812 epochs).
The shared-dof histories are synthetic damped oscillations at the cantilever's time step
(speed does not depend on the values).  Measures gradient steps per second, seconds per
epoch (compilation excluded), one refill call (n_s forwards per replica), and projects the
paper's full schedule.  Prints a table and writes JSON.

    python benchmarks/bench_training.py [--epochs 30] [--n-dof 15 15] [--n-hidden 100] [--batch-size 5]
                                        [--json PATH]

``--n-hidden 50 --batch-size 10`` is the setting in which the paper's published code was
timed at 1.19 s/epoch on this kind of machine (DESIGN.md).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

# Two host devices (one per replica) unless the caller chose otherwise; must precede jax.
if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxsync.surrogate import (  # noqa: E402
    LSTMArchitecture,
    Surrogate,
    TrainConfig,
    build_dataset,
    stack_replicas,
    train_replicas,
)
from jaxsync.surrogate.models import count_parameters  # noqa: E402


def synthetic_history(n_steps: int, n_dof: int, dt: float, seed: int) -> np.ndarray:
    """(n_steps, n_dof) damped oscillations with frequencies near the cantilever's 0.48 Hz."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_steps)[:, None] * dt
    w = 2 * np.pi * rng.uniform(0.4, 3.0, size=(1, n_dof))
    amp = rng.uniform(0.01, 0.08, size=(1, n_dof))
    return amp * (1.0 - np.exp(-0.25 * t) * np.cos(w * t))


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--epochs", type=int, default=30, help="epochs to time (default: %(default)s)")
    parser.add_argument("--epochs-per-call", type=int, default=10, help="epochs per compiled call")
    parser.add_argument("--n-dof", type=int, nargs=2, default=[15, 15],
                        help="shared dofs of the two parts (default: %(default)s)")
    parser.add_argument("--n-hidden", "--hidden", dest="n_hidden", type=int, default=100,
                        help="n_H (default: %(default)s, the paper's)")
    parser.add_argument("--batch-size", type=int, default=5, help="n_B (default: %(default)s, the paper's)")
    parser.add_argument("--devices", type=int, default=None,
                        help="devices to spread the two replicas over (default: all that divide 2)")
    parser.add_argument("--n-steps", type=int, default=100_000, help="steps of the run (default: %(default)s)")
    parser.add_argument("--json", default=os.path.join(os.path.dirname(__file__), "results", "bench_training.json"),
                        help="where to write the results (default: %(default)s)")
    args = parser.parse_args(argv)

    dt, n_s, n_p, n_f = 2.48e-4, 80, 20, 20
    runs = [synthetic_history(args.n_steps, n, dt, seed=p) for p, n in enumerate(args.n_dof)]
    data = stack_replicas([build_dataset([h], n_s, n_p, n_f, train_fraction=0.5) for h in runs])
    arch = LSTMArchitecture(n_dof=data.n_dof_max, n_hidden=args.n_hidden, n_layers=2, n_past=n_p, n_future=n_f)
    paper = TrainConfig(batch_size=5, eta0=5e-4, gamma=0.9995, eta_min=5e-7, n_epochs=None, patience=None)
    config = TrainConfig(batch_size=args.batch_size, eta0=5e-4, gamma=0.9995, eta_min=5e-7, n_epochs=args.epochs,
                         patience=None, epochs_per_call=args.epochs_per_call)
    load_before = os.getloadavg()[0]
    result = train_replicas(data, arch, config, jax.random.key(0), progress=True, description="benchmark",
                            devices=args.devices)

    # One refill call: n_s forwards per replica, both replicas batched (what the online solver does).
    buffer = jnp.asarray(np.stack([np.pad(h[:n_s * n_p], ((0, 0), (0, arch.n_dof - h.shape[1]))) for h in runs]))
    surrogate = Surrogate.from_result(result, n_s)
    predict_all = jax.jit(jax.vmap(lambda one, buf: one.predict(buf, n_s * n_p - 1)))

    def refill():
        return predict_all(surrogate, buffer).block_until_ready()

    refill()
    reps = 20
    start = time.perf_counter()
    for _ in range(reps):
        refill()
    refill_s = (time.perf_counter() - start) / reps

    full_epochs = paper.resolved_epochs
    out = {
        "device": str(jax.devices()[0].device_kind), "cpu_count": os.cpu_count(), "machine": platform.machine(),
        "jax": jax.__version__,
        # Other processes on the machine slow every number down: record how busy it was.
        "load_average_1min_before_after": [load_before, os.getloadavg()[0]],
        "devices_used": args.devices if args.devices else min(2, len(jax.local_devices())),
        "n_hidden": args.n_hidden, "batch_size": args.batch_size, "dof_counts": list(data.dof_counts),
        "n_train_windows": int(data.x_train.shape[1]),
        "n_val_windows": int(data.x_val.shape[1]), "parameters_per_replica": count_parameters(result.params) // 2,
        "steps_per_epoch": result.steps_per_epoch, "epochs_timed": args.epochs,
        "seconds_per_epoch": result.seconds_per_epoch,
        "gradient_steps_per_second": result.steps_per_epoch / result.seconds_per_epoch,
        "compile_seconds": result.compile_seconds,
        "paper_epochs": full_epochs,
        "projected_full_schedule_hours": full_epochs * result.seconds_per_epoch / 3600.0,
        "refill_call_seconds": refill_s,
        "val_loss_first_last": [result.val_loss[0].tolist(), result.val_loss[-1].tolist()],
    }
    rows = [
        ("replicas x dofs", f"2 x {data.dof_counts}"),
        ("n_H, n_B", f"{args.n_hidden}, {args.batch_size}"),
        ("train / val windows", f"{out['n_train_windows']} / {out['n_val_windows']}"),
        ("parameters per replica", f"{out['parameters_per_replica']}"),
        ("gradient steps per epoch", f"{out['steps_per_epoch']}"),
        ("gradient steps / s (both replicas)", f"{out['gradient_steps_per_second']:.1f}"),
        ("seconds / epoch", f"{out['seconds_per_epoch']:.4f}"),
        ("compile seconds", f"{out['compile_seconds']:.1f}"),
        (f"projected {full_epochs} epochs", f"{out['projected_full_schedule_hours']:.2f} h"),
        ("refill call (2 x 80 forwards)", f"{1e3 * refill_s:.2f} ms"),
        ("load average before / after", "{:.2f} / {:.2f}".format(*out["load_average_1min_before_after"])),
    ]
    width = max(len(k) for k, _ in rows)
    print("\nLSTM training, paper cantilever configuration")
    for key, value in rows:
        print(f"  {key:<{width}}  {value}")
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as fh:
        json.dump(out, fh, indent=2)
    print(f"wrote {args.json}")
    return out


if __name__ == "__main__":
    main()
