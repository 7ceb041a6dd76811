"""The distributed runner: advances per-part states of paper Algorithm 1 under the SPMD
programs of :mod:`jaxsync.parallel.spmd`, with the shared-node forces summed by
:func:`jaxsync.parallel.exchange.synchronize_forces` (the driver's runner interface, see
:mod:`jaxsync.solve.driver`)."""

from __future__ import annotations

import functools
import time

import jax
import numpy as np
from jax.sharding import Mesh as DeviceMesh
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from ..errors import ConfigError, PartitionError
from ..fem.stepper import ExplicitSystem, SolverState, advance
from ..parallel.exchange import PartSystems, build_part_systems, neighbour_exchange, synchronize_forces
from ..parallel.halo import advance_halo, check_halo_depth, check_save_every, halo_partition
from ..parallel.partitioning import Partition, partition_from_elements
from ..parallel.partitioning import partition as make_partition
from ..parallel.spmd import AXIS, spmd_program
from .driver import Chunk, chunk_of_saves

__all__ = ["DistributedRunner", "to_host"]


def _default_devices(n_parts: int, devices=None, sync: str = "psum"):
    """Devices of this run's mesh.

    ``"psum"``: the given devices or, by default, as many of ``jax.devices()`` as divide
    n_parts; across processes, all devices of all processes (each process must hold
    parts). ``"mpi"``: one device of this process (the others are reached through MPI)."""
    if sync == "mpi":
        local = list(jax.local_devices() if devices is None else devices)
        if len(local) != 1 or local[0].process_index != jax.process_index():
            raise ConfigError(
                f"sync='mpi' runs each process's parts on one device of that process, got "
                f"{len(local)} devices; pass devices=[one local device], start one process "
                "per device (mpiexec -n N_devices), or use sync='psum'")
        return local
    available = list(jax.devices() if devices is None else devices)
    if jax.process_count() > 1:
        if n_parts % len(available):
            raise PartitionError(
                f"n_parts={n_parts} must be a multiple of the {len(available)} devices of the "
                f"{jax.process_count()} processes; use a multiple of {len(available)} parts")
        return available
    n = max(d for d in range(1, min(len(available), n_parts) + 1) if n_parts % d == 0)
    return available[:n]


class DistributedRunner:
    """Advances per-part states under ``shard_map`` (a :class:`jaxsync.solve.driver.Runner`)."""

    def __init__(self, problem, system: ExplicitSystem, partitions, *, save_every: int,
                 mode: str = "preassembled", seed: int = 0, devices=None, sync: str | None = None,
                 allreduce: str = "auto", comm=None, record_shared: bool = False,
                 halo_depth: int = 1):
        """
        Args:
            problem, system: the problem and its global :class:`ExplicitSystem`.
            partitions: an int n_parts (METIS; in a multi-process run rank 0's partition is
                broadcast) or a :class:`Partition`.
            save_every: steps between saved snapshots.
            mode: ``"preassembled"`` or ``"recompute"`` (paper Remark 2).
            seed: METIS seed.
            devices: devices of the mesh (see :func:`_default_devices`).
            sync: how shared-node forces are summed across devices and processes:
                ``"psum"`` (XLA collective over all devices: emulated devices in one
                process, gloo between CPU processes, NCCL between GPUs), ``"ppermute"``
                (each device exchanges only the nodes it shares with each neighbouring
                device: :class:`NeighbourExchange`), ``"mpi"`` (one device per
                process, MPI Allreduce called from inside the compiled step) or
                ``"halo"`` (deep halos, :mod:`jaxsync.parallel.halo`: every part grown by
                ``halo_depth`` layers of its neighbours' elements steps alone and
                exchanges both displacement levels of its halo every ``halo_depth``
                steps, with a ``psum`` in one process and across GPUs, with the MPI
                Allreduce of ``"mpi"`` across CPU processes; exact, the same trajectory
                to round-off).
                Default: :func:`jaxsync.parallel.multiprocess.default_sync` (``"mpi"`` across
                processes, measured faster; ``"psum"`` in one process).
            allreduce: with ``sync="mpi"``, ``"mpi4jax"``, ``"callback"`` or ``"auto"``
                (see :func:`jaxsync.parallel.multiprocess.make_allreduce`).
            comm: with ``sync="mpi"``, the mpi4py communicator (default a duplicate of
                ``COMM_WORLD``); rank r runs parts [r k, (r + 1) k), k = n_parts / size.
            record_shared: also keep every part's shared-node displacements after EVERY
                step (the surrogates' training data; small), whatever ``save_every``.
            halo_depth: with ``sync="halo"``, k, the steps between two exchanges;
                ``save_every`` and k must divide one another, and runs advance in whole
                multiples of the larger.
        """
        from ..options import Sync, check_option
        from ..parallel import multiprocess

        sync = check_option("sync", multiprocess.default_sync() if sync is None else sync, Sync)
        self.sync = sync
        if isinstance(partitions, Partition):
            self.partition = partitions
        else:
            self.partition = make_partition(problem.mesh, partitions, seed=seed)
            if jax.process_count() > 1:  # every rank must use rank 0's parts
                from jax.experimental import multihost_utils

                reference = np.asarray(multihost_utils.broadcast_one_to_all(
                    self.partition.element_part))
                if not np.array_equal(reference, self.partition.element_part):
                    self.partition = partition_from_elements(problem.mesh, reference, seed=seed)
        n_parts = self.partition.n_parts
        # how values cross processes: MPI from inside the step (one device per process), or
        # XLA's collectives; deep halos exchange through MPI wherever it is the default
        self.transport = "mpi" if sync == "mpi" or (
            sync == "halo" and multiprocess.default_sync() == "mpi") else "xla"
        devices = _default_devices(n_parts, devices, "mpi" if self.transport == "mpi" else sync)
        if n_parts % len(devices):
            raise PartitionError(f"n_parts={n_parts} must be a multiple of the number of devices "
                                 f"({len(devices)})")
        self._part_slice = slice(None)
        # how a step sums shared values beyond the vmapped parts of one device: None (psum
        # over the device axis), an MPI Allreduce or a NeighbourExchange (the ``across`` of
        # jaxsync.parallel.exchange.synchronize_forces)
        self.across = None
        self.layout = self.partition  # the parts as the program holds them
        self.halo_depth = None
        self._unit = save_every  # the steps of the smallest whole chunk
        if sync == "halo":
            if record_shared:
                raise ConfigError(
                    "sync='halo' cannot record the shared-node displacements after every step "
                    "(the surrogates' training data, the synchronization-avoiding solver's "
                    "synchronized phases): use sync='psum' or 'ppermute' there")
            self.halo_depth = check_halo_depth(halo_depth)
            self._unit = check_save_every(save_every, self.halo_depth)
            self.layout = halo_partition(self.partition, self.halo_depth)
        elif halo_depth != 1:
            raise ConfigError(f"halo_depth={halo_depth!r} needs sync='halo' (got sync={sync!r})")
        if self.transport == "mpi":
            if comm is None:
                comm = multiprocess.world().Dup()  # the step's collectives, apart from others
            size, rank = comm.Get_size(), comm.Get_rank()
            if size > 1 and jax.process_count() != size:
                raise ConfigError(
                    f"sync='mpi' over {size} MPI ranks needs jax.distributed joined across them "
                    f"(JAX sees {jax.process_count()} process); call "
                    "jaxsync.parallel.multiprocess.initialize() at the start of every rank")
            if n_parts % size:
                raise PartitionError(f"n_parts={n_parts} must be a multiple of the {size} MPI "
                                     f"ranks; use a multiple of {size} parts")
            per_rank = n_parts // size
            self._part_slice = slice(rank * per_rank, (rank + 1) * per_rank)
            self.across = multiprocess.make_allreduce(comm, allreduce)
        if sync == "ppermute":
            self.across = neighbour_exchange(self.partition, len(devices))
        self.devices = devices
        self.device_mesh = DeviceMesh(np.array(devices), (AXIS,))
        self.sharding = NamedSharding(self.device_mesh, P(AXIS))
        self.save_every = save_every
        self.mode = mode
        self.record_shared = bool(record_shared)
        self.n_nodes = self.partition.mesh.n_nodes
        host = build_part_systems(problem, system, self.layout, mode)
        self.n_local = host.system.mass.shape[1]
        self.parts = self.put(host)
        self._advance = {}
        # where each part's local values go in the global field: all local nodes, or with
        # deep halos the owned ones (the only ones right inside an exchange cycle);
        # global_index[i] is the global node of flat local slot local_index[i] (part p's
        # slot k is p * n_local + k)
        kept = ([np.arange(p.n_local) for p in self.layout.parts] if self.halo_depth is None
                else list(self.layout.owned_local))
        self.global_index = np.concatenate([p.nodes[k] for p, k in zip(self.layout.parts, kept)])
        self.local_index = np.concatenate(
            [p.index * self.n_local + k for p, k in zip(self.layout.parts, kept)])

    def put(self, tree):
        """Place stacked host arrays (all parts) on the devices, sharded on the part axis.
        Multi-process: with ``"psum"`` each process supplies only its addressable shards of
        the global array; with ``"mpi"`` each process places its own parts on its device."""
        def put(x):
            x = np.asarray(x)[self._part_slice]
            return jax.make_array_from_callback(x.shape, self.sharding, lambda index: x[index])

        return jax.tree_util.tree_map(put, tree)

    def program(self, n_saves: int, *, save_every: int | None = None, synchronize: bool = True,
                record: bool = False):
        """The jitted SPMD program: ``(parts, state) -> (state, saved)`` advancing
        ``n_saves * save_every`` steps (``shard_map`` over the devices, the parts of one
        device vmapped). ``synchronize=False`` leaves the force synchronization out (used
        to time it, paper section 7). ``record=True``: ``saved`` is the pair (full field
        every ``save_every`` steps, shared-node displacements (n_parts, n_steps,
        n_shared_max, 3) after every step; padding slots read 0)."""
        save_every = self.save_every if save_every is None else save_every
        depth = self.halo_depth

        def one_part(part: PartSystems, state: SolverState):
            if depth is not None and synchronize:
                return advance_halo(part, state, n_saves, save_every, depth, self.layout.n_interface, self.across)
            return advance(part.system, state, n_saves, save_every,
                           synchronize=self.force_sum(part) if synchronize else None,
                           record=part.shared_displacement if record else None)

        return spmd_program(one_part, self.device_mesh, n_in=2, n_out=2)

    def force_sum(self, part: PartSystems):
        """One part's shared-node force sum, the ``synchronize`` of
        :func:`jaxsync.fem.stepper.step` (:func:`synchronize_forces` across this runner's
        devices and processes)."""
        return functools.partial(synchronize_forces, shared_local=part.shared_local,
                                 shared_interface=part.shared_interface,
                                 n_interface=self.layout.n_interface, across=self.across)

    def _compiled(self, n_saves: int):
        if n_saves not in self._advance:
            self._advance[n_saves] = self.program(n_saves, record=self.record_shared)
        return self._advance[n_saves]

    def chunk_steps(self, steps_left: int, preferred: int) -> int:
        if steps_left % self._unit:
            raise ConfigError(f"with deep halos of depth {self.halo_depth} and save_every="
                              f"{self.save_every}, runs advance in multiples of {self._unit} steps; "
                              f"got {steps_left} steps: use a multiple of {self._unit}")
        return chunk_of_saves(steps_left, preferred, self._unit)

    def compile(self, state, steps: int) -> float:
        """Compile the program for chunks of ``steps`` steps ahead of time (so that chunk
        timings exclude it); returns the seconds spent (0 when already compiled)."""
        n_saves = steps // self.save_every
        if isinstance(self._compiled(n_saves), jax.stages.Compiled):
            return 0.0
        start = time.perf_counter()
        self._advance[n_saves] = self._compiled(n_saves).lower(self.parts, state).compile()
        return time.perf_counter() - start

    def advance(self, state, steps: int):
        """``steps`` steps (a multiple of save_every): (state, :class:`Chunk` with the
        global field (n_saves, n_nodes, 3) and, when recording, each part's shared-node
        displacements after every step (steps, 3 n_shared_p))."""
        state, saved = self._compiled(steps // self.save_every)(self.parts, state)
        if not self.record_shared:
            return state, Chunk(self._merge(to_host(saved), axis=1))
        full, shared = (to_host(x) for x in saved)
        per_part = [shared[p, :, :part.n_shared].reshape(shared.shape[1], -1)
                    for p, part in enumerate(self.partition.parts)]
        return state, Chunk(self._merge(full, axis=1), per_part)

    def _merge(self, local, axis):
        """Per-part local arrays (n_parts, ..., n_local, 3) -> global (..., n_nodes, 3)."""
        local = np.moveaxis(local, 0, axis - 1) if axis > 1 else local
        lead = local.shape[1:-2]
        flat = local.reshape(local.shape[0], *lead, self.n_local, 3)
        flat = np.moveaxis(flat, 0, -3).reshape(*lead, -1, 3)  # (..., n_parts * n_local, 3)
        out = np.zeros((*lead, self.partition.mesh.n_nodes, 3), dtype=flat.dtype)
        out[..., self.global_index, :] = flat[..., self.local_index, :]
        return out

    def to_global(self, state) -> SolverState:
        return SolverState(self._merge(to_host(state.displacement), axis=1),
                           self._merge(to_host(state.previous), axis=1),
                           int(to_host(state.step)[0]))

    def from_global(self, state: SolverState):
        def split(x):
            x = np.asarray(x)
            return np.stack([np.pad(x[p.nodes], ((0, self.n_local - p.n_local), (0, 0)))
                             for p in self.layout.parts])

        n_parts = self.partition.n_parts
        host = SolverState(split(state.displacement), split(state.previous),
                           np.full(n_parts, int(state.step), dtype=np.int32))
        return self.put(host)


def to_host(x) -> np.ndarray:
    """A (possibly multi-process) array as one host numpy array with all parts.

    One process: ``np.asarray``. Several processes: ``process_allgather`` returns a global
    array (``"psum"`` runs) whole, and concatenates the processes' local arrays (``"mpi"``
    runs: rank r's parts follow rank r - 1's) along the part axis."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    # device_get: ~10 ms for 50 MB over 2 devices; np.asarray took up to 0.15 s on a fresh
    # sharded array (measured), several us per step of a saved run
    return np.asarray(jax.device_get(x))
