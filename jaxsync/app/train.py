"""``jaxsync train``: train the per-part LSTM surrogates on distributed trajectory files.

Writes, into the output directory: the checkpoint (``surrogate.h5`` by default), the loss
curves (``loss_curves.png``) and a JSON summary (``train_summary.json``).  Every file is
written under a temporary name and moved into place, so a failed run leaves earlier
results intact.

While it trains, ``training_state.h5`` in the output directory holds a resumable state,
rewritten every ``--checkpoint-every`` epochs: the same command run again continues from
it (and ends with the same parameters as an uninterrupted run); a state of other data or
options is refused.  It is deleted once the results are written.

The defaults are the laptop schedule of :class:`~jaxsync.surrogate.train.TrainConfig`
(n_H = 32, n_B = 5, eta0 = 2e-3, gamma = 0.995, 300 epochs, early stop after 100 epochs
without a better validation loss); the paper's is ``--hidden 100 --eta0 5e-4 --gamma
0.9995 --epochs paper`` (13 812 epochs).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np

from jaxsync.errors import CheckpointError, ConfigError
from jaxsync.trajectory import atomic_path
from jaxsync.surrogate.checkpoint import SurrogateCheckpoint, save_checkpoint
from jaxsync.surrogate.data import build_dataset, read_shared_histories, stack_replicas
from jaxsync.surrogate.evaluate import evaluate_result, max_applications
from jaxsync.surrogate.lstm import LSTMArchitecture, count_parameters
from jaxsync.surrogate.train import TrainConfig, TrainResult, train_replicas

DEFAULTS = TrainConfig()
DEFAULT_HIDDEN = 32
STATE_NAME = "training_state.h5"


def _epochs(text: str) -> int | None:
    """``--epochs`` value: a positive integer, or ``paper`` for the paper's rule (None)."""
    if text.strip().lower() == "paper":
        return None
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer or 'paper', got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"the epoch count must be >= 1, got {value}")
    return value


def _non_negative(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value}")
    return value


def add_train_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``train`` subcommand to an argparse subparsers object.

    ``args.func(args)`` runs it (see :func:`run_train`).
    """
    parser = subparsers.add_parser(
        "train",
        help="train the per-part LSTM surrogates on trajectory files",
        description="Train one LSTM encoder-decoder per part on the shared-dof histories of one or more "
        "distributed trajectory files (saved every step), all parts together.",
    )
    parser.add_argument("trajectories", nargs="+", help="trajectory HDF5 files (one run each, same partition)")
    parser.add_argument("-o", "--output", default="surrogate_out", help="output directory (default: %(default)s)")
    parser.add_argument("--checkpoint-name", default="surrogate.h5",
                        help="checkpoint file name inside the output directory (default: %(default)s)")
    parser.add_argument("--load-parameter", type=float, nargs="+", default=None,
                        help="load parameter alpha_f of each trajectory, in order (default: the files' "
                        "'load_parameter' attribute); needed with --cond-repeat > 0")
    parser.add_argument("--n-s", type=int, default=80, help="sampling stride n_s in steps (default: %(default)s)")
    parser.add_argument("--n-past", type=int, default=20, help="input snapshots n_p (default: %(default)s)")
    parser.add_argument("--n-future", type=int, default=20, help="predicted snapshots n_f (default: %(default)s)")
    parser.add_argument("--train-fraction", type=float, default=0.5,
                        help="leading fraction n_ts of each run used for training (default: %(default)s)")
    parser.add_argument("--val-fraction", type=float, default=0.25,
                        help="fraction of windows held out for validation (default: %(default)s)")
    parser.add_argument("--hidden", type=int, default=DEFAULT_HIDDEN,
                        help="encoder hidden size n_H (default: %(default)s; paper: 100)")
    parser.add_argument("--layers", type=int, default=2, help="bidirectional encoder layers k (default: %(default)s)")
    parser.add_argument("--cond-repeat", type=int, default=0,
                        help="copies q of the load parameter fed to the decoder; 0 = unconditional "
                        "(default: %(default)s; paper: 12)")
    parser.add_argument("--batch-size", type=int, default=DEFAULTS.batch_size,
                        help="mini-batch size n_B (default: %(default)s)")
    parser.add_argument("--eta0", type=float, default=DEFAULTS.eta0,
                        help="initial learning rate (default: %(default)s; paper: 5e-4)")
    parser.add_argument("--gamma", type=float, default=DEFAULTS.gamma,
                        help="per-epoch learning-rate decay (default: %(default)s; paper: 0.9995)")
    parser.add_argument("--eta-min", type=float, default=DEFAULTS.eta_min,
                        help="final learning rate of the paper's epoch rule, used with --epochs paper "
                        "(default: %(default)s)")
    parser.add_argument("--epochs", type=_epochs, default=DEFAULTS.n_epochs, metavar="N|paper",
                        help="largest number of epochs, or 'paper' for the paper's rule "
                        "floor(log_gamma(eta_min/eta0)) (13 812 epochs, about 40 min, with --eta0 5e-4 "
                        "--gamma 0.9995) (default: %(default)s)")
    parser.add_argument("--patience", type=_non_negative, default=DEFAULTS.patience,
                        help="stop when no part's validation loss has improved for this many epochs; "
                        "0 never stops early; each part keeps the parameters of its best epoch either way "
                        "(default: %(default)s)")
    parser.add_argument("--epochs-per-call", type=int, default=DEFAULTS.epochs_per_call,
                        help="epochs per compiled call between progress updates (default: %(default)s)")
    parser.add_argument("--checkpoint-every", type=_non_negative, default=50, metavar="N",
                        help=f"write the resumable training state {STATE_NAME} into the output directory "
                        "every N epochs; rerunning the same command resumes from it; 0 disables it "
                        "(default: %(default)s)")
    parser.add_argument("--allow-predicted", action="store_true",
                        help="accept synchronization-avoiding (jaxsync predict) trajectories, whose shared "
                        "dofs were partly predicted by surrogates, as training data (refused by default)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of initialization, shuffling and the train/validation split (default: %(default)s)")
    parser.add_argument("--emse-applications", type=int, default=60,
                        help="refill cycles N for the E_mse of the summary, clipped to what the first "
                        "trajectory holds; 0 skips it (default: %(default)s)")
    parser.add_argument("--devices", type=int, default=None,
                        help="local devices to spread the parts over (default: as many as divide the part count)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.set_defaults(func=run_train)
    return parser


def _load_runs(args):
    runs = [read_shared_histories(path, allow_predicted=args.allow_predicted) for path in args.trajectories]
    first = runs[0]
    for path, run in zip(args.trajectories[1:], runs[1:]):
        same = len(run.shared_nodes) == len(first.shared_nodes) and all(
            np.array_equal(a, b) for a, b in zip(run.shared_nodes, first.shared_nodes)
        )
        if not same:
            raise CheckpointError(
                f"{path} belongs to another partition than {args.trajectories[0]} (different shared nodes); "
                "train on runs of one partition"
            )
    if args.load_parameter is not None:
        if len(args.load_parameter) != len(runs):
            raise ConfigError(
                f"--load-parameter got {len(args.load_parameter)} values for {len(runs)} trajectories; give one each"
            )
        loads = list(args.load_parameter)
    elif all(run.load_parameter is not None for run in runs):
        loads = [run.load_parameter for run in runs]
    else:
        loads = None
    if args.cond_repeat > 0 and loads is None:
        raise ConfigError(
            "--cond-repeat > 0 trains the conditional network, which needs a load parameter per trajectory: "
            "pass --load-parameter or store a 'load_parameter' attribute in the files"
        )
    return runs, (loads if args.cond_repeat > 0 else None)


def _atomic_write_text(path: str, text: str) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "w") as fh:
            fh.write(text)


def plot_loss_curves(result: TrainResult, path: str) -> None:
    """Write the per-part training and validation loss curves to a PNG (atomically), with
    each part's best epoch (the parameters kept) and the early stop marked."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    fig = Figure(figsize=(7, 4.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    epochs = np.arange(1, result.train_loss.shape[0] + 1)
    best = result.best_epoch
    for p in range(result.train_loss.shape[1]):
        line, = ax.semilogy(epochs, result.train_loss[:, p], label=f"part {p} train")
        ax.semilogy(epochs, result.val_loss[:, p], "--", color=line.get_color(), label=f"part {p} validation")
        if best is not None:
            ax.semilogy([best[p]], [result.val_loss[best[p] - 1, p]], "o", color=line.get_color(), mfc="none",
                        label=f"part {p} best epoch ({best[p]}, kept)")
    if result.stopped_epoch is not None:
        ax.axvline(result.stopped_epoch, color="0.3", ls=":", lw=1.0,
                   label=f"early stop (epoch {result.stopped_epoch})")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("epoch")
    ax.set_ylabel("MSE of normalized displacements [-]")
    ax.set_title(f"Training of {result.train_loss.shape[1]} LSTM replicas (one per part)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")


def run_train(args: argparse.Namespace) -> int:
    """Run ``jaxsync train`` with parsed arguments; returns the exit status 0.

    Raises:
        ConfigError, CheckpointError: unusable options or trajectory files.
    """
    runs, loads = _load_runs(args)
    n_parts = len(runs[0].histories)
    datasets = [
        build_dataset([run.histories[p] for run in runs], args.n_s, args.n_past, args.n_future,
                      args.train_fraction, args.val_fraction, args.seed, loads)
        for p in range(n_parts)
    ]
    data = stack_replicas(datasets)
    arch = LSTMArchitecture(n_dof=data.n_dof_max, n_hidden=args.hidden, n_layers=args.layers,
                            n_past=args.n_past, n_future=args.n_future, n_cond_repeat=args.cond_repeat)
    config = TrainConfig(batch_size=args.batch_size, eta0=args.eta0, gamma=args.gamma, eta_min=args.eta_min,
                         n_epochs=args.epochs, epochs_per_call=args.epochs_per_call,
                         patience=args.patience or None)
    os.makedirs(args.output, exist_ok=True)
    state_path = os.path.join(args.output, STATE_NAME) if args.checkpoint_every else None
    if state_path is not None and os.path.exists(state_path):
        print(f"resuming from the training state {state_path}")
    started = time.perf_counter()
    result = train_replicas(data, arch, config, jax.random.key(args.seed), progress=not args.no_progress,
                            devices=args.devices, checkpoint=state_path, checkpoint_every=args.checkpoint_every)
    train_seconds = time.perf_counter() - started

    first = runs[0]
    n_app = min(args.emse_applications,
                max_applications(first.histories[0].shape[0], args.n_s, args.n_past, args.n_future))
    sqrt_e_mse = None
    if n_app > 0:
        histories = np.stack([np.pad(h, ((0, 0), (0, arch.n_dof - h.shape[1]))) for h in first.histories])
        err = evaluate_result(result, histories, args.n_s, n_app, cond=None if loads is None else loads[0])
        sqrt_e_mse = [float(v) for v in np.sqrt(err)]

    summary = {
        "trajectories": [os.path.abspath(p) for p in args.trajectories],
        "load_parameters": loads,
        "n_parts": n_parts,
        "dof_counts": list(result.dof_counts),
        "architecture": arch.to_dict(),
        "parameters_per_replica_padded": count_parameters(result.params) // n_parts,
        "training": {**config.to_dict(), "n_epochs_run": result.n_epochs_run,
                     "stopped_early": result.stopped_epoch is not None, "stopped_at_epoch": result.stopped_epoch,
                     "best_epoch": [int(e) for e in result.best_epoch],
                     "resumed_from_epoch": result.resumed_from, "checkpoint_every": args.checkpoint_every},
        "sampling": {"n_s": args.n_s, "train_fraction": args.train_fraction, "val_fraction": args.val_fraction,
                     "seed": args.seed, "n_train_windows": int(data.x_train.shape[1]),
                     "n_val_windows": int(data.x_val.shape[1])},
        "initial_val_loss": result.initial_val_loss.tolist(),
        "final_train_loss": result.train_loss[-1].tolist(),
        "final_val_loss": result.best_val_loss.tolist(),
        "last_epoch_val_loss": result.val_loss[-1].tolist(),
        "n_epochs_run": result.n_epochs_run,
        "stopped_at_epoch": result.stopped_epoch,
        "seconds_per_epoch": result.seconds_per_epoch,
        "gradient_steps_per_second": (result.steps_per_epoch / result.seconds_per_epoch
                                      if result.seconds_per_epoch > 0 else None),
        "compile_seconds": result.compile_seconds,
        "train_seconds": train_seconds,
        "e_mse_applications": n_app if sqrt_e_mse is not None else None,
        "sqrt_e_mse": sqrt_e_mse,
    }
    checkpoint_path = os.path.join(args.output, args.checkpoint_name)
    ckpt = SurrogateCheckpoint.from_result(
        result, args.n_s, first.shared_nodes,
        metadata={k: summary[k] for k in ("training", "sampling", "load_parameters", "final_val_loss", "sqrt_e_mse")},
    )
    save_checkpoint(checkpoint_path, ckpt)
    plot_path = os.path.join(args.output, "loss_curves.png")
    plot_loss_curves(result, plot_path)
    summary.update(checkpoint=os.path.abspath(checkpoint_path), loss_curves=os.path.abspath(plot_path),
                   loss_history={"train": result.train_loss.tolist(), "val": result.val_loss.tolist()})
    _atomic_write_text(os.path.join(args.output, "train_summary.json"), json.dumps(summary, indent=2))
    if state_path is not None and os.path.exists(state_path):
        os.remove(state_path)  # everything it could resume is written
    stop = (f"stopped early at epoch {result.stopped_epoch}" if result.stopped_epoch is not None
            else f"{result.n_epochs_run} epochs")
    print(f"wrote {checkpoint_path}, {plot_path} and train_summary.json ({stop}); "
          f"validation MSE of the kept parameters per part: {', '.join(f'{v:.3e}' for v in result.best_val_loss)} "
          f"(best epochs {', '.join(str(int(e)) for e in result.best_epoch)})")
    return 0


__all__ = ["add_train_parser", "run_train", "plot_loss_curves"]
