"""Trajectories: saved displacement histories, HDF5 files and ParaView (XDMF) output.

Every file is written under a temporary name in the target folder and renamed over the
target only when complete, so a failed or interrupted write never replaces a good file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
import tempfile
from typing import Any

import numpy as np

from .errors import CheckpointError
from .mesh import Mesh

__all__ = ["Trajectory", "atomic_path", "atomic_h5"]

FORMAT_VERSION = 1


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success,
    delete it on failure."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".tmp", dir=folder)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; give the usual permissions
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


@contextlib.contextmanager
def atomic_h5(path: str | os.PathLike):
    """Open a new HDF5 file for writing that appears at ``path`` only when complete."""
    import h5py

    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            yield f


@dataclasses.dataclass(frozen=True, eq=False)
class Trajectory:
    """Saved displacements of a run, in the mesh's node numbering.

    Attributes:
        times: (n_saved,) [s].
        displacement: (n_saved, n_nodes, 3) [cm].
        mesh: the mesh.
        dt: time step [s].
        save_every: steps between saved snapshots.
        parameters: problem parameters (E, nu, rho, damping...) for the record.
        parts: per-part data of a distributed run (shared node ids and their
            displacement history, and for synchronization-avoiding runs the part's own
            predictions), or empty.
        synchronized: (n_saved,) bool, False where the snapshot's step was predicted
            by surrogates instead of synchronized (None: all synchronized).
    """

    times: Any
    displacement: Any
    mesh: Mesh
    dt: Any
    save_every: int = 1
    parameters: dict = dataclasses.field(default_factory=dict)
    parts: tuple = ()
    synchronized: Any = None

    @property
    def n_saved(self) -> int:
        return int(np.shape(self.times)[0])

    @property
    def steps(self) -> np.ndarray:
        """(n_saved,) step index of each snapshot."""
        return np.arange(self.n_saved) * self.save_every

    def at_node(self, node: int):
        """(n_saved, 3) displacement history of one node."""
        return self.displacement[:, node, :]

    def save(self, path: str | os.PathLike) -> None:
        """Write an HDF5 file (atomically): ``/times``, ``/displacement``, ``/mesh/points``,
        ``/mesh/tets``, ``/mesh/facets/<name>``, root attributes ``dt``, ``save_every``,
        ``format_version`` and the problem parameters, and per-part groups
        ``/parts/<p>/shared_nodes``, ``/parts/<p>/shared_displacement`` when present."""
        with atomic_h5(path) as f:
            f.attrs["format"] = "jaxsync-trajectory"
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["dt"] = float(self.dt)
            f.attrs["save_every"] = int(self.save_every)
            for key, value in self.parameters.items():
                f.attrs[f"param_{key}"] = value
            f.create_dataset("times", data=np.asarray(self.times))
            if self.synchronized is not None:
                f.create_dataset("synchronized", data=np.asarray(self.synchronized, dtype=bool))
            f.create_dataset("displacement", data=np.asarray(self.displacement), chunks=True,
                             compression="gzip", compression_opts=1, shuffle=True)
            g = f.create_group("mesh")
            g["points"] = self.mesh.points
            g["tets"] = self.mesh.tets
            g["source_node_ids"] = self.mesh.source_node_ids
            facets = g.create_group("facets")
            for name, tri in self.mesh.facet_sets.items():
                facets[name] = tri
            if self.parts:
                f.attrs["n_parts"] = len(self.parts)
                parts = f.create_group("parts")
                for p, part in enumerate(self.parts):
                    pg = parts.create_group(str(p))
                    for key, value in part.items():
                        pg[key] = np.asarray(value)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Trajectory":
        """Read a file written by :meth:`save`; :class:`CheckpointError` if it is not one."""
        import h5py

        path = os.fspath(path)
        if not os.path.exists(path):
            raise CheckpointError(f"trajectory file {path!r} does not exist")
        try:
            with h5py.File(path, "r") as f:
                if f.attrs.get("format") != "jaxsync-trajectory":
                    raise CheckpointError(f"{path} is not a jaxsync trajectory file")
                version = int(f.attrs["format_version"])
                if version > FORMAT_VERSION:
                    raise CheckpointError(f"{path} has format version {version}, newer than this "
                                          f"jaxsync reads ({FORMAT_VERSION}): upgrade jaxsync")
                g = f["mesh"]
                mesh = Mesh(points=g["points"][...], tets=g["tets"][...],
                            facet_sets={k: v[...] for k, v in g["facets"].items()},
                            source_node_ids=g["source_node_ids"][...])
                params = {k[len("param_"):]: _attribute_value(v)
                          for k, v in f.attrs.items() if k.startswith("param_")}
                parts = ()
                if "parts" in f:
                    parts = tuple({k: v[...] for k, v in f["parts"][str(p)].items()}
                                  for p in range(int(f.attrs["n_parts"])))
                synchronized = f["synchronized"][...] if "synchronized" in f else None
                return cls(times=f["times"][...], displacement=f["displacement"][...], mesh=mesh,
                           dt=float(f.attrs["dt"]), save_every=int(f.attrs["save_every"]),
                           parameters=params, parts=parts, synchronized=synchronized)
        except CheckpointError:
            raise
        except Exception as exc:
            raise CheckpointError(f"cannot read trajectory {path}: {exc}") from exc

    def to_xdmf(self, path: str | os.PathLike, *, every: int = 1) -> str:
        """Write an XDMF time series for ParaView with the point field ``displacement``;
        ``every`` thins the snapshots. The heavy data go to ``<stem>.xdmf.h5`` beside it
        (a name that cannot collide with a trajectory file ``<stem>.h5``).

        Both files are written in a temporary folder and moved into place at the end.
        Returns the path of the data file."""
        import meshio

        path = os.fspath(path)
        if not path.endswith(".xdmf"):
            path += ".xdmf"
        folder = os.path.dirname(os.path.abspath(path))
        stem = os.path.splitext(os.path.basename(path))[0]
        data_name = f"{stem}.xdmf.h5"
        os.makedirs(folder, exist_ok=True)
        tmpdir = tempfile.mkdtemp(prefix=".xdmf.", dir=folder)
        try:
            cwd = os.getcwd()
            # meshio writes the .h5 into the working directory, named after the stem.
            os.chdir(tmpdir)
            try:
                with meshio.xdmf.TimeSeriesWriter(f"{stem}.xdmf") as writer:
                    writer.write_points_cells(self.mesh.points, [("tetra", self.mesh.tets)])
                    disp = np.asarray(self.displacement)
                    for i in range(0, self.n_saved, every):
                        writer.write_data(float(self.times[i]), point_data={"displacement": disp[i]})
            finally:
                os.chdir(cwd)
            with open(os.path.join(tmpdir, f"{stem}.xdmf")) as f:
                text = f.read().replace(f">{stem}.h5:/", f">{data_name}:/")
            with open(os.path.join(tmpdir, f"{stem}.xdmf"), "w") as f:
                f.write(text)
            os.replace(os.path.join(tmpdir, f"{stem}.h5"), os.path.join(folder, data_name))
            os.replace(os.path.join(tmpdir, f"{stem}.xdmf"), path)
        finally:
            shutil.rmtree(tmpdir, ignore_errors=True)
        return os.path.join(folder, data_name)


def _attribute_value(value):
    """An HDF5 attribute as a Python value: scalars as numbers, arrays as lists."""
    if getattr(value, "ndim", 0) > 0:
        return value.tolist()
    return value.item() if hasattr(value, "item") else value
