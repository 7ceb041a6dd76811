"""Distributed explicit solver (paper Algorithm 1) with ``jax.shard_map``.

Each part computes the internal force of its own elements at its local nodes, so at
shared nodes it holds a partial sum. Synchronization sums the partials: every part
scatters its shared-node forces into one interface vector (global shared numbering),
``jax.lax.psum`` adds the vectors of all parts, and each part gathers the sums back.
After that every part holds the full force at all its local nodes, and the update of a
shared node is identical on every part that holds it.

Parts are padded to equal sizes (nodes, elements, neighbours, shared nodes) so that one
SPMD program serves all; padding nodes have unit mass, zero stiffness and are fixed at
zero. With n_parts a multiple of the device count, each device carries several parts
(a vmapped axis); the psum then runs over both the local part axis and the devices.

Two ways to form the internal force (paper Remark 2): ``"preassembled"``, the part's
sparse stiffness stored once (node-blocked ELL), and ``"recompute"``, where the element
geometry, strains and stresses are formed every step (standing in for nonlinear
materials).
"""

from __future__ import annotations

import functools
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jax.sharding import Mesh as DeviceMesh
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from ..errors import ConfigError, PartitionError, ProblemError
from .partition import Partition, partition as make_partition, partition_from_elements
from ..pytree import pytree_dataclass, static_field
from ..fem.element_force import MODES, ElementStiffness
from ..solve.stepper import ExplicitSystem, SolverState, advance
from ..fem.sparse import BlockEll, block_ell_values, node_adjacency, pad_block_ell

__all__ = ["PartSystems", "DistributedRunner", "build_part_systems", "synchronize_forces",
           "NeighbourExchange", "neighbour_exchange", "MODES", "AXIS"]

AXIS = "parts"  # the device axis of the shard_map
LOCAL_AXIS = "local_parts"  # the vmapped axis of several parts on one device


@pytree_dataclass
class PartSystems:
    """Per-part explicit systems stacked on a leading part axis (all arrays (n_parts, ...)).

    Attributes:
        system: :class:`ExplicitSystem` in local numbering, padded to n_local_max nodes.
        shared_local: (n_parts, n_shared_max) local index of each shared node (padding:
            n_local_max, out of range, so that scatters drop it).
        shared_interface: (n_parts, n_shared_max) interface index (padding: n_interface).
    """

    system: ExplicitSystem
    shared_local: Any
    shared_interface: Any


def _pad_to(arrays, length, fill, axis=0):
    out = []
    for a in arrays:
        pad = [(0, 0)] * a.ndim
        pad[axis] = (0, length - a.shape[axis])
        out.append(np.pad(a, pad, constant_values=fill))
    return np.stack(out)


def build_part_systems(problem, system: ExplicitSystem, partition: Partition, mode: str) -> PartSystems:
    """Split the global ``system`` into padded, stacked per-part systems (numpy-backed)."""
    from ..fem.assembly import element_blocks

    if mode not in MODES:
        raise ProblemError(f"mode must be one of {MODES}, got {mode!r}")
    if partition.mesh is not problem.mesh and not (
            partition.mesh.n_nodes == problem.mesh.n_nodes
            and np.array_equal(partition.mesh.tets, problem.mesh.tets)):
        raise PartitionError("the partition was made for another mesh: partition problem.mesh")
    parts = partition.parts
    n_parts = len(parts)
    n_local = max(p.n_local for p in parts)
    n_shared = max(max(p.n_shared for p in parts), 1)
    mass = np.asarray(system.mass)
    loads = np.asarray(system.load_vectors)
    fixed, fixed_values = np.asarray(system.fixed), np.asarray(system.fixed_values)
    m = problem.material
    lam, mu = float(m.lam), float(m.mu)

    if mode == "preassembled":
        k_lambda, k_mu = element_blocks(problem.mesh)
        columns, blocks = [], []
        for part in parts:
            dofs = (3 * part.local_tets[:, :, None] + np.arange(3)).reshape(-1, 12)
            rows, cols = np.repeat(dofs, 12, axis=1).ravel(), np.tile(dofs, (1, 12)).ravel()
            values = (lam * k_lambda[part.elements] + mu * k_mu[part.elements]).ravel()
            K = sp.coo_matrix((values, (rows, cols)), shape=(3 * part.n_local,) * 2).tocsr()
            adjacency = node_adjacency(part.local_tets, part.n_local)
            columns.append(adjacency)
            blocks.append(block_ell_values(K, adjacency))
        width = max(c.shape[1] for c in columns)
        padded = [pad_block_ell(c, b, n_local, width) for c, b in zip(columns, blocks)]
        columns = np.stack([c for c, _ in padded])
        blocks = np.stack([b for _, b in padded])
        stiffness = BlockEll(columns.astype(np.int32), blocks)
    else:
        n_elem = max(len(p.elements) for p in parts)
        tets = _pad_to([p.local_tets for p in parts], n_elem, 0).astype(np.int32)
        for p, part in enumerate(parts):  # padding elements repeat element 0, with weight 0
            tets[p, len(part.elements):] = part.local_tets[0]
        weight = _pad_to([np.ones(len(p.elements)) for p in parts], n_elem, 0.0)
        points = _pad_to([problem.mesh.points[p.nodes] for p in parts], n_local, 0.0)
        stiffness = ElementStiffness(points, tets, weight, np.full(n_parts, lam), np.full(n_parts, mu))

    def local(array, fill):
        return _pad_to([array[p.nodes] for p in parts], n_local, fill)

    # (n_loads, n_nodes, 3) -> (n_parts, n_loads, n_local_max, 3)
    local_loads = np.moveaxis(local(np.moveaxis(loads, 0, 1), 0.0), 2, 1)
    stacked = ExplicitSystem(
        stiffness=stiffness, mass=local(mass, 1.0),
        damping=np.full(n_parts, float(system.damping)), dt=np.full(n_parts, float(system.dt)),
        load_vectors=local_loads,
        load_times=jax.tree_util.tree_map(lambda x: np.full((n_parts,) + np.shape(x), x),
                                          system.load_times),
        fixed=local(fixed, True), fixed_values=local(fixed_values, 0.0))
    shared_local = _pad_to([p.shared_local for p in parts], n_shared, n_local).astype(np.int32)
    shared_interface = _pad_to([p.shared_interface for p in parts], n_shared,
                               partition.n_interface).astype(np.int32)
    return PartSystems(stacked, shared_local, shared_interface)


def synchronize_forces(internal, shared_local, shared_interface, n_interface: int, across=None):
    """Sum the parts' partial forces at shared nodes (scatter -> sum -> gather).

    ``internal`` is a part's (n_local_max, 3) partial force [dyn]; the interface vector is
    (n_interface + 1, 3). The sum runs over the parts on this device (the vmapped axis),
    then across devices: ``jax.lax.psum`` over the mesh axis when ``across`` is None, else
    ``across(interface)`` (the MPI Allreduce of :func:`jaxsync.parallel.multiprocess.make_allreduce`
    with one device per process, or a :class:`NeighbourExchange`)."""
    # one spare slot at the end receives the padding entries (index n_interface)
    interface = jnp.zeros((n_interface + 1, 3), internal.dtype)
    interface = interface.at[shared_interface].add(internal[shared_local], mode="clip")
    total = jax.lax.psum(interface, LOCAL_AXIS)  # parts on this device first
    total = jax.lax.psum(total, AXIS) if across is None else across(total)
    return internal.at[shared_local].set(total[shared_interface], mode="drop")


@pytree_dataclass
class NeighbourExchange:
    """Device-to-device exchange of shared-node forces with ``jax.lax.ppermute``: the
    cheaper alternative to a psum of the whole interface when each device shares nodes
    with a few others (a chain of parts along a beam: 2 neighbours, whatever n_c).

    For each device offset k in ``offsets``, device d sends to device (d + k) mod D the
    sums of its own parts at the nodes the two devices share, and adds what it receives
    from device (d - k) mod D. Offsets at which no two devices share a node are left out.
    Interface indices of padding slots are n_interface, the interface vector's spare
    slot, which is never read back.

    Attributes:
        send: (n_offsets, n_devices, width) int32 interface index of each value that
            device d sends at offset ``offsets[i]``.
        receive: (n_offsets, n_devices, width) int32 interface index at which device e
            adds each value received at offset ``offsets[i]`` (the same nodes, in the same
            order, as ``send[i, e - k]``).
        offsets: the device offsets k used (static).
    """

    send: Any
    receive: Any
    offsets: tuple = static_field(default=())

    def __call__(self, local_total):
        """(n_interface + 1, 3) sum over this device's parts -> sum over all parts."""
        n_devices = self.send.shape[1]
        device = jax.lax.axis_index(AXIS)
        send, receive = jnp.asarray(self.send), jnp.asarray(self.receive)
        total = local_total
        for i, k in enumerate(self.offsets):
            outgoing = local_total[send[i, device]]  # (width, 3)
            incoming = jax.lax.ppermute(outgoing, AXIS,
                                        perm=[(d, (d + k) % n_devices) for d in range(n_devices)])
            total = total.at[receive[i, device]].add(incoming)
        return total


def neighbour_exchange(partition: Partition, n_devices: int) -> NeighbourExchange:
    """The :class:`NeighbourExchange` of ``partition`` with its parts spread over
    ``n_devices`` devices in order (device d holds parts [d k, (d + 1) k), k = n_parts /
    n_devices, as :class:`DistributedRunner` places them)."""
    n_parts, n_interface = partition.n_parts, partition.n_interface
    if n_parts % n_devices:
        raise PartitionError(f"n_parts={n_parts} must be a multiple of n_devices={n_devices}")
    per_device = n_parts // n_devices
    on_device = [np.unique(np.concatenate(
        [partition.parts[p].shared_interface for p in range(d * per_device, (d + 1) * per_device)]
        + [np.zeros(0, dtype=np.int64)])) for d in range(n_devices)]
    offsets, pairs = [], []
    for k in range(1, n_devices):
        common = [np.intersect1d(on_device[d], on_device[(d + k) % n_devices]) for d in range(n_devices)]
        if any(len(c) for c in common):
            offsets.append(k)
            pairs.append(common)
    width = max([len(c) for common in pairs for c in common] + [1])
    send = np.full((len(offsets), n_devices, width), n_interface, dtype=np.int32)
    receive = np.full_like(send, n_interface)
    for i, (k, common) in enumerate(zip(offsets, pairs)):
        for d, nodes in enumerate(common):
            send[i, d, :len(nodes)] = nodes
            receive[i, (d + k) % n_devices, :len(nodes)] = nodes
    return NeighbourExchange(send, receive, tuple(offsets))


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
    """Advances per-part states under ``shard_map`` (the driver interface of
    :class:`jaxsync.solve.solver.SingleDeviceRunner`)."""

    def __init__(self, problem, system: ExplicitSystem, partitions, *, save_every: int,
                 mode: str = "preassembled", seed: int = 0, devices=None, sync: str | None = None,
                 allreduce: str = "auto", comm=None, record_shared: bool = False):
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
                device: :class:`NeighbourExchange`) or ``"mpi"`` (one device per
                process, MPI Allreduce called from inside the compiled step).
                Default: :func:`jaxsync.parallel.multiprocess.default_sync` (``"mpi"`` across
                processes, measured faster; ``"psum"`` in one process).
            allreduce: with ``sync="mpi"``, ``"mpi4jax"``, ``"callback"`` or ``"auto"``
                (see :func:`jaxsync.parallel.multiprocess.make_allreduce`).
            comm: with ``sync="mpi"``, the mpi4py communicator (default a duplicate of
                ``COMM_WORLD``); rank r runs parts [r k, (r + 1) k), k = n_parts / size.
            record_shared: also keep every part's shared-node displacements after EVERY
                step (the surrogates' training data; small), whatever ``save_every``.
        """
        from . import multiprocess

        sync = multiprocess.default_sync() if sync is None else sync
        if sync not in multiprocess.SYNC_METHODS:
            raise ConfigError(f"sync must be one of {multiprocess.SYNC_METHODS}, got {sync!r}")
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
        devices = _default_devices(n_parts, devices, sync)
        if n_parts % len(devices):
            raise PartitionError(f"n_parts={n_parts} must be a multiple of the number of devices "
                                 f"({len(devices)})")
        self._part_slice = slice(None)
        self._allreduce = None
        if sync == "mpi":
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
            self._allreduce = multiprocess.make_allreduce(comm, allreduce)
        if sync == "ppermute":
            self._allreduce = neighbour_exchange(self.partition, len(devices))
        self.devices = devices
        self.device_mesh = DeviceMesh(np.array(devices), (AXIS,))
        self.sharding = NamedSharding(self.device_mesh, P(AXIS))
        self.save_every = save_every
        self.mode = mode
        self.record_shared = bool(record_shared)
        host = build_part_systems(problem, system, self.partition, mode)
        self.n_local = host.system.mass.shape[1]
        self.parts = self._put(host)
        self._advance = {}
        self._global_index = np.concatenate([p.nodes for p in self.partition.parts])
        self._local_index = np.concatenate(
            [p.index * self.n_local + np.arange(p.n_local) for p in self.partition.parts])

    def _put(self, tree):
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
        n_interface = self.partition.n_interface
        save_every = self.save_every if save_every is None else save_every
        across = self._allreduce

        def one_part(part: PartSystems, state: SolverState):
            sync = None
            if synchronize:
                sync = functools.partial(synchronize_forces, shared_local=part.shared_local,
                                         shared_interface=part.shared_interface,
                                         n_interface=n_interface, across=across)
            shared = None
            if record:
                def shared(s):
                    return s.displacement.at[part.shared_local].get(mode="fill", fill_value=0.0)
            return advance(part.system, state, n_saves, save_every, synchronize=sync, record=shared)

        body = jax.vmap(one_part, axis_name=LOCAL_AXIS)
        mapped = jax.shard_map(body, mesh=self.device_mesh, in_specs=(P(AXIS), P(AXIS)),
                               out_specs=(P(AXIS), P(AXIS)), check_vma=False)
        return jax.jit(mapped)

    def _compiled(self, n_saves: int):
        if n_saves not in self._advance:
            self._advance[n_saves] = self.program(n_saves, record=self.record_shared)
        return self._advance[n_saves]

    def compile(self, state, n_saves: int) -> float:
        """Compile the program for chunks of ``n_saves`` snapshots ahead of time (so that
        chunk timings exclude it); returns the seconds spent (0 when already compiled)."""
        if isinstance(self._compiled(n_saves), jax.stages.Compiled):
            return 0.0
        start = time.perf_counter()
        self._advance[n_saves] = self._compiled(n_saves).lower(self.parts, state).compile()
        return time.perf_counter() - start

    def advance(self, state, n_saves):
        """(state, saved (n_saves, n_nodes, 3) numpy, shared per part [(n_steps, 3
        n_shared_p)] after every step, or None when not recording)."""
        state, saved = self._compiled(n_saves)(self.parts, state)
        if not self.record_shared:
            return state, self._merge(_to_host(saved), axis=1), None
        full, shared = (_to_host(x) for x in saved)
        per_part = [shared[p, :, :part.n_shared].reshape(shared.shape[1], -1)
                    for p, part in enumerate(self.partition.parts)]
        return state, self._merge(full, axis=1), per_part

    def _merge(self, local, axis):
        """Per-part local arrays (n_parts, ..., n_local, 3) -> global (..., n_nodes, 3)."""
        local = np.moveaxis(local, 0, axis - 1) if axis > 1 else local
        lead = local.shape[1:-2]
        flat = local.reshape(local.shape[0], *lead, self.n_local, 3)
        flat = np.moveaxis(flat, 0, -3).reshape(*lead, -1, 3)  # (..., n_parts * n_local, 3)
        out = np.zeros((*lead, self.partition.mesh.n_nodes, 3), dtype=flat.dtype)
        out[..., self._global_index, :] = flat[..., self._local_index, :]
        return out

    def to_global(self, state) -> SolverState:
        return SolverState(self._merge(_to_host(state.displacement), axis=1),
                           self._merge(_to_host(state.previous), axis=1),
                           int(_to_host(state.step)[0]))

    def from_global(self, state: SolverState):
        def split(x):
            x = np.asarray(x)
            return np.stack([np.pad(x[p.nodes], ((0, self.n_local - p.n_local), (0, 0)))
                             for p in self.partition.parts])

        n_parts = self.partition.n_parts
        host = SolverState(split(state.displacement), split(state.previous),
                           np.full(n_parts, int(state.step), dtype=np.int32))
        return self._put(host)


def _to_host(x) -> np.ndarray:
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
