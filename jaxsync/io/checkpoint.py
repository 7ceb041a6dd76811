"""Resumable checkpoints of synchronized runs: the state (both displacement levels, and the
material's internal variables if its law carries any), the snapshots and shared histories
so far, a fingerprint of the problem that refuses foreign files and checksums that refuse
altered ones.

A checkpoint costs the new snapshots only. The file (layout 2) holds the run's snapshot
and shared-history rows in datasets allocated at their final size when it is first
written (atomically, :mod:`jaxsync.io`: once per run and per resume), so that each later
checkpoint (:class:`CheckpointWriter`) writes, in place, only

1. the rows since the last checkpoint, past the committed ones (nothing points at them
   yet); then
2. a *commit* in the slot of the two that does not hold the latest one: the state, the
   step, the committed row counts, a sequence number and a checksum over all of it and
   the committed rows (running sha256 digests, so never re-read).

These are writes of raw data at fixed places (no HDF5 structure changes: no dataset
grows, none is created), and the one a reader trusts is the valid commit with the
highest sequence number. A crash mid-way therefore leaves either the new commit complete
or the previous one intact, with all of its rows: a torn or damaged commit fails its
checksum and the other slot is used; when no slot passes, the file is refused. Rewriting
every snapshot at every checkpoint, as layout 1 did, made a run's checkpoints cost the
square of its length (a 1e6-step cantilever run: 10 of its 21 s). Files of layout 1 are
still read (the next checkpoint rewrites them in layout 2).
"""

from __future__ import annotations

import hashlib
import time

import jax.numpy as jnp
import numpy as np

from ..errors import CheckpointError, OutputError
from ..fem._stepper import SolverState
from .atomic import array_checksum, atomic_h5

__all__ = ["fingerprint", "save_checkpoint", "load_checkpoint", "committed_step", "CheckpointWriter",
           "CheckpointSchedule", "watch_chunks", "LAYOUT", "CHECKPOINT_SECONDS"]

LAYOUT = 2
"""Layout of the files written: 2, preallocated rows and two commit slots (1: every
array rewritten at each checkpoint, still read)."""

CHECKPOINT_SECONDS = 30.0
"""Without a checkpoint interval in steps, a run checkpoints when this many seconds (wall
time) have passed since its last checkpoint or its start, and at its end: a run killed
loses at most about this much work, and a fast one does not spend its time writing."""


def fingerprint(problem, dt: float, save_every: int) -> str:
    """Hash of everything that determines a trajectory, to refuse foreign checkpoints: the
    mesh, the material (a hyperelastic law: its type, every parameter and a hash of its
    fibre directions), dt, save_every, the Dirichlet set and values, the loads, the initial
    conditions, density scaling, element, supports, prescribed histories and the
    stiffness-proportional damping beta (only when nonzero: the fingerprints of problems
    without it are unchanged)."""
    h = hashlib.sha256()
    mesh = problem.mesh
    for arr in (mesh.points, mesh.tets):
        h.update(np.ascontiguousarray(arr).tobytes())
    m = problem.material
    lowered = problem.discrete
    dofs, values = lowered.dirichlet_dofs()
    h.update(np.asarray([float(m.E), float(m.nu), float(m.rho), float(lowered.damping), dt,
                         save_every], dtype=float).tobytes())
    h.update(dofs.tobytes())
    h.update(values.tobytes())
    for v in lowered.load_vectors:
        h.update(np.asarray(v, dtype=float).tobytes())
    from ..fem.forces._follower import follower_loads

    for load in follower_loads(problem):  # not among the load vectors (they follow the displacement)
        h.update(repr(("follower pressure", load.surface, float(load.magnitude), load.time)).encode())
    for ic in (problem.initial_displacement, problem.initial_velocity, problem.density_scale):
        if ic is not None:
            h.update(np.asarray(ic, dtype=float).tobytes())
    # supports and prescribed histories (absent from the fingerprints of problems without them)
    if problem.element != "P1":
        h.update(problem.element.encode())
    if problem.stiffness_damped:
        h.update(repr(("stiffness damping", float(problem.stiffness_damping))).encode())
    for support in problem.supports:
        h.update(repr((support.surface, float(support.stiffness), float(support.damping),
                       support.normal_only)).encode())
    for bc in problem.dirichlet:
        if bc.time is not None:
            h.update(repr((bc.where if isinstance(bc.where, str) else "predicate", bc.time)).encode())
    # what identifies the law besides E, nu, rho (a hyperelastic law: its type, every
    # parameter, its fibre directions; the linear law adds nothing, so its fingerprints
    # are those of before)
    h.update(m.fingerprint())
    return h.hexdigest()


_CHECKPOINT_KIND = "jaxsync-solver-checkpoint"
_COMMIT_FIELDS = ("sequence", "step", "n_snapshots", "n_shared")  # the columns of /commit


def _checkpoint_checksum(arrays: dict, fingerprint: str, step: int) -> str:
    """Layout 1: sha256 over the stored arrays, the problem fingerprint and the step."""
    return array_checksum(arrays, {"kind": _CHECKPOINT_KIND, "fingerprint": str(fingerprint),
                                   "step": int(step)})


def _commit_checksum(fingerprint: str, commit: dict, state: dict, streams: dict) -> str:
    """Layout 2: sha256 over a commit (sequence, step, row counts), its state arrays and
    the digests of the committed rows of each stream (``{name: (dtype, row shape, hex)}``)."""
    return array_checksum(state, {"kind": _CHECKPOINT_KIND, "layout": LAYOUT,
                                  "fingerprint": str(fingerprint),
                                  **{k: int(commit[k]) for k in _COMMIT_FIELDS},
                                  "streams": {k: list(v) for k, v in sorted(streams.items())}})


class _Stream:
    """Rows of one dataset (snapshots, or one part's shared history) and the running
    sha256 of the committed ones."""

    def __init__(self, name: str, blocks: list):
        self.name = name
        first = np.asarray(blocks[0])
        self.dtype, self.row_shape = first.dtype, first.shape[1:]
        self.blocks = []  # the committed rows (the caller's arrays, not copies)
        self.n_rows = 0
        self.digest = hashlib.sha256()
        self.add(blocks)

    def rows(self, blocks) -> np.ndarray:
        blocks = [np.asarray(b) for b in blocks]
        if not blocks:
            return np.zeros((0, *self.row_shape), self.dtype)
        return np.ascontiguousarray(np.concatenate(blocks, axis=0), dtype=self.dtype)

    def add(self, blocks) -> np.ndarray:
        """Commit ``blocks`` (hashed; kept by reference); returns their rows as one array."""
        blocks = [np.asarray(b) for b in blocks]
        rows = self.rows(blocks)
        if rows.shape[1:] != self.row_shape:
            raise CheckpointError(f"checkpoint rows of {self.name} changed shape: "
                                  f"{rows.shape[1:]} after {self.row_shape}")
        self.blocks.extend(blocks)
        self.n_rows += len(rows)
        self.digest.update(rows.tobytes())
        return rows

    def summary(self) -> tuple:
        return (self.dtype.str, list(self.row_shape), self.digest.hexdigest())


def _create_rows(f, name: str, capacity: int, rows: np.ndarray) -> None:
    """A contiguous dataset of ``capacity`` rows, its storage allocated now (later
    writes into it change no HDF5 structure), holding ``rows`` first."""
    import h5py

    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)
    dataset = f.create_dataset(name, shape=(max(capacity, len(rows)), *rows.shape[1:]),
                               dtype=rows.dtype, dcpl=dcpl)
    if len(rows):
        dataset[:len(rows)] = rows


class CheckpointWriter:
    """Writes the checkpoints of one run at ``path`` (see the module docstring).

    ``snapshots`` and ``recorded`` (per part, or None): the rows the run starts from (its
    first snapshot, or what it resumed from); ``n_steps``, ``save_every``: the run's
    length, which sizes the file. The first :meth:`commit` writes the whole file
    atomically; the later ones append in place. The rows given are kept by reference
    (the run holds them anyway), so that the file can be rewritten whole when it is not
    the one this writer last committed (deleted or replaced meanwhile)."""

    def __init__(self, path, fingerprint: str, snapshots, recorded=None, *, n_steps: int,
                 save_every: int):
        self.path, self.fingerprint = str(path), str(fingerprint)
        self.capacity = int(n_steps) // int(save_every) + 1
        self.shared_capacity = int(n_steps) + 1  # every-step histories, from step 0
        self.snapshots = _Stream("snapshots", list(snapshots))
        self.shared = [_Stream(f"shared_{p}", list(chunks)) for p, chunks in enumerate(recorded or ())]
        self.sequence = 0  # of the last commit; 0: nothing written yet
        self.slot = 1  # the slot of the last commit
        self.full_writes = 0  # for the record (tests, timing)

    def _streams(self) -> list:
        return [self.snapshots, *self.shared]

    def commit(self, state: SolverState, snapshots, shared=None) -> None:
        """Checkpoint ``state`` with the rows since the last commit: ``snapshots``, a list
        of (n, n_nodes, 3) blocks, and ``shared``, per part a list of blocks (or None)."""
        new = [self.snapshots.add(snapshots)]
        for stream, blocks in zip(self.shared, shared or [[] for _ in self.shared]):
            new.append(stream.add(blocks))
        arrays = {"displacement": np.asarray(state.displacement), "previous": np.asarray(state.previous),
                  **_internal_arrays(state)}
        step = int(state.step)
        if self.sequence == 0 or not self._append(arrays, step, new):
            self._write_whole(arrays, step)

    def _commit_record(self, step: int) -> dict:
        return {"sequence": self.sequence + 1, "step": step, "n_snapshots": self.snapshots.n_rows,
                "n_shared": self.shared[0].n_rows if self.shared else 0}

    def _checksum(self, record: dict, arrays: dict) -> str:
        return _commit_checksum(self.fingerprint, record, arrays,
                                {s.name: s.summary() for s in self._streams()})

    def _write_whole(self, arrays: dict, step: int) -> None:
        """The whole file, atomically: every committed row, the commit in slot 0."""
        record = self._commit_record(step)
        with atomic_h5(self.path) as f:
            f.attrs["kind"] = _CHECKPOINT_KIND
            f.attrs["layout"] = LAYOUT
            f.attrs["fingerprint"] = self.fingerprint
            f.attrs["step"] = np.int64(step)  # for readers of the step alone; /commit rules
            for stream in self._streams():
                capacity = self.capacity if stream is self.snapshots else self.shared_capacity
                _create_rows(f, stream.name, capacity, stream.rows(stream.blocks))
            for name, array in arrays.items():  # two state slots
                _create_rows(f, name, 2, np.stack([array, np.zeros_like(array)]))
            _create_rows(f, "commit", 2, np.array([[record[k] for k in _COMMIT_FIELDS], [0] * 4],
                                                  dtype=np.int64))
            _create_rows(f, "commit_checksum", 2, np.array([self._checksum(record, arrays).encode(), b""],
                                                           dtype="S64"))
        self.sequence, self.slot = record["sequence"], 0
        self.full_writes += 1

    def _append(self, arrays: dict, step: int, new: list) -> bool:
        """Write the new rows, then the commit into the other slot, in place; False (and
        nothing written) when the file is not the one of this writer's last commit, or
        it has no room for the rows."""
        import h5py

        record = self._commit_record(step)
        slot = 1 - self.slot
        try:
            f = h5py.File(self.path, "r+")
        except OSError:  # gone, or no HDF5 file any more
            return False
        with f:
            try:
                if (f.attrs.get("kind") != _CHECKPOINT_KIND or f.attrs.get("layout") != LAYOUT
                        or f.attrs.get("fingerprint") != self.fingerprint
                        or int(f["commit"][self.slot, 0]) != self.sequence
                        or any(name not in f for name in arrays)):
                    return False
                datasets = [f[stream.name] for stream in self._streams()]
            except (KeyError, OSError, ValueError):
                return False
            if any(len(d) < s.n_rows or d.dtype != s.dtype or d.shape[1:] != s.row_shape
                   for d, s in zip(datasets, self._streams())):
                return False
            try:
                for dataset, stream, rows in zip(datasets, self._streams(), new):
                    if len(rows):
                        dataset[stream.n_rows - len(rows):stream.n_rows] = rows
                f.flush()  # the rows reach the file before the commit that points at them
                for name, array in arrays.items():
                    f[name][slot] = array
                f.flush()
                f["commit"][slot] = [record[k] for k in _COMMIT_FIELDS]
                f["commit_checksum"][slot] = self._checksum(record, arrays).encode()
                f.flush()
                f.attrs.modify("step", np.int64(step))  # a hint for readers of the step alone
            except OSError as exc:
                raise OutputError(f"could not write the checkpoint {self.path}: {exc} (free space, "
                                  "or choose another location, and run again)") from exc
        self.sequence, self.slot = record["sequence"], slot
        return True


class CheckpointSchedule:
    """When a run checkpoints, asked after every chunk (:meth:`due`): every
    ``every_chunks`` chunks, or (None) once :data:`CHECKPOINT_SECONDS` have passed since
    the last checkpoint; always after the last chunk. Every process of a multi-process
    run gets the same answer (process 0's clock decides), as the checkpoint is a
    collective."""

    def __init__(self, every_chunks: int | None, clock=time.perf_counter):
        self.every = None if every_chunks is None else max(1, int(every_chunks))
        self.seconds = float(CHECKPOINT_SECONDS)
        self.clock = clock
        self.chunks = 0
        self.last = clock()

    def due(self, final: bool) -> bool:
        """Whether to checkpoint after this chunk (``final``: the run's last)."""
        self.chunks += 1
        if final:
            return True
        if self.every is not None:
            return self.chunks % self.every == 0
        due = self.clock() - self.last >= self.seconds
        import jax

        if jax.process_count() > 1:
            from jax.experimental import multihost_utils

            due = bool(multihost_utils.broadcast_one_to_all(np.int32(due)))
        return due

    def written(self) -> None:
        """Note that a checkpoint was just written (the clock restarts)."""
        self.last = self.clock()


class _Watched:
    """A runner that remembers its last ``advance``: ``last`` = (state, chunk)."""

    def __init__(self, runner):
        self._runner = runner
        self.last = None

    def __getattr__(self, name):
        return getattr(self._runner, name)

    def advance(self, state, steps: int):
        self.last = self._runner.advance(state, steps)
        return self.last


def watch_chunks(runner) -> _Watched:
    """``runner`` (a :class:`jaxsync.solve.executors.Runner`) wrapped so that the hook of
    :func:`jaxsync.solve.executors.run_chunks` finds the chunk just advanced and its state
    in ``.last``, instead of building the whole segment so far (whose cost grows with
    the run)."""
    return _Watched(runner)


def save_checkpoint(path, fingerprint, state: SolverState, snapshots, recorded=None, *,
                    n_steps: int | None = None, save_every: int = 1) -> None:
    """Write a whole checkpoint (atomically): ``snapshots``, a list of blocks of rows,
    and ``recorded``, per part the list of shared-history blocks kept every step; room
    for the rows of a run of ``n_steps`` (default: no more than given)."""
    snapshots = list(snapshots)
    n_rows = sum(len(np.asarray(b)) for b in snapshots)
    n_steps = (n_rows - 1) * int(save_every) if n_steps is None else int(n_steps)
    writer = CheckpointWriter(path, fingerprint, snapshots[:1], [c[:1] for c in recorded] if recorded else None,
                              n_steps=n_steps, save_every=save_every)
    writer.commit(state, snapshots[1:], [c[1:] for c in recorded] if recorded else None)


def committed_step(path) -> int | None:
    """The step of the latest commit of the checkpoint ``path`` (not verified: for
    messages), or None when ``path`` is no readable solver checkpoint."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("kind") != _CHECKPOINT_KIND:
                return None
            if f.attrs.get("layout", 1) == 1:
                return int(f.attrs["step"])
            commit = f["commit"][...]
            return int(commit[int(np.argmax(commit[:, 0])), 1])
    except Exception:  # noqa: BLE001 - unreadable: the solver says why when it runs
        return None


def load_checkpoint(path, fingerprint, n_steps, n_recorded: int = 0):
    """(state, snapshot chunks, per-part shared-history chunks or None) of the latest
    valid commit; ``n_recorded`` parts' every-step shared histories must be in the file
    when > 0. Raises :class:`CheckpointError` for a foreign, damaged or altered file."""
    import os

    import h5py

    if os.path.isdir(path):
        raise CheckpointError(f"checkpoint {os.fspath(path)!r} is a folder; give a .h5 file (pass another "
                              "checkpoint path)")
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("kind") != _CHECKPOINT_KIND:
                what = {"jaxsync-trajectory": "a jaxsync trajectory (a run's output)",
                        "jaxsync-lstm-surrogate": "a jaxsync surrogate file"}.get(str(f.attrs.get("format", "")))
                if what is not None:  # the user's result: never advise deleting it
                    raise CheckpointError(f"{path} is {what}, not a solver checkpoint: pass another checkpoint path "
                                          "(the checkpoint is the run's own resumable state, written beside its "
                                          "output)")
                raise CheckpointError(f"{path} is not a jaxsync solver checkpoint; delete it or "
                                      "pass another checkpoint path")
            if f.attrs["fingerprint"] != fingerprint:
                raise CheckpointError(
                    f"checkpoint {path} was written by a different problem, dt or save_every; "
                    "delete it or pass another checkpoint path")
            layout = int(f.attrs.get("layout", 1))
            if layout > LAYOUT:
                raise CheckpointError(f"checkpoint {path} has layout {layout}, newer than this "
                                      f"jaxsync reads ({LAYOUT}): upgrade jaxsync, or delete it")
            found = _read_layout1(f, path, fingerprint) if layout == 1 else _read_layout2(f, path, fingerprint)
    except CheckpointError:
        raise
    except Exception as exc:
        raise CheckpointError(f"cannot read checkpoint {path}: {' '.join(str(exc).split())}; delete it to start "
                              "over") from exc
    step_, arrays = found
    if step_ > n_steps:
        raise CheckpointError(f"checkpoint {path} is at step {step_}, beyond n_steps={n_steps}")
    recorded = None
    if n_recorded:
        if f"shared_{n_recorded - 1}" not in arrays:
            raise CheckpointError(
                f"checkpoint {path} holds no every-step shared histories (it was written with "
                "shared_every = save_every); delete it, or resume with the same shared_every")
        recorded = [[arrays[f"shared_{p}"]] for p in range(n_recorded)]
    internal = {name[len(_INTERNAL):]: jnp.asarray(value) for name, value in arrays.items()
                if name.startswith(_INTERNAL)}
    state = SolverState(jnp.asarray(arrays["displacement"]), jnp.asarray(arrays["previous"]),
                        jnp.asarray(step_, dtype=jnp.int32), internal)
    return state, [arrays["snapshots"]], recorded


_INTERNAL = "internal."
"""The prefix of the material's internal variables among a commit's state arrays (files
of laws without state, and those written before laws had state, hold none)."""


def _internal_arrays(state: SolverState) -> dict:
    """{"internal.<name>": array} of the state's internal variables (a flat dict)."""
    if not isinstance(state.internal, dict):
        raise CheckpointError("a checkpoint stores a material's internal variables as a flat dict {name: array}; "
                              f"this state holds {type(state.internal).__name__}: return a dict from the law's "
                              "internal_variables")
    return {_INTERNAL + str(name): np.asarray(value) for name, value in sorted(state.internal.items())}


def _shared_names(f) -> list:
    return sorted((k for k in f if k.startswith("shared_")), key=lambda k: int(k.split("_")[1]))


def _altered(path) -> CheckpointError:
    return CheckpointError(
        f"checkpoint {path} fails its checksum: the stored state was altered or damaged "
        "after it was written, and resuming from it would give a wrong trajectory; "
        "delete it to start over")


def _read_layout1(f, path, fingerprint):
    """(step, arrays) of a layout-1 file (one checksum over every array)."""
    step_ = int(f.attrs["step"])
    names = ["displacement", "previous", "snapshots"] + _shared_names(f)
    arrays = {name: f[name][...] for name in names}
    stored = f.attrs.get("checksum")
    if stored is None:
        raise CheckpointError(
            f"checkpoint {path} has no checksum (written by an older jaxsync), so its state "
            "cannot be verified; delete it to start over")
    if str(stored) != _checkpoint_checksum(arrays, fingerprint, step_):
        raise _altered(path)
    return step_, arrays


def _read_layout2(f, path, fingerprint):
    """(step, arrays) of the valid commit with the highest sequence number of a
    layout-2 file; the other slot when the latest fails its checksum (a write cut short)."""
    commits = f["commit"][...]
    checksums = f["commit_checksum"][...]
    names = _shared_names(f)
    for slot in sorted(range(len(commits)), key=lambda s: -int(commits[s, 0])):
        record = dict(zip(_COMMIT_FIELDS, (int(v) for v in commits[slot])))
        if record["sequence"] <= 0:
            continue
        n_rows = {"snapshots": record["n_snapshots"], **{name: record["n_shared"] for name in names}}
        if any(n > len(f[name]) for name, n in n_rows.items()):
            continue
        state = {name: f[name][slot] for name in ("displacement", "previous", *sorted(
            k for k in f if k.startswith(_INTERNAL)))}
        rows = {name: f[name][:n] for name, n in n_rows.items()}
        streams = {name: (f[name].dtype.str, list(f[name].shape[1:]),
                          hashlib.sha256(np.ascontiguousarray(values).tobytes()).hexdigest())
                   for name, values in rows.items()}
        if checksums[slot].decode() != _commit_checksum(fingerprint, record, state, streams):
            continue
        return record["step"], {**state, **rows}
    raise _altered(path)
