"""The ``jaxsync`` command line: ``demo``, ``simulate``, ``train``, ``predict``, ``finetune``, ``report``.

This module builds the parser from the subcommand modules (:mod:`jaxsync.app.commands`;
``train`` from :mod:`jaxsync.app.train`) and dispatches to the chosen one. Errors of the
package's own types are printed as one line (``error: ...``) with exit status 2; anything
else is a bug and keeps its traceback. Every command checks the locations it will write
before it computes anything; a write that fails all the same (a full disk) is such an
error too (:class:`jaxsync.io.OutputError`), and its line names the files written before
it, which are kept. The package's own warnings are shown as one line (``warning: ...``;
:func:`jaxsync.app.commands.common.package_warnings`).

Under ``mpiexec -n N`` (N > 1, detected from the launcher's environment) every rank joins
the others through ``jax.distributed`` before using JAX (:mod:`jaxsync.parallel.multiprocess`),
only rank 0 prints and writes files, and an error on any rank ends the whole job with a
non-zero status (the error is printed with its rank) instead of leaving the others waiting.

Option names are the same in every command: ``--parts`` is a count of parts (``simulate``
still accepts its former ``--partitions``), ``--mode``, ``--sync``, ``--compression`` and
``--component`` take their choices from :mod:`jaxsync.options`.
"""

from __future__ import annotations

import argparse
import os
import sys

from .commands import demo, finetune, predict, report, simulate

__all__ = ["build_parser", "main", "parts_of"]


def _enable_x64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


def build_parser() -> argparse.ArgumentParser:
    """The ``jaxsync`` argument parser with all subcommands."""
    from .. import __version__
    from .train import add_train_parser

    parser = argparse.ArgumentParser(
        prog="jaxsync",
        description="Differentiable, distributed explicit FEM for linear elastodynamics on "
                    "tetrahedra, with LSTM surrogates that replace synchronization.")
    parser.add_argument("--version", action="version", version=f"jaxsync {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    demo.add_parser(subparsers)
    simulate.add_parser(subparsers)
    add_train_parser(subparsers)
    predict.add_parser(subparsers)
    finetune.add_parser(subparsers)
    report.add_parser(subparsers)
    return parser


def parts_of(args) -> int:
    """How many parts the command runs (0: none), read without starting JAX."""
    command = getattr(args, "command", None)
    if command == "demo":
        from .commands.demo import demo_parts

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
    from ..io import OutputError, recording_writes
    from .commands.common import package_warnings, written_and_kept

    with recording_writes() as written, package_warnings():
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
        print(f"interrupted: {done} (files appear only when complete); a run with --checkpoint resumes "
              "from it when started again", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
