"""The trajectory's own HDF5 file (read back by :meth:`jaxsync.Trajectory.load`)."""

from __future__ import annotations

import dataclasses
import os
from typing import ClassVar

from ..atomic import OutputFile

__all__ = ["Hdf5Writer"]


@dataclasses.dataclass(frozen=True)
class Hdf5Writer:
    """The ``"hdf5"`` writer: :meth:`jaxsync.Trajectory.save` with ``compression`` and
    ``level``."""

    compression: str | None = "gzip"
    level: int = 1
    suffixes: ClassVar[tuple[str, ...]] = (".h5", ".hdf5")
    description: ClassVar[str] = "jaxsync trajectory file (HDF5; jaxsync.Trajectory.load reads it)"

    def outputs(self, path) -> tuple[OutputFile, ...]:
        path = os.fspath(path)
        return (OutputFile(path if path.endswith(self.suffixes) else path + self.suffixes[0], "trajectory"),)

    def write(self, trajectory, path: str, staged) -> None:
        trajectory.save(staged.path(path), compression=self.compression, level=self.level)
