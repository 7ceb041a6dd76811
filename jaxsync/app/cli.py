"""The ``jaxsync`` command line: ``demo``, ``simulate``, ``train``, ``predict``, ``report``.

Errors of the package's own types are printed as one line (``error: ...``) with exit
status 2; anything else is a bug and keeps its traceback.

Under ``mpiexec -n N`` (N > 1, detected from the launcher's environment) every rank joins
the others through ``jax.distributed`` before using JAX (:mod:`jaxsync.parallel.multiprocess`),
only rank 0 prints and writes files, and an error on any rank ends the whole job with a
non-zero status (the error is printed with its rank) instead of leaving the others waiting.
"""

from __future__ import annotations

import argparse
import os
import sys
import time


def _enable_x64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


def _add_demo(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="run the whole pipeline on the built-in cantilever and print a summary",
        description="The paper's pipeline on the built-in coarse cantilever with two parts: "
                    "synchronized distributed run, training of one LSTM surrogate per part, "
                    "synchronization-avoiding run, report. Prints a summary table and writes "
                    "trajectories, the checkpoint, figures and summary.json into --out. The "
                    "default schedule takes a few minutes on a 2-core laptop.")
    p.add_argument("--out", default="jaxsync-demo", help="output folder (default: %(default)s)")
    p.add_argument("--steps", type=int, default=100000,
                   help="time steps of both runs (default: %(default)s, 35 s of physical time as "
                        "in the paper)")
    p.add_argument("--parts", type=int, default=2, help="number of parts (default: %(default)s)")
    p.add_argument("--n-s", type=int, default=80, help="sampling stride n_s (default: %(default)s)")
    p.add_argument("--n-past", type=int, default=20, help="input snapshots n_p (default: %(default)s)")
    p.add_argument("--n-future", type=int, default=20,
                   help="predicted snapshots n_f (default: %(default)s)")
    p.add_argument("--hidden", type=int, default=32, help="LSTM hidden size n_H (default: %(default)s)")
    p.add_argument("--layers", type=int, default=2,
                   help="bidirectional encoder layers (default: %(default)s)")
    p.add_argument("--epochs", type=int, default=300, help="training epochs (default: %(default)s)")
    p.add_argument("--eta0", type=float, default=2e-3,
                   help="initial learning rate (default: %(default)s)")
    p.add_argument("--gamma", type=float, default=0.995,
                   help="per-epoch learning-rate decay (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of METIS, initialization and shuffling (default: %(default)s)")
    p.add_argument("--save-every", type=int, default=None,
                   help="full-field snapshot stride of both runs; divides n_s n_p and n_s n_f "
                        "(default: n_s; the parts' shared nodes are kept at every step)")
    p.add_argument("--resync-tolerance", default=None, metavar="CM|PCT%",
                   help="error control of the predicted run (see jaxsync predict --help)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    p.set_defaults(func=_run_demo)


def _run_demo(args) -> int:
    from .demo import format_summary, run_demo
    from ..errors import ConfigError

    if _process_count() > 1:
        raise ConfigError("jaxsync demo runs in one process (it uses emulated devices); "
                          "start it without mpiexec")
    summary = run_demo(args.out, n_steps=args.steps, n_parts=args.parts, n_s=args.n_s,
                       n_past=args.n_past, n_future=args.n_future, hidden=args.hidden,
                       layers=args.layers, epochs=args.epochs, eta0=args.eta0, gamma=args.gamma,
                       seed=args.seed, save_every=args.save_every,
                       resync_tolerance=args.resync_tolerance, progress=not args.no_progress)
    print("jaxsync demo: synchronization-avoiding cantilever")
    print(format_summary(summary))
    print(f"  summary written to {os.path.abspath(os.path.join(args.out, 'summary.json'))}")
    return 0


def _add_predict(subparsers) -> None:
    p = subparsers.add_parser(
        "predict", help="synchronization-avoiding run with trained surrogates",
        description="Run paper Algorithm 3: synchronized steps up to --n-cri, then the "
                    "surrogates of CHECKPOINT replace the synchronization. The partition is the "
                    "one of TRAJECTORY (the synchronized run the surrogates were trained on); "
                    "the problem comes from a TOML file (default: the packaged cantilever).")
    p.add_argument("trajectory", help="synchronized distributed trajectory (HDF5) that defines "
                                      "the partition")
    p.add_argument("checkpoint", help="surrogate checkpoint written by jaxsync train")
    p.add_argument("--config", default=None, help="TOML problem file (default: the cantilever)")
    p.add_argument("--mesh", default=None, help="mesh file to use instead of the config's")
    p.add_argument("--n-cri", type=int, default=None,
                   help="last synchronized step (default and minimum: n_p n_s)")
    p.add_argument("--steps", type=int, default=None,
                   help="total steps (default: as many as the trajectory holds)")
    p.add_argument("--save-every", type=int, default=None,
                   help="snapshot stride; must divide n_cri and n_s n_f (default: the "
                        "trajectory's, so that jaxsync report can compare the two)")
    p.add_argument("--mode", choices=("preassembled", "recompute"), default="preassembled",
                   help="internal force formulation (default: %(default)s)")
    p.add_argument("--cond", type=float, default=None,
                   help="load parameter for conditional surrogates")
    p.add_argument("--resync-tolerance", default=None, metavar="CM|PCT%",
                   help="error control: check each refill cycle's predictions before using "
                        "them; when es_hat, the parts' disagreement at the shared nodes (paper "
                        "eq. 26), exceeds this tolerance -- in cm (1e-4) or as a percentage of "
                        "the largest shared-node displacement seen in synchronized steps (2%%) "
                        "-- go back to the last synchronized state and recompute with the "
                        "synchronized solver (default: never)")
    p.add_argument("--output", "-o", default="online.h5", help="output trajectory (default: %(default)s)")
    p.add_argument("--force", action="store_true",
                   help="overwrite an existing output file (without it the run is refused before "
                        "it starts)")
    p.add_argument("--compression", choices=("gzip", "lzf", "none"), default="gzip",
                   help="HDF5 compression of the output's large datasets (default: %(default)s; "
                        "lzf is faster, none the fastest to write)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_run_predict)


def _run_predict(args) -> int:
    import numpy as np

    from .config import load_config, problem_from_config
    from ..errors import PartitionError
    from ..parallel.partition import partition_of
    from ..surrogate.checkpoint import load_checkpoint
    from ..solve.syncavoid import describe_run, simulate_sync_avoiding
    from ..trajectory import Trajectory

    _refuse_to_overwrite([args.output], force=args.force)
    reference = Trajectory.load(args.trajectory)
    part = partition_of(reference)
    problem, _ = problem_from_config(load_config(args.config), mesh_file=args.mesh)
    if (problem.mesh.n_nodes != reference.mesh.n_nodes
            or not np.array_equal(problem.mesh.tets, reference.mesh.tets)):
        raise PartitionError(f"the problem's mesh differs from the mesh of {args.trajectory}; "
                             "pass the same --config/--mesh as the synchronized run")
    ckpt = load_checkpoint(args.checkpoint, [p.shared_nodes for p in part.parts])
    n_cri = args.n_cri or ckpt.n_s * ckpt.arch.n_past
    n_steps = args.steps or int(round(float(reference.times[-1]) / reference.dt))
    online = simulate_sync_avoiding(problem, n_steps, partitions=part, surrogates=ckpt, n_cri=n_cri,
                                    dt=reference.dt, mode=args.mode,
                                    save_every=args.save_every or reference.save_every,
                                    cond=args.cond, progress=not args.no_progress,
                                    resync_tolerance=args.resync_tolerance)
    online.save(args.output, compression=_compression(args))
    print(describe_run(online) + f"; wrote {args.output}")
    return 0


def _add_report(subparsers) -> None:
    p = subparsers.add_parser(
        "report", help="figures and summary.json comparing an online run with the synchronized one",
        description="Compare a synchronization-avoiding trajectory (jaxsync predict) with the "
                    "synchronized reference: displacement at monitored nodes, e_l2(t), es and "
                    "es_hat, et histograms (PNG) and summary.json. By default the monitored nodes "
                    "are, for each part, the node that is neither shared nor constrained with the "
                    "largest amplitude in the reference, and the shared node with the largest "
                    "amplitude; never a node that does not move in the reference or belongs to "
                    "the Dirichlet set of --config.")
    p.add_argument("reference", help="synchronized trajectory (HDF5)")
    p.add_argument("online", help="synchronization-avoiding trajectory (HDF5)")
    p.add_argument("--out", "-o", default="report", help="output folder (default: %(default)s)")
    p.add_argument("--component", type=int, choices=(0, 1, 2), default=2,
                   help="displacement component shown and compared at the nodes (default: "
                        "%(default)s = z)")
    p.add_argument("--node", action="append", default=None, metavar="ID|X,Y,Z",
                   help="monitor this node instead of the automatic choice: a node id or "
                        "coordinates x,y,z (the nearest node); repeat for several")
    p.add_argument("--config", default=None,
                   help="TOML problem file of the run: its Dirichlet nodes are never chosen "
                        "(default: none; then the constrained nodes are those that never move in "
                        "the reference, which covers every fully clamped node)")
    p.set_defaults(func=_run_report)


def _run_report(args) -> int:
    import dataclasses

    from ..errors import CheckpointError
    from ..parallel.partition import partition_of
    from .plots import constrained_nodes, write_report
    from ..trajectory import Trajectory

    reference = Trajectory.load(args.reference)
    online = Trajectory.load(args.online)
    if online.synchronized is None:
        raise CheckpointError(f"{args.online} is not a synchronization-avoiding trajectory")
    stride, rest = divmod(online.save_every, reference.save_every)
    if rest or abs(online.dt - reference.dt) > 1e-12 * reference.dt:
        raise CheckpointError("the two trajectories do not share time steps (dt and save_every "
                              "must match, the reference saved at least as often)")
    n = online.n_saved
    if reference.n_saved < (n - 1) * stride + 1:
        raise CheckpointError(f"{args.reference} is shorter than {args.online}")
    reference = dataclasses.replace(reference, times=reference.times[:(n - 1) * stride + 1:stride],
                                    displacement=reference.displacement[:(n - 1) * stride + 1:stride],
                                    save_every=online.save_every)
    fixed = constrained_nodes(args.config, online.mesh, reference.displacement)
    summary = write_report(reference, online, partition_of(online), args.out,
                           component=args.component, fixed_nodes=fixed, nodes=args.node,
                           extra={"online_statistics": online.stats.to_dict()})
    for line in summary["node_notes"]:
        print(f"note: {line}")
    if online.stats.to_dict():
        from ..solve.syncavoid import describe_run

        print(describe_run(online))
    if "es_hat_tracking" in summary:
        from ..metrics import EstimateQuality

        print(EstimateQuality(**summary["es_hat_tracking"]).summary())
    c = "xyz"[args.component]
    print(f"wrote figures and summary.json to {os.path.abspath(args.out)}; largest-amplitude monitored "
          f"node {summary['monitored_node']} ({summary['monitored_label']}): max |error| in d_{c} "
          f"{summary['tip_max_abs_error']:.3e} cm of {summary['tip_max_abs_displacement']:.3e} cm; "
          f"e_l2 at the end {summary['l2_error_final']:.3e} cm")
    return 0


def _add_simulate(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate", help="run a problem described by a TOML file",
        description="Run the explicit solver on a problem described by a TOML file (default: "
                    "the packaged cantilever; see jaxsync.app.config for the layout). Command-line "
                    "options override the file's [run] and [mesh] entries; relative paths on the "
                    "command line are taken from the current directory, those in the file from "
                    "the file's folder. Existing output files are never overwritten without "
                    "--force.")
    _accept_negative_numbers(p)
    p.add_argument("config", nargs="?", default=None,
                   help="TOML problem file (default: the packaged cantilever)")
    p.add_argument("--mesh", default=None, help="mesh file to use instead of [mesh]")
    p.add_argument("--steps", type=int, default=None, help="number of time steps ([run] n_steps)")
    p.add_argument("--save-every", type=int, default=None,
                   help="keep one snapshot every this many steps ([run] save_every)")
    p.add_argument("--shared-every", type=int, default=None,
                   help="distributed runs: keep each part's shared-node displacements every this "
                        "many steps, a divisor of --save-every (default: --save-every); surrogate "
                        "training (jaxsync train) needs 1, while the full field can stay thinned")
    p.add_argument("--compression", choices=("gzip", "lzf", "none"), default="gzip",
                   help="HDF5 compression of the output's large datasets (default: %(default)s; "
                        "lzf is faster, none the fastest to write)")
    p.add_argument("--dt", type=float, default=None,
                   help="time step in s ([run] dt; default: the CFL step of the problem, after "
                        "mass scaling if any); must be positive and below the stability bound")
    scaling = p.add_mutually_exclusive_group()
    scaling.add_argument("--mass-scaling-dt", type=float, default=None, metavar="S",
                         help="artificial mass scaling (paper Algorithm 2): make every element "
                              "stable at this step in s, and run at it unless --dt is given "
                              "([run] mass_scaling_dt); the added mass is printed, with a warning "
                              "above 10 %%")
    scaling.add_argument("--mass-scaling-beta", type=float, default=None, metavar="B",
                         help="mass scaling to B times the CFL step ([run] mass_scaling_beta)")
    p.add_argument("--output", "-o", default=None,
                   help="HDF5 trajectory file ([run] output); with -o, an XDMF output the file "
                        "asks for ([run] xdmf) is named after it: <stem>.xdmf")
    p.add_argument("--xdmf", default=None, help="also write an XDMF time series for ParaView")
    p.add_argument("--force", action="store_true",
                   help="overwrite existing output files (trajectory, XDMF and its .xdmf.h5, "
                        "timings JSON); without it the run is refused before it starts, except "
                        "when it resumes from an existing --checkpoint: it then continues the "
                        "run that wrote those outputs and replaces them")
    p.add_argument("--checkpoint", default=None,
                   help="resumable run: store the state here and continue from it if present "
                        "(a checkpoint of another problem, or altered after it was written, is "
                        "refused: delete it to start over)")
    p.add_argument("--checkpoint-every", type=int, default=None,
                   help="steps between checkpoints (default: every compiled chunk)")
    p.add_argument("--partitions", type=int, default=None,
                   help="distributed run over this many METIS parts (default: single device; "
                        "under mpiexec -n N: N parts, one per process)")
    p.add_argument("--sync", choices=("psum", "ppermute", "mpi"), default=None,
                   help="how parts sum shared-node forces every step: XLA psum of the whole "
                        "interface (emulated devices, gloo between processes, NCCL between "
                        "GPUs), XLA ppermute exchange of the nodes neighbouring devices share, "
                        "or an MPI Allreduce inside the compiled step, one device per process "
                        "(default: mpi across processes, psum in one process)")
    p.add_argument("--mode", choices=("preassembled", "recompute"), default="preassembled",
                   help="internal force: stored sparse K, or element quantities formed every "
                        "step (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="METIS seed (default: %(default)s)")
    p.add_argument("--timings", nargs="?", const="", default=None, metavar="JSON",
                   help="instead of running, measure the per-step breakdown t_e, t_m, t_s, t_t "
                        "(paper section 7; max-average over parts), print the table and write it "
                        "as JSON (default file: <output>.timings.json)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.add_argument("--print-config", action="store_true",
                   help="print the packaged default configuration and exit")
    p.set_defaults(func=_run_simulate)


_NEGATIVE_NUMBER = r"^-(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$"


def _accept_negative_numbers(parser) -> None:
    """Let option values such as ``--dt -1e-4`` parse as numbers (and be refused by the
    package's own checks with a clear message) instead of argparse's "expected one
    argument": before Python 3.14 argparse takes a negative number in exponent notation
    for an option name. The parser has no options that look like negative numbers."""
    import re

    if hasattr(parser, "_negative_number_matcher"):
        parser._negative_number_matcher = re.compile(_NEGATIVE_NUMBER)


def _simulate_outputs(args, config: dict) -> tuple[str, str | None, str | None, bool]:
    """(trajectory path, xdmf path or None, checkpoint path or None, resuming) of a
    ``jaxsync simulate`` run, from the command line over the (path-resolved) config."""
    from .config import RunConfig

    run = config.get("run", {})
    output = args.output or run.get("output", RunConfig.output)
    if args.xdmf:
        xdmf = args.xdmf
    elif run.get("xdmf") and args.output:  # two runs with different -o keep their own xdmf
        xdmf = os.path.splitext(args.output)[0] + ".xdmf"
    else:
        xdmf = run.get("xdmf")
    if xdmf and not xdmf.endswith(".xdmf"):
        xdmf += ".xdmf"  # as Trajectory.to_xdmf names it
    checkpoint = args.checkpoint or run.get("checkpoint")
    return output, xdmf, checkpoint, bool(checkpoint) and os.path.exists(checkpoint)


def _xdmf_files(xdmf: str) -> list[str]:
    """The files Trajectory.to_xdmf writes: ``<stem>.xdmf`` and ``<stem>.xdmf.h5``."""
    return [xdmf, os.path.splitext(xdmf)[0] + ".xdmf.h5"]


def _refuse_to_overwrite(paths: list[str], *, force: bool, checkpoint: str | None = None) -> None:
    """ConfigError, before anything runs, when two outputs (or an output and the
    checkpoint) are the same file, or when an output exists and ``force`` is False."""
    from ..errors import ConfigError

    seen: dict[str, str] = {}
    for path in paths + ([checkpoint] if checkpoint else []):
        key = os.path.normcase(os.path.realpath(path))
        if key in seen:
            raise ConfigError(f"{path} is used for two outputs (also as {seen[key]}); give the "
                              "trajectory, XDMF and checkpoint files different names")
        seen[key] = path
    existing = [path for path in paths if os.path.exists(path)]
    if existing and not force:
        names = ", ".join(existing)
        raise ConfigError(f"{names} already exist{'s' if len(existing) == 1 else ''} (the output "
                          "of an earlier run?); pass --force to overwrite, or choose other "
                          "names with -o/--xdmf")


def _report_warnings(caught) -> None:
    """Show warnings recorded while building the problem: the package's own as one
    ``warning: ...`` line on stderr, any other as Python shows it."""
    import warnings

    from ..fem.mesh import MeshWarning
    from ..fem.timestep import MassScalingWarning

    for w in caught:
        if issubclass(w.category, (MeshWarning, MassScalingWarning)):
            print(f"warning: {w.message}", file=sys.stderr)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def _run_simulate(args) -> int:
    import dataclasses
    import warnings

    from .config import default_config_path, load_config, problem_from_config
    from ..errors import StabilityError
    from ..solve.solver import simulate

    if args.print_config:
        with open(default_config_path()) as f:
            sys.stdout.write(f.read())
        return 0
    main_rank = _is_main_process()
    config = load_config(args.config)
    output, xdmf, checkpoint, resuming = _simulate_outputs(args, config)
    if args.timings is not None:
        timings_path = args.timings or os.path.splitext(output)[0] + ".timings.json"
        if main_rank:
            _refuse_to_overwrite([timings_path], force=args.force)
    elif main_rank:  # the writer; checked before the mesh is read and anything runs
        _refuse_to_overwrite([output] + (_xdmf_files(xdmf) if xdmf else []),
                             force=args.force or resuming, checkpoint=checkpoint)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        problem, run = problem_from_config(config, mesh_file=args.mesh,
                                           mass_scaling_dt=args.mass_scaling_dt,
                                           mass_scaling_beta=args.mass_scaling_beta)
    if main_rank:
        _report_warnings(caught)
    n_steps = args.steps if args.steps is not None else run.n_steps
    save_every = args.save_every if args.save_every is not None else run.save_every
    dt = args.dt if args.dt is not None else run.dt  # None: the (mass-scaled) CFL step
    if args.timings is not None:
        from ..perf.timing import timing_breakdown

        report = timing_breakdown(problem, args.partitions or 1, mode=args.mode, dt=dt,
                                  seed=args.seed)
        if main_rank:
            print(report.table())
            report.save_json(timings_path)
            print(f"wrote {timings_path}")
        return 0
    n_processes = _process_count()
    partitions = args.partitions
    if partitions is None and n_processes > 1:
        partitions = n_processes  # one part per process
    # passed only when asked for, so that simulate() keeps its own default
    sync = {} if args.sync is None else {"sync": args.sync}
    if main_rank:
        print(problem.summary())
        if run.added_mass_percent is not None:
            print(f"mass scaling to dt {float(problem.dt):.4e} s: added mass "
                  f"{run.added_mass_percent:.2f} % of the total")
        if n_processes > 1:
            print(f"{n_processes} processes, {partitions} parts")
    start = time.perf_counter()
    try:
        trajectory = simulate(problem, n_steps, dt=dt,
                              save_every=save_every, progress=main_rank and not args.no_progress,
                              partitions=partitions, mode=args.mode, seed=args.seed,
                              checkpoint=checkpoint,
                              checkpoint_every=args.checkpoint_every or run.checkpoint_every,
                              shared_every=args.shared_every, **sync)
    except StabilityError as exc:
        partial = getattr(exc, "trajectory", None)
        if not main_rank:
            _barrier()  # let rank 0 write the partial trajectory before the job ends
            raise
        if partial is not None and partial.n_saved:
            root, ext = os.path.splitext(output)
            partial_path = f"{root}.partial{ext or '.h5'}"
            partial.save(partial_path)
            print(f"saved the {partial.n_saved} snapshots before divergence to {partial_path}",
                  file=sys.stderr)
        _barrier()
        raise
    elapsed = time.perf_counter() - start
    if not main_rank:  # rank 0 writes and prints
        return 0
    if run.added_mass_percent is not None:
        trajectory = dataclasses.replace(trajectory, parameters={
            **trajectory.parameters, "added_mass_percent": float(run.added_mass_percent)})
    trajectory.save(output, compression=_compression(args))
    st = trajectory.stats
    speed = (f"{st.us_per_step:.1f} us/step, compilation {st.compile_seconds:.2f} s not included"
             if st.us_per_step is not None else "no steps run")
    shared = (f", {partitions // st.n_devices} parts per device"
              if partitions and partitions > st.n_devices else "")
    print(f"{n_steps} steps in {elapsed:.2f} s ({speed}; {st.n_devices} {st.device_kind} "
          f"device{'s' if st.n_devices > 1 else ''}{', emulated' if st.emulated else ''}"
          f"{shared}); wrote {output}")
    if xdmf:
        trajectory.to_xdmf(xdmf)
        print(f"wrote {xdmf}")
    return 0


def _process_count() -> int:
    from ..parallel.multiprocess import process_count

    return process_count()


def _is_main_process() -> bool:
    from ..parallel.multiprocess import is_main_process

    return is_main_process()


def _barrier() -> None:
    """Wait for all processes (a no-op in a single-process run)."""
    if _process_count() > 1:
        from ..parallel.multiprocess import world

        world().Barrier()


def build_parser() -> argparse.ArgumentParser:
    """The ``jaxsync`` argument parser with all subcommands."""
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="jaxsync",
        description="Differentiable, distributed explicit FEM for linear elastodynamics on "
                    "tetrahedra, with LSTM surrogates that replace synchronization.")
    parser.add_argument("--version", action="version", version=f"jaxsync {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    from .train import add_train_parser

    _add_demo(subparsers)
    _add_simulate(subparsers)
    add_train_parser(subparsers)
    _add_predict(subparsers)
    _add_report(subparsers)
    return parser


def _compression(args) -> str | None:
    """``--compression`` as :meth:`jaxsync.Trajectory.save` takes it."""
    return None if args.compression == "none" else args.compression


def _parts_of(args) -> int:
    """How many parts the command runs (0: none), read without starting JAX."""
    command = getattr(args, "command", None)
    if command == "demo":
        return int(args.parts)
    if command == "simulate":
        return int(args.partitions or 0)
    if command in ("predict", "train"):
        path = args.trajectory if command == "predict" else args.trajectories[0]
        try:
            import h5py

            with h5py.File(path, "r") as f:
                return int(f.attrs.get("n_parts", 0))
        except (OSError, ValueError):
            return 0  # the command itself reports the unreadable file
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxsync`` console script."""
    from ..errors import JaxsyncError

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    from ..parallel.multiprocess import abort_on_error, initialize, launched_by_mpi

    if launched_by_mpi():  # mpiexec -n N, N > 1: join the others before any JAX use
        with abort_on_error():
            initialize()
            _enable_x64()
            return int(args.func(args) or 0)
    from ..parallel.devices import request_cpu_devices

    request_cpu_devices(_parts_of(args))  # one emulated CPU device per part, before JAX starts
    _enable_x64()
    try:
        return int(args.func(args) or 0)
    except JaxsyncError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C: one line, the shell's status for SIGINT
        print("interrupted: no output file was written or replaced (files appear only when "
              "complete); a run with --checkpoint resumes from it when started again",
              file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
