"""Trajectories: saved displacement histories, HDF5 files and ParaView (XDMF) output.

Every file is written under a temporary name in the target folder and renamed over the
target only when complete, so a failed or interrupted write never replaces a good file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import shutil
import tempfile
from typing import Any, Mapping

import numpy as np

from .errors import CheckpointError
from .fem.mesh import Mesh

__all__ = ["Trajectory", "atomic_path", "atomic_h5", "array_checksum"]

FORMAT_VERSION = 1


STALE_TEMP_AGE_S = 3600.0
"""A temporary file of :func:`atomic_path` whose writer cannot be checked (another host,
or written by an older jaxsync) counts as abandoned when unmodified for this long."""


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success,
    delete it on failure.

    The temporary file is ``.<name>.<pid>@<host>.<random>.tmp``. A writer killed hard
    (SIGKILL, power loss) cannot delete it, so every write first removes the temporary
    files of the same target left by writers that are gone: on this host, those whose
    process no longer exists; from another host or an older jaxsync (no owner in the
    name), those unmodified for :data:`STALE_TEMP_AGE_S`. Live concurrent writers keep
    theirs."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    prefix = f".{os.path.basename(path)}."
    _remove_stale_temporaries(folder, prefix)
    fd, tmp = tempfile.mkstemp(prefix=f"{prefix}{os.getpid()}@{_host_tag()}.", suffix=".tmp",
                               dir=folder)
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


def _host_tag() -> str:
    """This host's name as it goes into temporary file names (letters, digits, '-')."""
    import re
    import socket

    return re.sub(r"[^A-Za-z0-9-]", "-", socket.gethostname())[:64] or "host"


def _process_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return True  # cannot tell: keep the file
    return True


def _remove_stale_temporaries(folder: str, prefix: str) -> None:
    """Delete ``<prefix><pid>@<host>.<random>.tmp`` files whose writer is gone, and
    ``<prefix><random>.tmp`` files (older jaxsync) unmodified for STALE_TEMP_AGE_S."""
    import re
    import time

    owned = re.compile(re.escape(prefix) + r"(\d+)@([A-Za-z0-9-]+)\.[A-Za-z0-9_]+\.tmp$")
    legacy = re.compile(re.escape(prefix) + r"[a-z0-9_]{8}\.tmp$")  # mkstemp's 8 characters
    try:
        names = [n for n in os.listdir(folder) if n.startswith(prefix) and n.endswith(".tmp")]
    except OSError:
        return
    host, now = _host_tag(), time.time()
    for name in names:
        full = os.path.join(folder, name)
        match = owned.match(name)
        try:
            if match and match.group(2) == host:
                stale = not _process_alive(int(match.group(1)))
            elif match or legacy.match(name):
                stale = now - os.stat(full).st_mtime > STALE_TEMP_AGE_S
            else:
                continue  # another target's temporary whose name starts alike
            if stale and os.path.isfile(full):
                os.remove(full)
        except OSError:
            continue  # removed meanwhile, or not ours to remove


def array_checksum(arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> str:
    """sha256 (hex) over named arrays (name, dtype, shape and bytes of each, in name order)
    and JSON-serialisable metadata: stored in a file, it shows whether the file's content
    was altered after it was written."""
    digest = hashlib.sha256()
    for name in sorted(arrays):
        array = np.ascontiguousarray(arrays[name])
        digest.update(name.encode())
        digest.update(array.dtype.str.encode())
        digest.update(repr(array.shape).encode())
        digest.update(array.tobytes())
    digest.update(json.dumps(dict(meta), sort_keys=True).encode())
    return digest.hexdigest()


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
        statistics: how the run went, apart from the physics: ``us_per_step`` (compiled
            chunks, compilation excluded), ``compile_seconds``, ``n_devices`` and
            ``device_kind``, and for synchronization-avoiding runs the step counts and
            re-synchronizations (see :func:`jaxsync.simulate_sync_avoiding`).
        shared_every: steps between the entries of each part's ``shared_displacement``
            (None: ``save_every``, one per snapshot). Surrogate training needs 1.
    """

    times: Any
    displacement: Any
    mesh: Mesh
    dt: Any
    save_every: int = 1
    parameters: dict = dataclasses.field(default_factory=dict)
    parts: tuple = ()
    synchronized: Any = None
    statistics: dict = dataclasses.field(default_factory=dict)
    shared_every: int | None = None

    @property
    def shared_stride(self) -> int:
        """Steps between the entries of the parts' ``shared_displacement``."""
        return int(self.save_every if self.shared_every is None else self.shared_every)

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

    def save(self, path: str | os.PathLike, *, compression: str | None = "gzip",
             level: int = 1) -> None:
        """Write an HDF5 file (atomically): ``/times``, ``/displacement``, ``/mesh/points``,
        ``/mesh/tets``, ``/mesh/facets/<name>``, root attributes ``dt``, ``save_every``,
        ``shared_every``, ``format_version``, the problem parameters (``param_*``) and
        the run statistics (``stat_*``), and per-part groups ``/parts/<p>/shared_nodes``,
        ``/parts/<p>/shared_displacement`` when present.

        ``compression``: HDF5 filter of the large datasets, ``"gzip"`` (at ``level``
        1-9, with byte shuffling), ``"lzf"`` (faster, lighter) or None. Float64
        displacements compress by about 10-30 % (the last mantissa bits are noise);
        saving fewer steps (``save_every``) is what makes files small."""
        if compression not in ("gzip", "lzf", None):
            raise CheckpointError(f"compression must be 'gzip', 'lzf' or None, got {compression!r}")
        if compression == "gzip" and not (isinstance(level, int) and 1 <= level <= 9):
            raise CheckpointError(f"gzip level must be an integer 1-9, got {level!r}")
        filters = {} if compression is None else {
            "chunks": True, "compression": compression, "shuffle": True,
            **({"compression_opts": level} if compression == "gzip" else {})}
        with atomic_h5(path) as f:
            f.attrs["format"] = "jaxsync-trajectory"
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["dt"] = float(self.dt)
            f.attrs["save_every"] = int(self.save_every)
            f.attrs["shared_every"] = self.shared_stride
            for key, value in self.parameters.items():
                f.attrs[f"param_{key}"] = value
            for key, value in self.statistics.items():
                f.attrs[f"stat_{key}"] = value
            f.create_dataset("times", data=np.asarray(self.times))
            if self.synchronized is not None:
                f.create_dataset("synchronized", data=np.asarray(self.synchronized, dtype=bool))
            f.create_dataset("displacement", data=np.asarray(self.displacement), **filters)
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
                        value = np.asarray(value)
                        if value.ndim == 2 and value.size > 4096:  # the per-step histories
                            pg.create_dataset(key, data=value, **filters)
                        else:
                            pg[key] = value

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
                stats = {k[len("stat_"):]: _attribute_value(v)
                         for k, v in f.attrs.items() if k.startswith("stat_")}
                parts = ()
                if "parts" in f:
                    parts = tuple({k: v[...] for k, v in f["parts"][str(p)].items()}
                                  for p in range(int(f.attrs["n_parts"])))
                synchronized = f["synchronized"][...] if "synchronized" in f else None
                shared_every = f.attrs.get("shared_every")
                return cls(times=f["times"][...], displacement=f["displacement"][...], mesh=mesh,
                           dt=float(f.attrs["dt"]), save_every=int(f.attrs["save_every"]),
                           parameters=params, parts=parts, synchronized=synchronized,
                           statistics=stats,
                           shared_every=None if shared_every is None else int(shared_every))
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
