"""Trajectories: saved displacement histories with their run statistics and per-part
shared-node histories; HDF5 files (the one reader and writer) and ParaView output (XDMF, or
a VTU series with its .pvd collection).

Files are written atomically (:mod:`jaxsync.io`): a failed or interrupted write never
replaces a good file. These formats are the writers ``"hdf5"``, ``"xdmf"`` and ``"vtu"`` of
the registry :mod:`jaxsync.io.writers`, where other formats are added.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import os
from typing import Any

import jax
import numpy as np

from ..errors import CheckpointError, OutputError
from ..mesh import Mesh
from ..run_stats import RunStats
from .atomic import atomic_h5
from .writers._vtu import check_vtu_location, vtu_series_paths, write_pvd

__all__ = ["Trajectory", "RunStats", "PartHistory", "Result", "vtu_series_paths", "check_vtu_location",
           "write_vtu"]

FORMAT_VERSION = 1


class Result(enum.IntEnum):
    """How a run ended (``Trajectory.result``; under ``jit`` an int32 array of these codes).

    - ``SUCCESSFUL``: every step ran and every saved value is finite.
    - ``DIVERGED``: the displacement became NaN/Inf or blew up; a host run stops there and
      keeps the snapshots saved before (``StabilityError.trajectory``), a traced run goes
      on and says so here.
    """

    SUCCESSFUL = 0
    DIVERGED = 1


@dataclasses.dataclass(frozen=True, eq=False)
class PartHistory:
    """One part of a distributed run: its shared nodes and their displacement history.

    Attributes:
        shared_nodes: (n_shared,) global ids of the nodes the part shares with others.
        elements: (n_elements_p,) global ids of the part's elements.
        shared_displacement: (n_entries, 3 n_shared) the shared nodes' displacement
            [cm], one row every ``Trajectory.shared_stride`` steps from step 0, columns
            node-major (x, y, z of shared_nodes[0], then of shared_nodes[1] ...).
        predicted_shared_displacement: synchronization-avoiding runs only:
            (n_predicted_saved, 3 n_shared) the part's OWN predictions at the saved
            predicted steps [cm]; None otherwise.
    """

    shared_nodes: Any
    elements: Any
    shared_displacement: Any
    predicted_shared_displacement: Any = None

    @property
    def n_shared(self) -> int:
        return int(np.shape(self.shared_nodes)[0])

    def arrays(self) -> dict:
        """The fields that are set, by name (as stored in a file)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) is not None}


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
        parts: per-part shared-node histories of a distributed run
            (:class:`PartHistory`, one per part), or empty.
        synchronized: (n_saved,) bool, False where the snapshot's step was predicted
            by surrogates instead of synchronized (None: all synchronized).
        stats: how the run went, apart from the physics, typed by the kind of run
            (:mod:`jaxsync.run_stats`: :class:`~jaxsync.SynchronizedStats`,
            :class:`~jaxsync.SyncAvoidingStats`, ...; time per step, compilation, devices,
            and for synchronization-avoiding runs the step counts and re-synchronizations).
        shared_every: steps between the entries of each part's ``shared_displacement``
            (None: ``save_every``, one per snapshot). Surrogate training needs 1.
        result: how the run ended (:class:`Result`; a JAX int32 array in a traced run,
            None: not recorded, files of an older jaxsync).
        element: ``"P1"`` or ``"P2"``: the nodes the displacement is on (:attr:`space`;
            P2: the mesh's vertices, then one node per edge).
        error_estimate: synchronization-avoiding runs with error control
            (``ResyncTolerance(indicator="estimate")``): (n_saved,) the estimated largest
            nodal error at each predicted snapshot [cm] (:mod:`jaxsync.solve.coupling`),
            NaN at synchronized ones; None otherwise.
        load_signal: (n_rows, n_u) the problem's known load signals (the time functions
            of its loads and prescribed motions, :mod:`jaxsync.fem`) at the
            steps of the parts' shared rows (every :attr:`shared_stride` steps from step
            0), dimensionless: what a load-aware surrogate is trained with. None: not
            recorded (files of an older jaxsync, traced time functions).
        load_inputs: the (n_u,) :class:`~jaxsync.fem.LoadInput` descriptions
            of the columns of ``load_signal`` (empty without it).

    A pytree (the arrays, ``dt``, the parts and ``result`` are its leaves), so a traced run
    can return it from ``jit``.
    """

    times: Any
    displacement: Any
    mesh: Mesh
    dt: Any
    save_every: int = 1
    parameters: dict = dataclasses.field(default_factory=dict)
    parts: tuple[PartHistory, ...] = ()
    synchronized: Any = None
    stats: RunStats = RunStats()
    shared_every: int | None = None
    result: Any = None
    element: str = "P1"
    error_estimate: Any = None
    load_signal: Any = None
    load_inputs: tuple = ()

    def __post_init__(self):
        object.__setattr__(self, "load_inputs", tuple(self.load_inputs))
        if self.stats is None:  # a run that recorded no statistics (a diverged run's kept snapshots)
            object.__setattr__(self, "stats", RunStats())
        elif isinstance(self.stats, dict):
            object.__setattr__(self, "stats", RunStats.from_dict(self.stats))
        if any(not isinstance(part, PartHistory) for part in self.parts):
            raise TypeError("Trajectory.parts must hold PartHistory objects")

    @property
    def space(self):
        """The :class:`~jaxsync.fem.FunctionSpace` of the displacement's nodes."""
        from ..fem._space import function_space

        return function_space(self.mesh, self.element)

    @property
    def points(self) -> np.ndarray:
        """(n_nodes, 3) coordinates of the displacement's nodes [cm]."""
        return self.space.points

    def output_cells(self) -> tuple[np.ndarray, str, np.ndarray]:
        """(points, meshio cell type, cells) of the nodes for ParaView: ``"tetra"``, or
        ``"tetra10"`` in VTK's node order for P2."""
        from ..fem._space import vtk_cells

        kind, cells = vtk_cells(self.space)
        return self.points, kind, cells

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
             level: int = 1, overwrite: bool = True) -> None:
        """Write an HDF5 file (atomically): ``/times``, ``/displacement``, ``/mesh/points``,
        ``/mesh/tets``, ``/mesh/facets/<name>``, root attributes ``dt``, ``save_every``,
        ``shared_every``, ``format_version``, the problem parameters (``param_*``) and
        the run statistics (``stat_*``), and per-part groups ``/parts/<p>/shared_nodes``,
        ``/parts/<p>/shared_displacement`` when present.

        ``compression``: HDF5 filter of the large datasets, ``"gzip"`` (at ``level``
        1-9, with byte shuffling), ``"lzf"`` (faster, lighter) or None. Float64
        displacements compress by about 10-30 % (the last mantissa bits are noise);
        saving fewer steps (``save_every``) is what makes files small.

        ``overwrite``: True (default, as :func:`numpy.save` and :class:`h5py.File` do)
        replaces a file at ``path``, atomically (a failed write leaves the old one as it
        was); False refuses an existing file (:class:`jaxsync.io.OutputError`, nothing
        written), and one that another process writes meanwhile is kept: this trajectory
        then goes beside it as ``<stem>.conflict-1.h5``, and the error names both."""
        if compression not in ("gzip", "lzf", None):
            raise CheckpointError(f"compression must be 'gzip', 'lzf' or None, got {compression!r}")
        if not overwrite and os.path.lexists(path):
            from .atomic import OutputError

            raise OutputError(f"{os.fspath(path)} exists and overwrite=False: choose another path, or pass "
                              "overwrite=True to replace it")
        if compression == "gzip" and not (isinstance(level, int) and 1 <= level <= 9):
            raise CheckpointError(f"gzip level must be an integer 1-9, got {level!r}")
        filters = {} if compression is None else {
            "chunks": True, "compression": compression, "shuffle": True,
            **({"compression_opts": level} if compression == "gzip" else {})}
        with atomic_h5(path, replace=overwrite) as f:
            f.attrs["format"] = "jaxsync-trajectory"
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["dt"] = float(self.dt)
            f.attrs["save_every"] = int(self.save_every)
            f.attrs["shared_every"] = self.shared_stride
            if self.result is not None:
                f.attrs["result"] = int(self.result)
            for key, value in self.parameters.items():
                f.attrs[f"param_{key}"] = value
            for key, value in self.stats.to_dict().items():
                f.attrs[f"stat_{key}"] = value
            f.create_dataset("times", data=np.asarray(self.times))
            if self.synchronized is not None:
                f.create_dataset("synchronized", data=np.asarray(self.synchronized, dtype=bool))
            f.create_dataset("displacement", data=np.asarray(self.displacement), **filters)
            if self.error_estimate is not None:
                f.create_dataset("error_estimate", data=np.asarray(self.error_estimate, dtype=float))
            if self.load_signal is not None:
                f.create_dataset("load_signal", data=np.asarray(self.load_signal, dtype=np.float64))
                f.attrs["load_inputs"] = json.dumps([i.to_dict() for i in self.load_inputs])
            g = f.create_group("mesh")
            g["points"] = self.mesh.points
            g["tets"] = self.mesh.tets
            g["source_node_ids"] = self.mesh.source_node_ids
            if self.mesh.mid_nodes is not None:
                g["mid_nodes"] = self.mesh.mid_nodes
            if self.element != "P1":
                f.attrs["element"] = self.element
            facets = g.create_group("facets")
            for name, tri in self.mesh.facet_sets.items():
                facets[name] = tri
            if self.parts:
                f.attrs["n_parts"] = len(self.parts)
                parts = f.create_group("parts")
                for p, part in enumerate(self.parts):
                    pg = parts.create_group(str(p))
                    for key, value in part.arrays().items():
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
        if os.path.isdir(path):
            raise CheckpointError(f"trajectory {path!r} is a folder; give a .h5 file")
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
                            source_node_ids=g["source_node_ids"][...],
                            mid_nodes=g["mid_nodes"][...] if "mid_nodes" in g else None)
                params = {k[len("param_"):]: _attribute_value(v)
                          for k, v in f.attrs.items() if k.startswith("param_")}
                stats = {k[len("stat_"):]: _attribute_value(v)
                         for k, v in f.attrs.items() if k.startswith("stat_")}
                parts = ()
                if "parts" in f:
                    parts = tuple(_part_history(f["parts"][str(p)]) for p in range(int(f.attrs["n_parts"])))
                synchronized = f["synchronized"][...] if "synchronized" in f else None
                shared_every = f.attrs.get("shared_every")
                result = f.attrs.get("result")
                load_signal, load_inputs = None, ()
                if "load_signal" in f:
                    from ..fem._load_signals import LoadInput

                    load_signal = f["load_signal"][...]
                    load_inputs = tuple(LoadInput.from_dict(d) for d in json.loads(f.attrs["load_inputs"]))
                return cls(times=f["times"][...], displacement=f["displacement"][...], mesh=mesh,
                           dt=float(f.attrs["dt"]), save_every=int(f.attrs["save_every"]),
                           parameters=params, parts=parts, synchronized=synchronized,
                           stats=RunStats.from_dict(stats),
                           shared_every=None if shared_every is None else int(shared_every),
                           result=None if result is None else Result(int(result)),
                           element=str(f.attrs.get("element", "P1")),
                           error_estimate=f["error_estimate"][...] if "error_estimate" in f else None,
                           load_signal=load_signal, load_inputs=load_inputs)
        except CheckpointError:
            raise
        except Exception as exc:  # h5py's reasons can span lines: one line
            raise CheckpointError(f"cannot read trajectory {path}: {' '.join(str(exc).split())}") from exc

    def to_xdmf(self, path: str | os.PathLike, *, every: int = 1) -> str:
        """Write an XDMF time series for ParaView with the point field ``displacement``;
        ``every`` thins the snapshots. The heavy data go to ``<stem>.xdmf.h5`` beside it
        (a name that cannot collide with a trajectory file ``<stem>.h5``), which the XDMF
        file names relative to itself: the pair can be moved together.

        Both files are written in a staging folder beside them and moved into place at the
        end (:func:`jaxsync.io.staged_outputs`); the working directory is not changed.
        Returns the path of the data file.

        Raises:
            OutputError: a location that cannot be written (checked first: a folder in
                the way, a folder that is not writable), or a failed write (an
                :class:`OSError`); it names ``path``, and earlier files are left as they were.
        """
        from .atomic import OutputFile, check_writable, staged_outputs
        from .writers._xdmf import write_xdmf_series, xdmf_paths

        path, data = xdmf_paths(path)
        check_writable(path, what="XDMF file")
        check_writable(data, what="XDMF data file")
        points, kind, cells = self.output_cells()
        disp, times = np.asarray(self.displacement), np.asarray(self.times)
        steps = range(0, self.n_saved, every)
        with staged_outputs((OutputFile(data, "XDMF data file"), OutputFile(path, "XDMF file")), main=path) as staged:
            write_xdmf_series(staged.path(path), staged.path(data), points, kind, cells, times[list(steps)],
                              ({"displacement": disp[i]} for i in steps))
        return os.path.abspath(data)

    def to_vtu(self, path: str | os.PathLike, *, every: int = 1) -> str:
        """Write a VTU time series for ParaView: one ``.vtu`` file per saved snapshot (the
        mesh, ``tetra`` cells, and the point data ``displacement`` [cm] and
        ``GlobalNodeID``, each node's 1-based number in the file the mesh was read from:
        for a SimVascular mesh, the user's own ``GlobalNodeID``), and a ParaView collection
        ``.pvd`` that lists them with their times [s]; ``every`` thins the snapshots.

        ``path`` is the series' prefix: ``out/run`` (or ``out/run.pvd``, or the folder
        ``out/run/``) writes the collection ``out/run.pvd`` and the step files
        ``out/run/run_000000.vtu``, ... in the folder beside it (:func:`vtu_series_paths`).
        Everything is written in a staging folder and moved into place at the end
        (:func:`jaxsync.io.staged_outputs`), so a failed write leaves an earlier series as
        it was; an existing folder of that name is replaced only when it holds nothing but
        ``.vtu`` files (an earlier series).

        Returns the path of the ``.pvd`` file.

        Raises:
            OutputError: a bad ``every``, a location taken by something else than an
                earlier series, or a failed write (an :class:`OSError`).
        """
        if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
            raise OutputError(f"to_vtu: every must be a positive integer, got {every!r}")
        from .atomic import OutputFile, staged_outputs

        pvd, folder = check_vtu_location(path)
        stem = os.path.basename(folder)
        with staged_outputs((OutputFile(folder, "VTU step files", folder=True), OutputFile(pvd, "VTU collection")),
                            main=pvd) as staged:
            steps = staged.path(folder)
            os.mkdir(steps)
            displacement, times = np.asarray(self.displacement), np.asarray(self.times)
            points, kind, cells = self.output_cells()
            numbers = self.mesh.source_node_ids + 1
            if self.element != "P1":  # edge nodes have no number in the file: 0
                numbers = np.concatenate([numbers, np.zeros(len(points) - len(numbers), dtype=numbers.dtype)])
            if numbers.size and np.abs(numbers).max() < 2**31:
                numbers = numbers.astype(np.int32)  # SimVascular's type
            width = max(6, len(str(max(self.n_saved - 1, 0))))
            entries = []
            for i in range(0, self.n_saved, int(every)):
                name = f"{stem}_{i:0{width}d}.vtu"
                write_vtu(os.path.join(steps, name), points, cells, kind,
                          point_data={"displacement": displacement[i], "GlobalNodeID": numbers})
                entries.append((float(times[i]), f"{stem}/{name}"))
            write_pvd(staged.path(pvd), entries)
        return pvd


def write_vtu(path: str | os.PathLike, points, cells, cell_type: str, *,
              point_data: dict | None = None) -> None:
    """Write one ``.vtu`` file: ``points`` (n, 3), ``cells`` (n_cells, nodes per cell) of
    the meshio ``cell_type`` (``"tetra"``; ``"tetra10"`` in VTK's node order) and the
    point data (zlib-compressed binary)."""
    import meshio

    mesh = meshio.Mesh(np.asarray(points), [(cell_type, np.asarray(cells))],
                       point_data=dict(point_data or {}))
    meshio.write(os.fspath(path), mesh, file_format="vtu")


def _part_history(group) -> PartHistory:
    """A :class:`PartHistory` from its HDF5 group (``elements`` and the predictions may be
    absent in files of other writers)."""
    read = {name: group[name][...] for name in group}
    return PartHistory(shared_nodes=read["shared_nodes"], elements=read.get("elements"),
                       shared_displacement=read["shared_displacement"],
                       predicted_shared_displacement=read.get("predicted_shared_displacement"))


def _attribute_value(value):
    """An HDF5 attribute as a Python value: scalars as numbers, arrays as lists."""
    if getattr(value, "ndim", 0) > 0:
        return value.tolist()
    return value.item() if hasattr(value, "item") else value


class _Frozen:
    """A dict as hashable static data of a pytree (compared and hashed by its content)."""

    def __init__(self, mapping: dict):
        self.mapping = dict(mapping)
        self._key = json.dumps(self.mapping, sort_keys=True, default=repr)

    def __eq__(self, other):
        return isinstance(other, _Frozen) and other._key == self._key

    def __hash__(self):
        return hash(self._key)


def _flatten_trajectory(t: Trajectory):
    children = (t.times, t.displacement, t.dt, t.parts, t.synchronized, t.result, t.error_estimate, t.load_signal)
    return children, (t.mesh, t.save_every, _Frozen(t.parameters), t.stats, t.shared_every, t.element,
                      t.load_inputs)


def _unflatten_trajectory(aux, children) -> Trajectory:
    mesh, save_every, parameters, stats, shared_every, element, load_inputs = aux
    times, displacement, dt, parts, synchronized, result, error_estimate, load_signal = children
    t = object.__new__(Trajectory)  # without __post_init__: leaves may be placeholders
    for name, value in (("times", times), ("displacement", displacement), ("mesh", mesh), ("dt", dt),
                        ("save_every", save_every), ("parameters", dict(parameters.mapping)),
                        ("parts", tuple(parts)), ("synchronized", synchronized), ("stats", stats),
                        ("shared_every", shared_every), ("result", result), ("element", element),
                        ("error_estimate", error_estimate), ("load_signal", load_signal),
                        ("load_inputs", load_inputs)):
        object.__setattr__(t, name, value)
    return t


jax.tree_util.register_pytree_node(Trajectory, _flatten_trajectory, _unflatten_trajectory)
jax.tree_util.register_dataclass(PartHistory, data_fields=["shared_nodes", "elements", "shared_displacement",
                                                           "predicted_shared_displacement"], meta_fields=[])
