"""Output writers: the formats a :class:`jaxsync.Trajectory` is written in, found by name
or by file suffix through one registry.

A writer is any object with

* ``suffixes``: the file suffixes it claims (``(".xdmf",)``), the first one its default;
* ``description``: one line that says what it writes;
* ``outputs(path)``: the :class:`~jaxsync.io.OutputFile` s it writes for the ``path`` a
  user gives (normalised: a missing suffix added), in the order they are moved into
  place (the file that refers to the others last); the last one is the main output;
* ``write(trajectory, path, staged)``: write them, each at ``staged.path(output.path)``
  (``path``: the main output; ``staged``: a :class:`~jaxsync.io.StagedOutputs`).

:func:`write_output` runs a writer: it stages the outputs in a hidden folder beside them
and moves them into place only when the writer returned, so every writer, built-in or
not, gets the guarantees of :mod:`jaxsync.io`: a failed or interrupted write leaves the
earlier files as they were, ``overwrite=False`` never replaces a file, and a failure is an
:class:`~jaxsync.errors.OutputError` naming the output. :class:`OutputWriter` is a base
class that supplies ``outputs`` for a writer of one file.

The registry (:func:`register_writer`, :func:`writer_for`, :func:`registered_writers`,
:func:`unregister_writer`)
is the one place that maps a format's name and suffixes to its writer; it holds the
built-in ``"hdf5"`` (:class:`Hdf5Writer`, the trajectory file that
:meth:`jaxsync.Trajectory.load` reads), ``"xdmf"`` (:class:`XdmfWriter`) and ``"vtu"``
(:class:`VtuWriter`), and ``jaxsync simulate``'s ``--xdmf`` and ``--vtu`` (``[run] xdmf``
and ``vtu``) write through it. Adding a format is one class and one
:func:`register_writer` call (the guide *Extending the output*).
"""

from __future__ import annotations

import os
from typing import Any, Protocol, runtime_checkable

from ...errors import OutputError
from ..atomic import OutputFile, StagedOutputs, staged_outputs
from ._hdf5 import Hdf5Writer
from ._vtu import VtuWriter, check_vtu_location, vtu_series_paths
from ._xdmf import XdmfWriter, xdmf_paths

__all__ = ["Writer", "OutputWriter", "register_writer", "unregister_writer", "writer_for", "registered_writers",
           "write_output", "Hdf5Writer", "XdmfWriter", "VtuWriter", "OutputFile", "StagedOutputs",
           "xdmf_paths", "vtu_series_paths", "check_vtu_location"]


@runtime_checkable
class Writer(Protocol):
    """What :func:`write_output` and the registry need of a writer (module docstring)."""

    suffixes: tuple[str, ...]
    description: str

    def outputs(self, path: str) -> tuple[OutputFile, ...]: ...

    def write(self, trajectory, path: str, staged: StagedOutputs) -> None: ...


class OutputWriter:
    """Base class of a writer of one file: subclasses set ``suffixes`` and
    ``description`` and define :meth:`write`; :meth:`outputs` is the ``path`` given, with
    the first suffix added when it has none of them."""

    suffixes: tuple[str, ...] = ()
    description: str = "output"

    def path_for(self, path: str | os.PathLike) -> str:
        """``path`` with the writer's first suffix added unless it ends with one of them."""
        path = os.fspath(path)
        return path if path.endswith(tuple(self.suffixes)) else path + self.suffixes[0]

    def outputs(self, path: str | os.PathLike) -> tuple[OutputFile, ...]:
        """The one file written for ``path``."""
        return (OutputFile(self.path_for(path), self.description),)

    def write(self, trajectory, path: str, staged: StagedOutputs) -> None:
        raise NotImplementedError(f"{type(self).__name__}.write")


_WRITERS: dict[str, Any] = {}
"""The registry: format name -> writer (explicit global state, changed only by
:func:`register_writer`)."""


def register_writer(name: str, writer, *, replace: bool = False) -> None:
    """Register ``writer`` (an object of the :class:`Writer` protocol) under ``name``, so
    that :func:`writer_for` finds it by ``name`` and by its suffixes.

    Raises:
        OutputError: a ``name`` taken by another writer (pass ``replace=True`` to
            replace it), a suffix that another registered writer claims, or an object
            that lacks ``suffixes``, ``description``, ``outputs`` or ``write``.
    """
    if not isinstance(name, str) or not name or os.sep in name or "." in name:
        raise OutputError(f"a writer's name is a word such as 'csv', got {name!r}")
    if not isinstance(writer, Writer) or not writer.suffixes or not all(
            isinstance(s, str) and s.startswith(".") for s in writer.suffixes):
        raise OutputError(f"register_writer({name!r}, ...): {writer!r} is not a writer: it needs suffixes (a tuple "
                          "of '.ext' strings), description, outputs(path) and write(trajectory, path, staged) "
                          "(jaxsync.io.writers.OutputWriter supplies outputs)")
    if name in _WRITERS and not replace:
        raise OutputError(f"an output writer named {name!r} is registered already ({_WRITERS[name].description}); "
                          "choose another name, or pass replace=True")
    for other, registered in _WRITERS.items():
        shared = set(registered.suffixes) & set(writer.suffixes)
        if other != name and shared:
            raise OutputError(f"the suffix {sorted(shared)[0]} is claimed by the writer {other!r} already; give "
                              f"{name!r} other suffixes")
    _WRITERS[name] = writer


def unregister_writer(name: str) -> None:
    """Remove the writer registered under ``name`` (OutputError: none is)."""
    if name not in _WRITERS:
        raise OutputError(f"no output writer is registered under {name!r}; registered: {', '.join(_WRITERS)}")
    del _WRITERS[name]


def registered_writers() -> dict[str, Any]:
    """{name: writer} of every registered writer (a copy)."""
    return dict(_WRITERS)


def writer_for(name_or_path) -> Any:
    """The writer of a format: ``name_or_path`` is a registered name (``"xdmf"``), a path
    whose suffix a registered writer claims (``"out/run.pvd"``; the longest suffix wins),
    or a writer object (returned as it is).

    Raises:
        OutputError: neither a name nor a claimed suffix; it lists the registered ones.
    """
    if isinstance(name_or_path, Writer):
        return name_or_path
    text = os.fspath(name_or_path)
    if text in _WRITERS:
        return _WRITERS[text]
    claims = [(len(s), w) for w in _WRITERS.values() for s in w.suffixes if text.endswith(s)]
    if claims:
        return max(claims, key=lambda c: c[0])[1]
    known = "; ".join(f"{n} ({', '.join(w.suffixes)}): {w.description}" for n, w in _WRITERS.items())
    raise OutputError(f"no output writer for {text!r}: give a registered format name or a file name with its "
                      f"suffix; registered: {known}")


def write_output(trajectory, path: str | os.PathLike, writer=None, *, overwrite: bool = True) -> str:
    """Write ``trajectory`` at ``path`` with ``writer`` (a name, a writer, or None: found
    by the suffix of ``path``), every output staged and moved into place only when the
    writer succeeded (:func:`jaxsync.io.staged_outputs`). ``overwrite=False`` never
    replaces an existing file: it is kept, and the new one goes beside it
    (``<stem>.conflict-<k><ext>``, :class:`OutputError` naming both).

    Returns the path of the main output (the last of ``writer.outputs(path)``)."""
    writer = writer_for(path if writer is None else writer)
    outputs = tuple(writer.outputs(os.fspath(path)))
    main = outputs[-1].path
    with staged_outputs(outputs, main=main, replace=overwrite) as staged:
        writer.write(trajectory, main, staged)
    return main


for _name, _writer in (("hdf5", Hdf5Writer()), ("xdmf", XdmfWriter()), ("vtu", VtuWriter())):
    register_writer(_name, _writer)
del _name, _writer
