"""``jaxsync finetune``: solver-in-the-loop fine-tuning of trained surrogates
(:func:`jaxsync.solve.fine_tune_in_the_loop`) on the partition of a synchronized
trajectory; writes a new surrogate file that ``jaxsync predict`` reads."""

from __future__ import annotations

from . import common


def add_parser(subparsers) -> None:
    # defaults: jaxsync.solve.FineTuneConfig's (read in run: building the parser
    # imports no solver)
    p = subparsers.add_parser(
        "finetune", help="fine-tune trained surrogates on the error of the coupled online run",
        description="Train every part's network further on what the synchronization-avoiding run "
                    "does: windows of the synchronized TRAJECTORY (n_s n_p synchronized steps, then "
                    "--window-cycles refill cycles predicted) against the synchronized run from the "
                    "same state, gradients through the solver and all the networks together (Adam); "
                    "the weights with the lowest loss on validation windows are kept and written to "
                    "--output. The problem comes from a TOML file (default: the packaged cantilever).")
    common.add_trained_run_arguments(p)
    p.add_argument("--span", type=int, default=None,
                   help="windows lie within the first SPAN steps (default: the part of the trajectory "
                        "the surrogates were trained on, its train_fraction; else the whole trajectory)")
    p.add_argument("--iterations", type=int, default=None,
                   help="Adam steps, one window each (default: FineTuneConfig's, 60)")
    p.add_argument("--window-cycles", type=int, default=None,
                   help="refill cycles predicted per window (default: FineTuneConfig's, 2)")
    p.add_argument("--learning-rate", type=float, default=None,
                   help="Adam's step size (default: FineTuneConfig's, 1e-4)")
    p.add_argument("--seed", type=int, default=None, help="draws of the windows (default: 0)")
    common.add_mode_option(p)
    p.add_argument("--output", "-o", default="surrogate_finetuned.h5",
                   help="the fine-tuned surrogate file (default: %(default)s)")
    p.add_argument("--force", action="store_true",
                   help="overwrite an existing output file (without it the run is refused before it starts)")
    common.add_progress_option(p)
    p.set_defaults(func=run)


def run(args) -> int:
    import dataclasses

    from ..errors import ConfigError
    from ..solve._finetune import FineTuneConfig, fine_tune_in_the_loop
    from ..surrogate import Surrogate

    common.check_outputs((args.output, "fine-tuned surrogate file", "-o"))
    common.refuse_to_overwrite([args.output], force=args.force, inputs=common.trained_run_inputs(args))
    reference, part, problem, saved = common.load_trained_run(args)
    if saved.arch.conditional:
        raise ConfigError("fine-tuning conditional surrogates (trained on several runs with load "
                          "parameters) is not supported: fine-tune unconditional ones")
    n_steps = int(round(float(reference.times[-1]) / reference.dt))
    fraction = saved.metadata.get("sampling", {}).get("train_fraction")
    span = args.span or (int(fraction * n_steps) if fraction else n_steps)
    if not 0 < span <= n_steps:
        raise ConfigError(f"--span {span} must be between 1 and the trajectory's {n_steps} steps")
    given = {"n_iterations": args.iterations, "window_cycles": args.window_cycles,
             "learning_rate": args.learning_rate, "seed": args.seed}
    config = FineTuneConfig(**{k: v for k, v in given.items() if v is not None})
    config = dataclasses.replace(config, validate_every=min(config.validate_every, config.n_iterations))
    result = fine_tune_in_the_loop(problem, Surrogate.from_saved(saved), part, n_steps=span, config=config,
                                   dt=reference.dt, mode=common.mode_of(args), progress=not args.no_progress)
    metadata = {**saved.metadata, "fine_tuned": {**result.summary(), "span_steps": span,
                                                "config": {k: getattr(config, k) for k in config.__dataclass_fields__},
                                                "from_surrogate": str(args.surrogate)}}
    with common.writing(args.output):
        result.surrogate.save(args.output, shared_nodes=saved.shared_nodes, metadata=metadata)
    kept = ("the trained weights (no step lowered the validation loss)" if result.best_iteration == 0
            else f"the weights of step {result.best_iteration}")
    print(f"fine-tuned on {config.n_iterations} windows of {config.window_cycles} refill cycles within the first "
          f"{span} steps: validation loss x {result.improvement:.3f}, kept {kept}; {result.seconds:.1f} s "
          f"({result.compile_seconds:.1f} s compiling); wrote {args.output}")
    return 0
