"""``jaxsync predict``: the synchronization-avoiding run (paper Algorithm 3) with trained
surrogates, on the partition of a synchronized trajectory."""

from __future__ import annotations

import argparse
import os

from . import common


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "predict", help="synchronization-avoiding run with trained surrogates",
        description="Run paper Algorithm 3: synchronized steps up to --n-cri, then the "
                    "surrogates of SURROGATE replace the synchronization. The partition is the "
                    "one of TRAJECTORY (the synchronized run the surrogates were trained on); "
                    "the problem comes from a TOML file (default: the packaged cantilever).")
    common.add_trained_run_arguments(p)
    p.add_argument("--n-cri", type=int, default=None,
                   help="last synchronized step (default and minimum: n_p n_s)")
    p.add_argument("--steps", type=int, default=None,
                   help="total steps (default: as many as the trajectory holds)")
    p.add_argument("--save-every", type=int, default=None,
                   help="snapshot stride; must divide n_cri and n_s n_f (default: the "
                        "trajectory's, so that jaxsync report can compare the two)")
    common.add_mode_option(p)
    common.add_sync_option(p)
    p.add_argument("--load-parameter", "--cond", dest="load_parameter", type=float, default=None,
                   help="load parameter of conditional surrogates (--cond: its former name)")
    common.add_resync_tolerance_option(
        p, help="error control: hold the run to this tolerance -- in cm (1e-4) or as a percentage (2%%) of the "
                "shared amplitude the surrogates were trained on (the largest shared-node displacement in the steps "
                "their training read, which the surrogate file records; a file without it: of TRAJECTORY): each "
                "refill cycle's es_hat (the parts' disagreement, paper eq. 26) is checked before it runs and the "
                "estimated error since the last synchronized state (the force-balance defect probed at the saved "
                "steps, see --error-indicator) after; above it the run goes back to the last synchronized state "
                "and recomputes with the synchronized solver (default: 1%%; none turns it off)")
    common.add_online_learning_option(p)
    p.add_argument("--raw-refill", action="store_true",
                   help="write the paper's raw refill into the solver (n_s interleaved network "
                        "applications, which jitter from step to step) instead of the default smooth "
                        "curve through their block means (jaxsync.surrogate.smooth_refill)")
    p.add_argument("--refill-samples", type=_refill_samples, default=None, metavar="N|all",
                   help="network applications per smooth refill: the block means the curve goes through are "
                        "estimated from N applications evenly spaced over the n_s (jaxsync.surrogate."
                        "refill_block_means; default: jaxsync.surrogate.DEFAULT_REFILL_SAMPLES, 16; 'all': every "
                        "one, n_s network calls per refill)")
    p.add_argument("--inference-dtype", choices=("float32", "bfloat16"), default=None,
                   help="compute the networks in bfloat16 (float32 accumulation; jaxsync.surrogate."
                        "inference): checked first on the synchronized run's shared histories and "
                        "refused when it deviates from the trained precision by more than 1 %% "
                        "(default: the networks' own dtype)")
    p.add_argument("--load-jumps", choices=("synchronize", "predict"), default="synchronize",
                   help="at the steps where a load's time function jumps (a load switched off): stay "
                        "synchronized until the networks' whole input history follows the last jump "
                        "(default; no surrogate can foresee it), or predict through them as the paper did")
    p.add_argument("--output", "-o", default="online.h5", help="output trajectory (default: %(default)s)")
    p.add_argument("--force", action="store_true",
                   help="overwrite an existing output file (without it the run is refused before "
                        "it starts)")
    common.add_compression_option(p)
    common.add_progress_option(p)
    p.set_defaults(func=run)


def trained_amplitude(saved, reference) -> float | None:
    """The shared amplitude [cm] a percentage tolerance of ``jaxsync predict`` refers to:
    the one the surrogate file records of its training data
    (:attr:`jaxsync.surrogate.TrainedSurrogates.shared_amplitude`), else the largest
    shared-node displacement of the trajectory ``reference``; None when that is 0 (the
    tolerance then follows the amplitude the run observes)."""
    import numpy as np

    amplitude = saved.metadata.get("shared_amplitude_cm")
    if amplitude is None:
        amplitude = max(float(np.abs(p.shared_displacement).max(initial=0.0)) for p in reference.parts)
    return float(amplitude) if amplitude and amplitude > 0 else None


def run(args) -> int:
    from ..solve.coupling._syncavoid import describe_run, simulate_sync_avoiding

    learned = getattr(args, "learn_save", None)
    common.check_outputs((args.output, "output trajectory", "-o"),
                         *([(learned, "learned surrogate file", "--learn-save")] if learned else []))
    common.refuse_to_overwrite([args.output] + ([learned] if learned else []), force=args.force,
                               inputs=common.trained_run_inputs(args))
    if args.resync_tolerance is None:
        args.resync_tolerance = "1%"  # of the shared amplitude the surrogates were trained on (below)
    common.online_learning_of(args)  # --learn without a tolerance: refused before the run
    reference, part, problem, saved = common.load_trained_run(args)
    n_cri = args.n_cri or saved.n_s * saved.arch.n_past
    n_steps = args.steps or int(round(float(reference.times[-1]) / reference.dt))
    import dataclasses

    from ..solve._strategies import HostExecutor
    from ..surrogate import Surrogate

    # the surrogate file's shared nodes were checked against the partition when it was loaded
    surrogates = dataclasses.replace(Surrogate.from_saved(saved, args.load_parameter), smooth=not args.raw_refill)
    if args.refill_samples is not None:
        surrogates = surrogates.with_refill_samples(None if args.refill_samples == "all" else args.refill_samples)
    if args.inference_dtype == "bfloat16":
        # bound to the problem's load signals first (surrogates with load input read them)
        surrogates = _reduced_precision(surrogates.for_problem(problem, reference.dt), reference, args.trajectory)
    tolerance = common.resync_tolerance_of(args)
    if tolerance is not None and tolerance.relative is not None and tolerance.amplitude is None:
        tolerance = dataclasses.replace(tolerance, amplitude=trained_amplitude(saved, reference))
    online = simulate_sync_avoiding(problem, n_steps, partitions=part, surrogates=surrogates, n_cri=n_cri,
                                    dt=reference.dt, mode=common.mode_of(args),
                                    save=args.save_every or reference.save_every,
                                    resync_tolerance=tolerance, load_jumps=args.load_jumps,
                                    executor=HostExecutor(progress=not args.no_progress), **common.sync_of(args))
    with common.writing(args.output):
        online.save(args.output, compression=common.compression_of(args))
    print(describe_run(online) + f"; wrote {args.output}"
          + (f" and the learned surrogates to {learned}" if learned and os.path.exists(learned) else ""))
    return 0


def _reduced_precision(surrogate, reference, name):
    """``surrogate`` computing in bfloat16, after the check on ``reference``'s shared
    histories (:func:`jaxsync.surrogate.reduced_precision`: refused above the
    default bound, with the deviation in the message)."""
    from ..errors import ConfigError
    from ..surrogate._inference import DEFAULT_BOUND, reduced_precision, surrogate_signal_windows, surrogate_windows

    if reference.shared_stride != 1:
        raise ConfigError(f"--inference-dtype bfloat16 checks the reduced precision on the shared "
                          f"histories of {name} at every step, which keeps them every "
                          f"{reference.shared_stride} steps: rerun it with --shared-every 1")
    histories = [p.shared_displacement for p in reference.parts]
    windows = surrogate_windows(surrogate, histories, max_windows=256)
    signals = (surrogate_signal_windows(surrogate, len(histories[0]), max_windows=256) if surrogate.n_load
               else None)
    reduced, report = reduced_precision(surrogate, windows, "bfloat16", signals=signals)
    print(f"bfloat16 inference: deviates from {surrogate.arch.dtype} by at most {100 * report.worst:.3g} % "
          f"(RMS over {report.n_windows} windows of {name}; bound {100 * DEFAULT_BOUND:.3g} %)")
    return reduced


def _refill_samples(text: str) -> int | str:
    """``--refill-samples``: an integer >= 1, or ``"all"``."""
    if text.strip().lower() == "all":
        return "all"
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1 or 'all', got {text!r}")
    return value
