"""XDMF time series for ParaView: ``<stem>.xdmf`` and its heavy data ``<stem>.xdmf.h5``."""

from __future__ import annotations

import dataclasses
import os
from typing import ClassVar

import numpy as np

from ...errors import OutputError
from ..atomic import OutputFile

__all__ = ["XdmfWriter", "xdmf_paths", "write_xdmf_series"]


def xdmf_paths(path: str | os.PathLike) -> tuple[str, str]:
    """(XDMF file, its data file) written for ``path``: ``out/run`` and ``out/run.xdmf``
    both give (``out/run.xdmf``, ``out/run.xdmf.h5``), a data file name that cannot
    collide with a trajectory file ``out/run.h5``."""
    path = os.fspath(path)
    if not path.endswith(".xdmf"):
        path += ".xdmf"
    return path, path + ".h5"


def write_xdmf_series(path: str, data_path: str, points, cell_type: str, cells, times,
                      point_data_series) -> None:
    """Write an XDMF time series at ``path`` whose heavy data go to ``data_path`` (in the
    same folder: the XDMF file names it relative to itself, so the pair can be moved
    together). ``points`` (n, 3), ``cells`` (n_cells, nodes per cell) of the meshio
    ``cell_type``; ``times`` (n_steps,) [s] and ``point_data_series`` n_steps dicts of
    point fields (n, ...). Writes by absolute paths only: the working directory, which
    meshio's own writer would put the data file in, is neither used nor changed."""
    import h5py
    import meshio

    if os.path.dirname(os.path.abspath(path)) != os.path.dirname(os.path.abspath(data_path)):
        raise OutputError(f"the XDMF data file {data_path} must be in the folder of {path}")

    class _AbsoluteDataFile(meshio.xdmf.TimeSeriesWriter):
        # meshio opens "<stem>.h5" relative to the working directory; open ours by its full
        # path instead (it refers to the file by its base name, relative to the .xdmf)
        def __enter__(self):
            self.h5_filename = os.path.abspath(data_path)
            self.h5_file = h5py.File(self.h5_filename, "w")
            return self

    with _AbsoluteDataFile(os.path.abspath(path)) as writer:
        writer.write_points_cells(np.asarray(points), [(cell_type, np.asarray(cells))])
        for time, point_data in zip(times, point_data_series):
            writer.write_data(float(time), point_data=point_data)


@dataclasses.dataclass(frozen=True)
class XdmfWriter:
    """The ``"xdmf"`` writer: :meth:`jaxsync.Trajectory.to_xdmf`, the point field
    ``displacement`` [cm] every ``every`` saved snapshots."""

    every: int = 1
    suffixes: ClassVar[tuple[str, ...]] = (".xdmf",)
    description: ClassVar[str] = "XDMF time series for ParaView (<stem>.xdmf and its data <stem>.xdmf.h5)"

    def outputs(self, path) -> tuple[OutputFile, ...]:
        """The data file, then the ``.xdmf`` that refers to it."""
        xdmf, data = xdmf_paths(path)
        return OutputFile(data, "XDMF data file"), OutputFile(xdmf, "XDMF file")

    def write(self, trajectory, path: str, staged) -> None:
        trajectory.to_xdmf(staged.path(path), every=self.every)
