"""Helpers shared by the subcommands: options that several commands take, output files
that must not be overwritten and locations that must be writable before anything runs,
writes that fail as one ``error:`` line, the package's warnings as one ``warning:`` line,
and the processes of an ``mpiexec`` run."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import sys

from ..options import DEFAULT_COMPRESSION, DEFAULT_MODE, Compression, Mode, choices

__all__ = ["add_compression_option", "compression_of", "add_mode_option", "mode_of", "add_sync_option", "sync_of",
           "add_resync_tolerance_option", "resync_tolerance_of", "add_progress_option", "surrogate_defaults",
           "SURROGATE_OPTIONS",
           "add_surrogate_options", "join_negative_values", "accept_negative_numbers", "refuse_to_overwrite",
           "process_count", "is_main_process", "barrier", "add_trained_run_arguments", "load_trained_run",
           "trained_run_inputs",
           "check_outputs", "writing", "written_and_kept", "is_package_warning", "package_warnings", "report_warnings"]


def add_trained_run_arguments(parser) -> None:
    """TRAJECTORY and SURROGATE, ``--config`` and ``--mesh``: a synchronized run and the
    surrogates trained on it (``predict``, ``finetune``)."""
    parser.add_argument("trajectory", help="synchronized distributed trajectory (HDF5) the surrogates were "
                                           "trained on: it defines the partition")
    parser.add_argument("surrogate", help="surrogate file written by jaxsync train (surrogate.h5)")
    parser.add_argument("--config", default=None, help="TOML problem file (default: the cantilever)")
    parser.add_argument("--mesh", default=None, help="mesh file to use instead of the config's")


def trained_run_inputs(args) -> list[str]:
    """The files the commands of :func:`add_trained_run_arguments` read (no output may be one)."""
    return [p for p in (args.trajectory, args.surrogate, args.config, args.mesh) if p]


def load_trained_run(args):
    """(reference trajectory, its partition, the problem, the surrogate file checked against the
    partition) of :func:`add_trained_run_arguments`' arguments; the problem's mesh must be the
    trajectory's (:class:`jaxsync.PartitionError` otherwise)."""
    import numpy as np

    from ..app.config import load_config, problem_from_config
    from ..errors import PartitionError
    from ..io.surrogate_file import load_surrogate
    from ..io.trajectory import Trajectory
    from ..parallel._partitioning import partition_of

    reference = Trajectory.load(args.trajectory)
    part = partition_of(reference)
    # the run's element is the trajectory's (a P2 run's surrogates predict at P2 nodes)
    problem, _ = problem_from_config(load_config(args.config), mesh_file=args.mesh, element=reference.element)
    if (problem.mesh.n_nodes != reference.mesh.n_nodes
            or not np.array_equal(problem.mesh.tets, reference.mesh.tets)):
        raise PartitionError(f"the problem's mesh differs from the mesh of {args.trajectory}; "
                             "pass the same --config/--mesh as the synchronized run")
    return reference, part, problem, load_surrogate(args.surrogate, [p.shared_nodes for p in part.parts])


def add_compression_option(parser) -> None:
    """``--compression``: HDF5 compression of the output trajectory's large datasets."""
    parser.add_argument("--compression", choices=choices(Compression), default=DEFAULT_COMPRESSION,
                        help="HDF5 compression of the output's large datasets (default: %(default)s; "
                             "lzf is faster, none the fastest to write)")


def add_mode_option(parser) -> None:
    """``--mode``: the internal force formulation (paper Remark 2), and
    ``--float32-blocks``: the stored K's blocks in single precision."""
    parser.add_argument("--mode", choices=choices(Mode), default=DEFAULT_MODE,
                        help="internal force: stored sparse K, or element quantities formed every "
                             "step (default: %(default)s)")
    parser.add_argument("--float32-blocks", action="store_true",
                        help="store K's off-diagonal blocks in float32 (state and sums stay float64): a "
                             "faster step on large meshes, displacements within about 1e-6 relative of "
                             "float64 for runs loaded from rest (docs: performance guide); "
                             "--mode preassembled only")


def mode_of(args):
    """The force model of ``--mode`` and ``--float32-blocks``: the mode's name, or
    :class:`jaxsync.fem.forces.Preassembled` with float32 blocks."""
    from ..errors import ConfigError

    if not getattr(args, "float32_blocks", False):
        return args.mode
    if args.mode != "preassembled":
        raise ConfigError("--float32-blocks stores the preassembled K: use it with --mode preassembled")
    from ..fem.forces._internal_force import Preassembled

    return Preassembled(blocks_dtype="float32")


def add_sync_option(parser, deep_halos: bool = False) -> None:
    """``--sync``: how the parts sum shared-node forces; left None unless given, so that
    the library's one default applies (:func:`jaxsync.parallel.multiprocess.default_sync`).
    ``deep_halos``: also offer ``--sync halo`` and ``--halo-depth`` (synchronized runs only)."""
    from ..parallel.exchange._builtin import exchange_names, sync_strategy

    # every registered exchange (jaxsync.solve.register_exchange); without deep halos only
    # those that synchronize every step
    methods = [m for m in exchange_names() if deep_halos or sync_strategy(m).synchronizes_every_step]
    parser.add_argument("--sync", choices=methods, default=None,
                        help="how parts sum shared-node forces every synchronized step: XLA psum of "
                             "the whole interface (emulated devices, gloo between processes, NCCL "
                             "between GPUs), XLA ppermute exchange of the nodes neighbouring devices "
                             "share, or an MPI Allreduce inside the compiled step, one device per "
                             "process"
                             + (", or deep halos: parts grown by --halo-depth layers exchange their "
                                "halo every that many steps, exactly" if deep_halos else "")
                             + " (default: jaxsync.parallel.multiprocess.default_sync(): mpi "
                             "across CPU processes, psum otherwise)")
    if deep_halos:
        parser.add_argument("--halo-depth", type=int, default=None, metavar="K",
                            help="with --sync halo: steps between two exchanges, the layers of "
                                 "neighbouring elements each part also holds (default 1; "
                                 "--save-every and K must divide one another)")


def sync_of(args) -> dict:
    """``{"sync": strategy}`` when ``--sync`` was given (``--sync halo`` with its
    ``--halo-depth``: :class:`jaxsync.Halo`), else ``{}`` (the library's default)."""
    from ..errors import ConfigError
    from ..solve._strategies import Halo

    depth = getattr(args, "halo_depth", None)
    if depth is not None and args.sync != "halo":
        raise ConfigError(f"--halo-depth {depth} needs --sync halo (got --sync {args.sync})")
    if args.sync is None:
        return {}
    return {"sync": Halo(1 if depth is None else depth) if args.sync == "halo" else args.sync}


def compression_of(args) -> str | None:
    """``--compression`` as :meth:`jaxsync.Trajectory.save` takes it."""
    return None if args.compression == "none" else args.compression


def add_resync_tolerance_option(parser, help: str | None = None) -> None:
    """``--resync-tolerance CM|PCT%`` and ``--error-indicator``: error control of the
    synchronization-avoiding run (:func:`resync_tolerance_of` reads them)."""
    parser.add_argument(
        "--resync-tolerance", default=None, metavar="CM|PCT%",
        help=help or "error control: hold the run to this tolerance -- in cm (1e-4) or as a percentage "
                     "of the largest shared-node displacement seen in synchronized steps (2%%): each "
                     "refill cycle's es_hat (the parts' disagreement, paper eq. 26) is checked before it "
                     "runs and the estimated error since the last synchronized state (the force-balance "
                     "defect probed at the saved steps, see --error-indicator) after; above it the run "
                     "goes back to the last synchronized state and recomputes with the synchronized "
                     "solver (default: never)")
    parser.add_argument(
        "--error-indicator", choices=("estimate", "es_hat"), default="estimate",
        help="what --resync-tolerance holds: 'estimate' (default: es_hat and the estimated error, which "
             "also sees errors that every part makes alike; one exchange of partial forces per saved "
             "step) or 'es_hat' (the parts' disagreement only, no exchange while predicting)")


def add_online_learning_option(parser) -> None:
    """``--learn`` and ``--learn-budget``: learning while synchronized
    (:func:`online_learning_of` reads them)."""
    parser.add_argument(
        "--learn", action="store_true",
        help="with --resync-tolerance: after every rejected cycle, train the surrogates on the steps recomputed "
             "synchronized (and on windows replayed from the first synchronized stretch) before predicting "
             "again: least squares for the linear model, Adam steps for the LSTM (jaxsync.surrogate.training)")
    parser.add_argument(
        "--learn-budget", type=float, default=None, metavar="SECONDS",
        help="the most wall time all updates of the run may take together (default: 120)")
    parser.add_argument(
        "--learn-save", default=None, metavar="FILE",
        help="with --learn: write the learned surrogates to this surrogate file (.h5) after every update "
             "that changed them, to run or learn from again (refused if it exists, unless --force)")


def online_learning_of(args):
    """The :class:`jaxsync.surrogate.OnlineLearning` of ``--learn`` and ``--learn-budget``,
    or None (checked: they go with ``--resync-tolerance``)."""
    from ..errors import ConfigError

    learn, budget = getattr(args, "learn", False), getattr(args, "learn_budget", None)
    save_to = getattr(args, "learn_save", None)
    if not learn:
        if budget is not None:
            raise ConfigError("--learn-budget sets the time budget of --learn; give --learn too")
        if save_to is not None:
            raise ConfigError("--learn-save writes the surrogates that --learn updates; give --learn too")
        return None
    if args.resync_tolerance is None or str(args.resync_tolerance).lower() == "none":
        raise ConfigError("--learn learns from the steps that error control recomputes after a rejected cycle: "
                          "give --resync-tolerance too (e.g. --resync-tolerance 1%)")
    from ..surrogate.training._online import OnlineLearning

    return OnlineLearning(**({} if budget is None else {"budget_seconds": budget}), save_to=save_to)


def resync_tolerance_of(args, value=None):
    """The :class:`jaxsync.ResyncTolerance` of ``--resync-tolerance`` (or ``value``),
    ``--error-indicator`` and (where the command has them) ``--learn``,
    ``--learn-budget``; None without a tolerance."""
    from ..solve._strategies import ResyncTolerance

    value = args.resync_tolerance if value is None else value
    learning = online_learning_of(args)
    if value is None or str(value).lower() == "none":
        return None
    tolerance = ResyncTolerance.parse(value)
    return dataclasses.replace(tolerance, indicator=getattr(args, "error_indicator", "estimate"), learning=learning)


def add_progress_option(parser, what: str = "the progress bar") -> None:
    parser.add_argument("--no-progress", action="store_true", help=f"hide {what}")


def surrogate_defaults() -> dict:
    """Defaults of the surrogate options, read from the library's settings (as
    ``jaxsync train`` reads them): :class:`jaxsync.surrogate.Sampling` (n_s, n_p, n_f),
    :class:`jaxsync.surrogate.ArchitectureChoice` (n_H, k) and
    :class:`jaxsync.surrogate.TrainConfig` (eta0, gamma, epochs)."""
    from ..surrogate import ArchitectureChoice, Sampling, TrainConfig

    sampling, architecture, config = Sampling(), ArchitectureChoice(), TrainConfig()
    return {"n_s": sampling.n_s, "n_past": sampling.n_past, "n_future": sampling.n_future,
            "n_hidden": architecture.n_hidden, "n_layers": architecture.n_layers, "eta0": config.eta0,
            "gamma": config.gamma, "epochs": config.n_epochs}


SURROGATE_OPTIONS = (
    # (flags, type, dest = key of surrogate_defaults(), help); the spellings of jaxsync train
    (("--n-s",), int, "n_s", "sampling stride n_s in steps"),
    (("--n-past",), int, "n_past", "input snapshots n_p"),
    (("--n-future",), int, "n_future", "predicted snapshots n_f"),
    (("--n-hidden", "--hidden"), int, "n_hidden", "LSTM encoder hidden size n_H (paper: 100)"),
    (("--n-layers", "--layers"), int, "n_layers", "bidirectional encoder layers k"),
    (("--eta0",), float, "eta0", "initial learning rate (paper: 5e-4)"),
    (("--gamma",), float, "gamma", "per-epoch learning-rate decay (paper: 0.9995)"),
)


def add_surrogate_options(parser, case_defaults: bool = False) -> None:
    """The sampling, network and schedule options of the surrogates
    (:data:`SURROGATE_OPTIONS`), with the defaults of :func:`surrogate_defaults` (the
    laptop schedule); with ``case_defaults`` they default to None and the command fills
    in its case's (``jaxsync demo``: :func:`jaxsync.app.demo.demo_defaults`)."""
    defaults = surrogate_defaults()
    for flags, kind, dest, text in SURROGATE_OPTIONS:
        if case_defaults:
            help_text = f"{text} (default: the case's; cantilever {defaults[dest]})"
        else:
            help_text = f"{text} (default: %(default)s)"
        parser.add_argument(*flags, dest=dest, type=kind, default=None if case_defaults else defaults[dest],
                            help=help_text)


NEGATIVE_NUMBER = r"^-(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$"


def join_negative_values(args: list[str]) -> list[str]:
    """``args`` with every negative number that follows an option joined to it:
    ``["--dt", "-1e-4"]`` becomes ``["--dt=-1e-4"]``, the spelling argparse always reads
    as a value (before Python 3.14 it takes ``-1e-4`` alone for an option name and stops
    with "expected one argument"). Tokens after ``--``, and options already given as
    ``--opt=value``, are left as they are; an option that takes no value is still refused
    by argparse ("ignored explicit argument")."""
    import re

    number = re.compile(NEGATIVE_NUMBER)
    out: list[str] = []
    for k, arg in enumerate(args):
        previous = out[-1] if out else None
        if (previous is not None and number.match(arg) and previous.startswith("-") and "=" not in previous
                and not number.match(previous) and "--" not in args[:k]):
            out[-1] = f"{previous}={arg}"
        else:
            out.append(arg)
    return out


def accept_negative_numbers(parser: argparse.ArgumentParser) -> None:
    """Let option values such as ``--dt -1e-4`` parse as numbers (and be refused by the
    package's own checks with a clear message) instead of argparse's "expected one
    argument": the parser's public :meth:`~argparse.ArgumentParser.parse_known_args`
    (which ``parse_args`` and a parent's subcommand dispatch call) first joins them to
    their option (:func:`join_negative_values`). For parsers whose options take no
    negative-number-like names."""
    parse_known_args = parser.parse_known_args

    def parse_with_negative_values(args=None, namespace=None):
        args = sys.argv[1:] if args is None else list(args)
        return parse_known_args(join_negative_values(args), namespace)

    parser.parse_known_args = parse_with_negative_values


def refuse_to_overwrite(paths: list[str], *, force: bool, checkpoint: str | None = None,
                        inputs=(), options: str = "-o") -> None:
    """Before anything runs: ConfigError when two outputs (or an output and the checkpoint)
    are the same file, when an output is one of the command's ``inputs`` (even with
    ``force``: a command never writes over what it reads), or when an output exists and
    ``force`` is False (the message names ``options``, those that choose the locations).
    Then each output is claimed (:func:`jaxsync.io.claim_output`, inside the command
    line's :func:`jaxsync.io.claimed_outputs`): a second jaxsync
    process writing the same file stops at once, and a file that appears while this one
    runs is never replaced."""
    from ..errors import ConfigError
    from ..io.atomic import claim_output, claiming

    def key(path):
        return os.path.normcase(os.path.realpath(path))

    seen: dict[str, str] = {}
    for path in paths + ([checkpoint] if checkpoint else []):
        if key(path) in seen:
            raise ConfigError(f"{path} is used for two outputs (also as {seen[key(path)]}); give the "
                              "trajectory, XDMF, VTU and checkpoint files different names")
        seen[key(path)] = path
    read = {key(p): p for p in inputs if p}
    for path in paths:
        if key(path) in read:
            raise ConfigError(f"the output {path} is also an input of this command ({read[key(path)]}): writing it "
                              "would destroy what the command reads, even with --force; choose another output name")
    existing = [path for path in paths if os.path.exists(path)]
    if existing and not force:
        names = ", ".join(existing)
        raise ConfigError(f"{names} already exist{'s' if len(existing) == 1 else ''} (the output "
                          "of an earlier run?); pass --force to overwrite, or choose another "
                          f"location with {options}")
    if claiming():  # the command line's scope (a library caller has none)
        for path in paths:  # a folder output (a VTU series' step files) is claimed as one
            claim_output(path, replace=force, folder=os.path.isdir(path))


def process_count() -> int:
    """Processes of this run (``mpiexec -n N``: N; otherwise 1)."""
    from ..parallel.multiprocess import process_count as count

    return count()


def is_main_process() -> bool:
    """True on rank 0, which prints and writes files."""
    from ..parallel.multiprocess import is_main_process as main

    return main()


def barrier() -> None:
    """Wait for all processes (a no-op in a single-process run)."""
    if process_count() > 1:
        from ..parallel.multiprocess import world

        world().Barrier()


def check_outputs(*outputs) -> None:
    """Refuse, before anything runs, output locations that cannot be written: each of
    ``outputs`` is ``(path, what, option)`` for a file, or ``(path, what, option, True)``
    for a folder the command fills; None paths are skipped
    (:func:`jaxsync.io.check_writable`; :class:`jaxsync.io.OutputError` naming the path,
    why, and the option that chooses another location)."""
    from ..io.atomic import check_writable

    for path, what, option, *folder in outputs:
        if path:
            check_writable(path, what=what, option=option, folder=bool(folder and folder[0]))


def _stat(path: str):
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_ino, st.st_size, st.st_mtime_ns


@contextlib.contextmanager
def writing(*paths):
    """Write ``paths`` inside the block: an :class:`OSError` (a full disk...) becomes one
    :class:`jaxsync.io.OutputError` naming them, and each of them the block did replace
    or create counts as written (:func:`jaxsync.io.note_written`), also on failure; the
    files written before are kept."""
    from ..io.atomic import OutputError, note_written, os_reason

    paths = [os.fspath(p) for p in paths]
    before = {p: _stat(p) for p in paths}
    try:
        yield
    except OSError as exc:
        changed = [p for p in paths if _stat(p) is not None and _stat(p) != before[p]]
        for p in changed:
            note_written(p)
        if isinstance(exc, OutputError):
            raise
        failed = [p for p in paths if p not in changed] or paths
        raise OutputError(f"could not write {', '.join(failed)}: {os_reason(exc)} (free space, or choose "
                          "another location, and run again)") from exc
    for p in paths:
        if os.path.exists(p):
            note_written(p)


def written_and_kept(written) -> str:
    """What a failed command leaves: the files of ``written`` (from
    :func:`jaxsync.io.recording_writes`) that exist, for its error line."""
    kept = [p for p in dict.fromkeys(written) if os.path.exists(p)]
    if not kept:
        return "no output file was written"
    return f"written before the failure and kept: {', '.join(kept)}"


def is_package_warning(category) -> bool:
    """True for the warning classes of jaxsync itself (MeshWarning, MassScalingWarning,
    RolloutWarning, ReducedPrecisionWarning and any later one: every Warning subclass
    defined in the package)."""
    return (isinstance(category, type) and issubclass(category, Warning)
            and getattr(category, "__module__", "").split(".")[0] == "jaxsync")


def _show_warning(message, category=None) -> None:
    if process_count() > 1 and not is_main_process():
        return  # rank 0 speaks for all
    text = " ".join(str(message).split())
    if category is not None and not is_package_warning(category):
        text += f" ({getattr(category, '__name__', category)})"  # another library's: say whose kind
    print(f"warning: {text}", file=sys.stderr)


@contextlib.contextmanager
def package_warnings():
    """Inside the block, every warning is shown as one line, ``warning: <message>``, on
    stderr (by rank 0 of an ``mpiexec`` run), instead of Python's two lines with the source
    line that raised it; one from another library (JAX, NumPy...) names its category at
    the end. Which warnings are shown follows the filters as usual."""
    import warnings

    with warnings.catch_warnings():
        def show(message, category, filename, lineno, file=None, line=None):
            _show_warning(message, category)

        warnings.showwarning = show
        yield


def report_warnings(caught) -> None:
    """Show warnings recorded with ``warnings.catch_warnings(record=True)`` as one
    ``warning: ...`` line each on stderr (:func:`package_warnings`); a repeated warning
    (the same class and text) once."""
    seen = set()
    for w in caught:
        key = (w.category, str(w.message))
        if key in seen:
            continue
        seen.add(key)
        _show_warning(w.message, w.category)
