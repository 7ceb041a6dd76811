"""``jaxsync train``: train the per-part LSTM surrogates on distributed trajectory files
(``--model linear``: fit the linear autoregressive baseline by least squares instead).

Argument parsing and printing around :func:`jaxsync.surrogate.train_surrogates` and
:meth:`~jaxsync.surrogate.TrainedSurrogates.write`, which writes, into the output
directory: the surrogate file (``surrogate.h5`` by default, ``--surrogate-name``), the loss
curves (``loss_curves.png``) and a JSON summary (``train_summary.json``).  Every file is
written under a temporary name and moved into place, so a failed run leaves earlier
results intact.

While it trains, ``training_state.h5`` in the output directory holds a resumable state,
rewritten every ``--state-every`` epochs (:class:`~jaxsync.surrogate.TrainingState`): the
same command run again continues from it (and ends with the same parameters as an
uninterrupted run); a state of other data or options is refused.  It is deleted once the
results are written.

Every default is the library's, read from its settings dataclasses
(:class:`~jaxsync.surrogate.ArchitectureChoice`, :class:`~jaxsync.surrogate.Sampling`,
:class:`~jaxsync.surrogate.TrainConfig`, :class:`~jaxsync.surrogate.TrainingChecks`,
:class:`~jaxsync.surrogate.TrainingState`): the laptop schedule of
:class:`~jaxsync.surrogate.training.TrainConfig`
(n_H = 50, n_B = 10, eta0 = 2e-3, gamma = 0.995, 800 epochs, early stop after 200 epochs
without a better validation loss); the paper's is ``--n-hidden 100 --batch-size 5 --eta0 5e-4 --gamma
0.9995 --epochs paper`` (13 812 epochs).  ``--model linear`` fits the affine map of least
squares on the same windows (:mod:`jaxsync.surrogate.models`, ridge ``--regularization``);
it writes the same files, and the optimization options do not apply to it. ``--model``
also names any model registered with :func:`jaxsync.surrogate.register_surrogate` before
the parser is built (:mod:`jaxsync.surrogate.models`): it takes the options of the names
of its hyperparameters (``--n-hidden``, ``--n-layers``, ``--cond-repeat``).
"""

from __future__ import annotations

import argparse
import os

from jaxsync.options import EpochRule, LoadJumpWindows, ValidationSplit, choices
from jaxsync.surrogate.models._architecture import ArchitectureChoice
from jaxsync.surrogate.models._registry import surrogate_kinds
from jaxsync.surrogate.training._data import Sampling
from jaxsync.surrogate.training._evaluate import TrainingChecks
from jaxsync.surrogate.training._fit import LOSS_CURVES_NAME, SUMMARY_NAME, SURROGATE_NAME, train_surrogates
from jaxsync.surrogate.training._train import TrainConfig
from jaxsync.surrogate.training._training_state import STATE_NAME, TrainingState

# the defaults are those of the library's settings
ARCHITECTURE, SAMPLING, DEFAULTS, CHECKS = ArchitectureChoice(), Sampling(), TrainConfig(), TrainingChecks()


def _non_negative(text: str) -> int:
    """An integer >= 0 (``--patience``, ``--state-every``)."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return value


def _epochs(text: str) -> int | None:
    """``--epochs`` value: a positive integer, or an :data:`~jaxsync.options.EpochRule`
    (``paper``: the paper's rule, None)."""
    if text.strip().lower() in choices(EpochRule):
        return None
    try:
        if _non_negative(text) >= 1:
            return int(text)
    except argparse.ArgumentTypeError:
        pass
    rules = " or ".join(repr(r) for r in choices(EpochRule))
    raise argparse.ArgumentTypeError(f"expected a positive integer or {rules}, got {text!r}")


def add_train_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``train`` subcommand to an argparse subparsers object.

    ``args.func(args)`` runs it (see :func:`run_train`).
    """
    parser = subparsers.add_parser(
        "train",
        help="train the per-part LSTM surrogates on trajectory files",
        description="Train one LSTM encoder-decoder per part on the shared-dof histories of one or more "
        "distributed trajectory files (shared nodes kept at a stride dividing n_s), all parts together "
        "(--model linear: fit the linear autoregressive baseline by least squares instead).",
    )
    parser.add_argument("trajectories", nargs="+", help="trajectory HDF5 files (one run each, same partition)")
    parser.add_argument("-o", "--output", default="surrogate_out", help="output directory (default: %(default)s)")
    parser.add_argument("--model", choices=surrogate_kinds(), default=ARCHITECTURE.model,
                        help="the surrogate: the LSTM encoder-decoder, or the linear autoregressive baseline "
                        "fitted by least squares on the same windows (unconditional; the optimization options "
                        "do not apply to it), or a model registered with jaxsync.surrogate.register_surrogate "
                        "before the parser was built (default: %(default)s)")
    parser.add_argument("--regularization", type=float, default=ARCHITECTURE.regularization, metavar="R",
                        help="--model linear: ridge parameter relative to the largest squared singular value of "
                        "the training inputs; 0 is plain least squares (default: %(default)s)")
    parser.add_argument("--surrogate-name", dest="surrogate_name", default=SURROGATE_NAME,
                        help="name of the surrogate file (the trained networks) inside the output directory "
                        "(default: %(default)s)")
    parser.add_argument("--load-parameter", type=float, nargs="+", default=None,
                        help="the condition of each trajectory, in order: its load parameter alpha_f, an "
                        "initial-condition label, any scalar that tells the runs apart (default: the "
                        "trajectories' 'load_parameter', which jaxsync.ensemble(labels=...) stores); needed "
                        "with --cond-repeat > 0")
    parser.add_argument("--n-s", type=int, default=SAMPLING.n_s,
                        help="sampling stride n_s in steps (default: %(default)s)")
    parser.add_argument("--n-past", type=int, default=SAMPLING.n_past,
                        help="input snapshots n_p (default: %(default)s)")
    parser.add_argument("--n-future", type=int, default=SAMPLING.n_future,
                        help="predicted snapshots n_f (default: %(default)s)")
    parser.add_argument("--offsets", dest="n_offsets", type=int, default=SAMPLING.n_offsets,
                        help="sampled sequences taken from each run, at evenly spaced starting steps within n_s "
                        "(more windows of the same run; default: %(default)s)")
    parser.add_argument("--candidates", dest="n_candidates", type=int, default=DEFAULTS.n_candidates,
                        help="networks trained per part from different initial weights, all at once; each "
                        "part keeps the one of lowest validation loss (default: %(default)s)")
    parser.add_argument("--train-fraction", type=float, default=SAMPLING.train_fraction,
                        help="leading fraction n_ts of each run used for training (default: %(default)s)")
    parser.add_argument("--val-fraction", type=float, default=SAMPLING.val_fraction,
                        help="fraction of windows held out for validation (default: %(default)s)")
    parser.add_argument("--split", choices=choices(ValidationSplit), default=SAMPLING.split,
                        help="which windows are held out for validation: every 4th (interleaved, at the default "
                        "fraction) or a seeded random subset (the paper's) (default: %(default)s)")
    parser.add_argument("--load-jump-windows", choices=choices(LoadJumpWindows), default=SAMPLING.load_jump_windows,
                        help="leave out, or keep, the windows that straddle a load jump the trajectory "
                        "records (a load switched off); an online run stays synchronized through jumps by "
                        "default, and needs them kept to predict through one (default: exclude for "
                        "--model linear, whose fit they bend; keep for the LSTM)")
    parser.add_argument("--n-hidden", "--hidden", dest="n_hidden", type=int, default=ARCHITECTURE.n_hidden,
                        help="encoder hidden size n_H (default: %(default)s; paper: 100)")
    parser.add_argument("--n-layers", "--layers", dest="n_layers", type=int, default=ARCHITECTURE.n_layers,
                        help="bidirectional encoder layers k (default: %(default)s)")
    parser.add_argument("--load-input", dest="load_input", action=argparse.BooleanOptionalAction,
                        default=ARCHITECTURE.load_input,
                        help="feed the surrogates the known load signals (the time functions of the problem's "
                        "loads and prescribed motions over the past and predicted windows; the linear model "
                        "becomes ARX). Default: on when the trajectories record them (every run of jaxsync "
                        "simulate does), off for files written before; --load-input requires them, "
                        "--no-load-input trains the load-blind model")
    parser.add_argument("--highway", action=argparse.BooleanOptionalAction, default=ARCHITECTURE.highway,
                        help="give the LSTM a linear autoregressive highway: the least-squares affine map of the "
                        "window (the linear model, ARX with the load input) plus what the decoder learns on "
                        "top, trained from that fit (default: on for the LSTM; --no-highway trains the paper's "
                        "network)")
    parser.add_argument("--cond-repeat", type=int, default=ARCHITECTURE.n_cond_repeat,
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
    parser.add_argument("--state-every", type=_non_negative, default=TrainingState.every, metavar="N",
                        help=f"write the resumable training state {STATE_NAME} into the output directory "
                        "every N epochs; rerunning the same command resumes from it; 0 disables it "
                        "(default: %(default)s)")
    parser.add_argument("--allow-predicted", action="store_true",
                        help="accept synchronization-avoiding (jaxsync predict) trajectories, whose shared "
                        "dofs were partly predicted by surrogates, as training data (refused by default)")
    parser.add_argument("--seed", type=int, default=SAMPLING.seed,
                        help="seed of initialization, shuffling and the train/validation split (default: %(default)s)")
    parser.add_argument("--emse-applications", type=int, default=CHECKS.emse_applications,
                        help="refill cycles N for the E_mse of the summary, clipped to what the first "
                        "trajectory holds; 0 skips it (default: %(default)s)")
    parser.add_argument("--rollout-tolerance", type=float, default=CHECKS.rollout_tolerance, metavar="FRACTION",
                        help="offline check after training: warn when a part's autonomous rollout over the first "
                        "trajectory is off by more than this fraction of its shared amplitude; 0 skips it "
                        "(default: %(default)s)")
    parser.add_argument("--devices", type=int, default=None,
                        help="local devices to spread the parts over (default: as many as divide the part count)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("--force", action="store_true",
                        help="replace the surrogate file, loss curves and summary of an earlier training in the "
                             "output folder (without it the run is refused before it starts)")
    parser.set_defaults(func=run_train)
    return parser


def run_train(args: argparse.Namespace) -> int:
    """Run ``jaxsync train`` with parsed arguments; returns the exit status 0.

    Raises:
        ConfigError, CheckpointError: unusable options or trajectory files.
    """
    from jaxsync.cli.common import check_outputs, refuse_to_overwrite

    # before any data is read: the folder (created if missing) and every file written into it
    results = [os.path.join(args.output, name) for name in (args.surrogate_name, LOSS_CURVES_NAME, SUMMARY_NAME)]
    check_outputs((args.output, "output folder", "-o", True),
                  *((os.path.join(args.output, name), "output", "-o" if name != args.surrogate_name
                     else "-o/--surrogate-name")
                    for name in (args.surrogate_name, LOSS_CURVES_NAME, SUMMARY_NAME, STATE_NAME)))
    refuse_to_overwrite(results, force=args.force, inputs=args.trajectories, options="-o/--surrogate-name")
    state = TrainingState(args.output, every=args.state_every) if args.state_every else None
    architecture = ArchitectureChoice(model=args.model, n_hidden=args.n_hidden, n_layers=args.n_layers,
                                      n_cond_repeat=args.cond_repeat, regularization=args.regularization,
                                      load_input=args.load_input, highway=args.highway)
    if architecture.model_class.resumes_training and state is not None and os.path.exists(state.path):
        print(f"resuming from the training state {state.path}")
    trained = train_surrogates(
        args.trajectories,
        architecture=architecture,
        sampling=Sampling(n_s=args.n_s, n_past=args.n_past, n_future=args.n_future,
                          train_fraction=args.train_fraction, val_fraction=args.val_fraction,
                          n_offsets=args.n_offsets, split=args.split, load_jump_windows=args.load_jump_windows,
                          seed=args.seed),
        optimizer=TrainConfig(batch_size=args.batch_size, eta0=args.eta0, gamma=args.gamma, eta_min=args.eta_min,
                              n_epochs=args.epochs, epochs_per_call=args.epochs_per_call,
                              patience=args.patience or None, n_candidates=args.n_candidates),
        checks=TrainingChecks(emse_applications=args.emse_applications,
                              rollout_tolerance=args.rollout_tolerance or None),
        load_parameters=args.load_parameter, allow_predicted=args.allow_predicted, state=state,
        devices=args.devices, progress=not args.no_progress,
    ).write(args.output, surrogate_name=args.surrogate_name)
    result = trained.result
    # the epoch each part kept, where training ran epochs
    kept = "" if result.best_epoch is None else f" (best epochs {', '.join(str(int(e)) for e in result.best_epoch)})"
    print(f"wrote {os.path.join(args.output, args.surrogate_name)}, {os.path.join(args.output, LOSS_CURVES_NAME)} "
          f"and {SUMMARY_NAME} ({result.arch.fit_description(result)}); validation MSE of the kept parameters per "
          f"part: {', '.join(f'{v:.3e}' for v in result.best_val_loss)}{kept}")
    inputs = result.load_inputs
    print(f"load input: {len(inputs)} known load signal(s): " + "; ".join(map(str, inputs)) if inputs else
          "load input: none (load-blind surrogates)")
    if trained.candidates is not None:
        c = trained.candidates
        print(f"candidates: {c['n_candidates']} networks per part, kept candidate "
              f"{', '.join(str(k) for k in c['chosen'])} (validation MSE per candidate and part: "
              + "; ".join(", ".join(f"{v:.3e}" for v in row) for row in c["best_val_loss"]) + ")")
    if trained.rollout is not None:
        verdict = "within" if trained.rollout_passed else "ABOVE"
        print(f"offline check: rolled out over {trained.rollout.n_steps} steps, shared displacements off by up to "
              f"{', '.join(f'{100 * v:.2f} %' for v in trained.rollout.relative)} of each part's amplitude "
              f"({verdict} the tolerance of {100 * trained.rollout_tolerance:g} %)")
    return 0


__all__ = ["add_train_parser", "run_train"]
