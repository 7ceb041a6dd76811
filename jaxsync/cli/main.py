"""The ``jaxsync`` command line: ``demo``, ``simulate``, ``train``, ``predict``, ``finetune``, ``report``,
``unload``.

This module builds the parser from the subcommand modules of :mod:`jaxsync.cli` and
dispatches to the chosen one. Errors of the package's own types are printed as one line
(``error: ...``) with exit status 2; anything else is a bug and keeps its traceback. Every
command checks the locations it will write before it computes anything; a write that fails
all the same (a full disk) is such an error too (:class:`jaxsync.io.OutputError`), and its
line names the files written before it, which are kept. The package's own warnings are shown
as one line (``warning: ...``; :func:`jaxsync.cli.common.package_warnings`).

Under ``mpiexec -n N`` (N > 1, detected from the launcher's environment) every rank joins
the others through ``jax.distributed`` before using JAX (:mod:`jaxsync.parallel.multiprocess`),
only rank 0 prints and writes files, and an error on any rank ends the whole job with a
non-zero status (the error is printed with its rank) instead of leaving the others waiting.

Option names are the same in every command: ``--parts`` is a count of parts (``simulate``
still accepts its former ``--partitions``), ``--mode``, ``--sync``, ``--compression`` and
``--component`` take their choices from :mod:`jaxsync.options`.

Start-up: the parser is built without JAX or any other numerical library (``jaxsync``
imports its names on first use, :mod:`jaxsync.lazy`), so that ``--help``, ``--version``
and an argument error answer at once; a command imports what it uses when it runs, after
the emulated CPU devices are requested and float64 is switched on.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable

from . import demo, finetune, predict, report, simulate, unload

__all__ = ["build_parser", "main", "parts_of", "SubcommandParser", "DEFERRED_HELP"]

# The subcommands whose options take their defaults from the surrogate settings, in modules
# that import JAX and optax: their line of ``jaxsync --help`` (the help their parser
# function gives), the rest of their parser made on first use (:class:`SubcommandParser`).
DEFERRED_HELP = {
    "demo": "run the whole pipeline on the built-in cantilever (or --case vessel) and print a summary",
    "train": "train the per-part LSTM surrogates on trajectory files",
}


def _enable_x64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


class SubcommandParser(argparse.ArgumentParser):
    """The parser of one subcommand, whose arguments may be added on first use
    (:meth:`define_on_first_use`): when it parses, formats its help or usage, or its
    actions are read, all of which go through its list of actions."""

    def __init__(self, *args, **kwargs):
        self._define = None
        super().__init__(*args, **kwargs)

    def define_on_first_use(self, define: Callable[[argparse.ArgumentParser], None]) -> None:
        """Call ``define(self)``, which adds the parser's arguments, the first time the
        parser is used, instead of now."""
        self._define = define

    @property
    def _actions(self) -> list:
        define, self._define = self._define, None
        if define is not None:
            define(self)
        return self._action_list

    @_actions.setter
    def _actions(self, actions: list) -> None:
        self._action_list = actions


class _MadeParser:
    """argparse's subparsers, for a function that adds a subcommand (``add_parser``, then
    its arguments), when the subcommand's parser exists already: its ``add_parser`` sets
    the parser's description (and any other setting but the help line) and returns it."""

    def __init__(self, parser: argparse.ArgumentParser):
        self.parser = parser

    def add_parser(self, name: str, *, help: str | None = None, **settings) -> argparse.ArgumentParser:
        for key, value in settings.items():
            setattr(self.parser, key, value)
        return self.parser


def _add_train_parser(subparsers) -> None:
    from .train import add_train_parser

    add_train_parser(subparsers)


def build_parser() -> argparse.ArgumentParser:
    """The ``jaxsync`` argument parser with all subcommands.

    Building it imports no numerical library (JAX, SciPy, h5py...), so that ``--help``,
    ``--version`` and a mistyped option answer at once; a subcommand imports what it uses
    when it runs. The options of ``demo`` and ``train`` are added when the subcommand is
    parsed or its help shown (:data:`DEFERRED_HELP`)."""
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="jaxsync",
        description="Differentiable, distributed explicit FEM for linear elastodynamics on "
                    "tetrahedra, with LSTM surrogates that replace synchronization.")
    parser.add_argument("--version", action="version", version=f"jaxsync {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=SubcommandParser)
    for name, add_parser in (("demo", demo.add_parser), ("simulate", simulate.add_parser),
                             ("train", _add_train_parser), ("predict", predict.add_parser),
                             ("finetune", finetune.add_parser), ("report", report.add_parser),
                             ("unload", unload.add_parser)):
        if name in DEFERRED_HELP:
            subparser = subparsers.add_parser(name, help=DEFERRED_HELP[name])
            subparser.define_on_first_use(lambda made, add_parser=add_parser: add_parser(_MadeParser(made)))
        else:
            add_parser(subparsers)
    return parser


def parts_of(args) -> int:
    """How many parts the command runs (0: none), read without starting JAX."""
    command = getattr(args, "command", None)
    if command == "demo":
        from .demo import demo_parts

        return demo_parts(args)
    if command == "simulate":
        return int(args.parts or 0)
    if command in ("predict", "finetune", "train"):
        path = args.trajectories[0] if command == "train" else args.trajectory
        try:
            import h5py

            with h5py.File(path, "r") as f:
                return int(f.attrs.get("n_parts", 0))
        except (OSError, ValueError):
            return 0  # the command itself reports the unreadable file
    return 0


def _run(args) -> int:
    """Run the chosen command: the package's warnings as one line each, and a failed
    write (:class:`jaxsync.io.OutputError`) told with the files written before it."""
    from ..io.atomic import OutputError, claimed_outputs, recording_writes
    from .common import package_warnings, written_and_kept

    with recording_writes() as written, package_warnings(), claimed_outputs():
        try:
            return int(args.func(args) or 0)
        except OutputError as exc:
            raise OutputError(f"{exc}; {written_and_kept(written)}") from exc
        except KeyboardInterrupt as exc:
            exc.written = list(dict.fromkeys(written))  # what main's line names as kept
            raise


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
            return _run(args)
    from ..parallel.devices import request_cpu_devices

    request_cpu_devices(parts_of(args))  # one emulated CPU device per part, before JAX starts
    _enable_x64()
    try:
        return _run(args)
    except JaxsyncError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C: one line, the shell's status for SIGINT
        kept = [p for p in getattr(exc, "written", ()) if os.path.exists(p)]
        done = (f"the files completed before were kept ({', '.join(kept)}), no other was written or replaced"
                if kept else "no output file was written or replaced")
        print(f"interrupted: {done} (files appear only when complete){resume_hint(args)}", file=sys.stderr)
        return 130


def resume_hint(args) -> str:
    """How an interrupted command goes on, for its Ctrl-C line ("" when it cannot)."""
    command = getattr(args, "command", None)
    if command == "simulate":
        if getattr(args, "checkpoint", None):
            return f"; the same command resumes from the checkpoint {args.checkpoint}"
        return "; a run with --checkpoint PATH can be resumed when interrupted"
    if command == "train" and getattr(args, "state_every", None):
        state = os.path.join(args.output, "training_state.h5")
        return f"; the same command resumes from the training state {state} if one was written"
    return ""
