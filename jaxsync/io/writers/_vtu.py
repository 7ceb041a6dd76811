"""VTU series for ParaView: a ``.pvd`` collection and a folder of one ``.vtu`` per snapshot."""

from __future__ import annotations

import dataclasses
import os
from typing import ClassVar

from ...errors import OutputError
from ..atomic import OutputFile

__all__ = ["VtuWriter", "vtu_series_paths", "check_vtu_location", "is_vtu_series", "write_pvd"]


def vtu_series_paths(path: str | os.PathLike) -> tuple[str, str]:
    """(collection file, folder of the step files) that :meth:`jaxsync.Trajectory.to_vtu`
    writes for ``path``: ``out/run``, ``out/run.pvd`` and ``out/run/`` all give
    (``out/run.pvd``, ``out/run``)."""
    text = os.fspath(path)
    prefix = text.rstrip("/" + os.sep)
    if prefix.endswith(".pvd"):
        prefix = prefix[:-len(".pvd")]
    if os.path.basename(prefix) in ("", ".", ".."):
        raise OutputError(f"cannot write a VTU series at {text!r}: give a prefix that ends in a "
                          "name, such as out/run (out/run.pvd and the folder out/run/)")
    return prefix + ".pvd", prefix


def check_vtu_location(path: str | os.PathLike) -> tuple[str, str]:
    """:func:`vtu_series_paths` of ``path``, with an :class:`OutputError` where
    :meth:`jaxsync.Trajectory.to_vtu` would refuse to write: the collection's name is a
    folder, or the folder of the step files exists and holds something else than ``.vtu``
    files."""
    pvd, folder = vtu_series_paths(path)
    if os.path.isdir(pvd):
        raise OutputError(f"cannot write the VTU collection {pvd}: it is a folder; choose "
                          "another prefix")
    if os.path.lexists(folder) and not is_vtu_series(folder):
        raise OutputError(
            f"cannot write the VTU step files into {folder}: it exists and is not a VTU series "
            "(a folder of .vtu files only); choose another prefix, or remove it")
    return pvd, folder


def is_vtu_series(folder: str) -> bool:
    """A folder that holds nothing but ``.vtu`` files (what :meth:`jaxsync.Trajectory.to_vtu`
    writes)."""
    if not os.path.isdir(folder) or os.path.islink(folder):
        return False
    with os.scandir(folder) as entries:
        return all(e.is_file(follow_symlinks=False) and e.name.endswith(".vtu") for e in entries)


def write_pvd(path: str, entries: list[tuple[float, str]]) -> None:
    """A ParaView collection listing (time [s], file relative to it) ``entries``; times in
    full precision."""
    from xml.sax.saxutils import quoteattr

    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             "  <Collection>"]
    lines += [f'    <DataSet timestep="{time!r}" group="" part="0" file={quoteattr(name)}/>'
              for time, name in entries]
    lines += ["  </Collection>", "</VTKFile>", ""]
    with open(path, "w") as f:
        f.write("\n".join(lines))


@dataclasses.dataclass(frozen=True)
class VtuWriter:
    """The ``"vtu"`` writer: :meth:`jaxsync.Trajectory.to_vtu` every ``every`` saved
    snapshots; the path is the series' prefix (``out/run`` or ``out/run.pvd``)."""

    every: int = 1
    suffixes: ClassVar[tuple[str, ...]] = (".pvd",)
    description: ClassVar[str] = "VTU series for ParaView (<prefix>.pvd and <prefix>/<name>_NNNNNN.vtu)"

    def outputs(self, path) -> tuple[OutputFile, ...]:
        """The folder of the step files, then the collection that lists them."""
        pvd, folder = check_vtu_location(path)
        return OutputFile(folder, "VTU step files", folder=True), OutputFile(pvd, "VTU collection")

    def write(self, trajectory, path: str, staged) -> None:
        trajectory.to_vtu(staged.path(path), every=self.every)
