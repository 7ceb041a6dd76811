"""The parts of a distributed run (paper Algorithm 1), and the host runner that advances
them in compiled chunks.

:class:`DistributedParts` is what both executors need of a distributed run, built once
on the host from the problem's mesh and the partition: the padded layout
(:class:`~jaxsync.parallel.PartLayout`), the devices and how the parts exchange
across them (the :class:`~jaxsync.parallel.exchange.ExchangePlan` of the run's ``sync``
exchange), and the force model. Its :meth:`~DistributedParts.systems` are JAX functions of
the problem's global system, so traced material, damping, loads and dt flow through.

:class:`DistributedRunner` is the host executor's runner of synchronized steps
(:mod:`jaxsync.solve.executors`): the parts placed on their devices, the SPMD program of
:func:`jaxsync.solve.executors.part_synchronized_steps` per chunk length, and the way
between per-part states and the global one.
"""

from __future__ import annotations

import time

import jax
import numpy as np
from jax.sharding import Mesh as DeviceMesh
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from ...errors import ConfigError
from ...fem._stepper import ExplicitSystem, SolverState
from ...fem.forces._internal_force import force_model
from ...parallel._layout import PartSystems, part_systems
from ...parallel._partitioning import Partition, partition_from_elements
from ...parallel._partitioning import partition as make_partition
from ...parallel._spmd import AXIS, spmd_program
from ...parallel.exchange._builtin import sync_strategy
from ...parallel.exchange._halo import check_save_every
from ._driver import Chunk, chunk_of_saves
from ._phases import check_recordable, part_synchronized_steps, synchronized_steps

__all__ = ["DistributedParts", "DistributedRunner", "to_host"]


def _partition(problem, partitions) -> Partition:
    """The :class:`Partition` of ``partitions`` on the problem's nodes (a Partition, or an
    int: METIS with seed 0; in a multi-process run every rank takes rank 0's parts). A
    partition of the problem's mesh made for other nodes (a P1 partition of a P2 problem)
    is rebuilt on the problem's nodes with the same elements in each part."""
    if isinstance(partitions, Partition):
        if partitions.space is problem.space:
            return partitions
        if partitions.mesh is problem.mesh or (partitions.mesh.n_elements == problem.mesh.n_elements and
                                                np.array_equal(partitions.mesh.tets, problem.mesh.tets)):
            return partition_from_elements(problem.space, partitions.element_part, seed=partitions.seed)
        return partitions  # another mesh: refused with the fix when the parts are laid out
    partition = make_partition(problem, partitions)
    if jax.process_count() > 1:  # every rank must use rank 0's parts
        from jax.experimental import multihost_utils

        reference = np.asarray(multihost_utils.broadcast_one_to_all(partition.element_part))
        if not np.array_equal(reference, partition.element_part):
            partition = partition_from_elements(problem.space, reference)
    return partition


class DistributedParts:
    """The parts of a distributed run, their devices and their exchange (host, static).

    Args:
        problem: the problem (its mesh is partitioned).
        partitions: an int n_parts (METIS, seed 0; ``jaxsync.partition(mesh, n, seed=s)``
            for another seed) or a :class:`jaxsync.Partition`.
        sync: the exchange (:func:`jaxsync.parallel.exchange.sync_strategy`: a
            :class:`~jaxsync.parallel.exchange.Psum`, ``Ppermute``, ``Mpi``, ``Halo`` or any
            :class:`~jaxsync.parallel.exchange.ExchangeStrategy`, a registered name, or None
            for the default).
        mode: the force model (:func:`jaxsync.fem.forces.force_model`).
        devices: the devices to run on (None: the exchange's own choice); passed to
            the exchange's ``plan``.

    Attributes:
        partition: the element :class:`Partition`.
        sync: the exchange.
        plan: its :class:`~jaxsync.parallel.exchange.ExchangePlan` for this partition, which
            the attributes below unpack.
        layout: :class:`PartLayout` of the parts as the programs hold them (the grown
            parts of deep halos).
        exchange: :class:`Exchange` of the programs.
        transport: ``"mpi"`` (values cross processes through MPI from inside the step, one
            device per process) or ``"xla"`` (XLA's collectives).
        part_slice: the parts this process holds (MPI: its own; else all).
        devices, device_mesh, sharding: where the parts run (the part axis sharded over
            the devices in order).
    """

    def __init__(self, problem, partitions, sync=None, *, mode="preassembled", devices=None):
        self.sync = sync_strategy(sync)
        self.partition = _partition(problem, partitions)
        self.force_model = force_model(mode)
        self.plan = self.sync.plan(self.partition, devices)
        self.layout, self.exchange, self.devices = self.plan.layout, self.plan.exchange, list(self.plan.devices)
        self.part_slice, self.transport = self.plan.part_slice, self.plan.transport
        self.device_mesh = DeviceMesh(np.array(self.devices), (AXIS,))
        self.sharding = NamedSharding(self.device_mesh, P(AXIS))

    @property
    def n_parts(self) -> int:
        return self.partition.n_parts

    @property
    def halo_depth(self) -> int | None:
        return self.exchange.halo_depth

    def systems(self, problem, system: ExplicitSystem) -> PartSystems:
        """The parts' systems of ``system`` (:func:`jaxsync.parallel.part_systems`;
        JAX, not placed)."""
        return part_systems(problem, system, self.layout, self.force_model)

    def put(self, tree):
        """Place stacked host arrays (all parts) on the devices, sharded on the part axis.
        Multi-process: with XLA's collectives each process supplies only its addressable
        shards of the global array; with MPI each process places its own parts on its
        device."""
        def put(x):
            x = np.asarray(x)[self.part_slice]
            return jax.make_array_from_callback(x.shape, self.sharding, lambda index: x[index])

        return jax.tree_util.tree_map(put, tree)

    def spmd(self, per_part, *, n_in: int, n_out: int, jit: bool = True):
        """``per_part`` over all parts on this run's devices
        (:func:`jaxsync.parallel.spmd_program`)."""
        return spmd_program(per_part, self.device_mesh, n_in=n_in, n_out=n_out, jit=jit)

    def check_recordable(self) -> None:
        """Refuse to record every step's shared-node displacements with an exchange that
        does not synchronize every step (deep halos, or any exchange whose
        ``synchronizes_every_step`` is False): a :class:`~jaxsync.errors.ConfigError`
        naming the fix."""
        check_recordable(self.exchange)
        if not self.sync.synchronizes_every_step:
            raise ConfigError(
                f"sync={self.sync.name!r} does not synchronize every step, so the shared-node displacements "
                "after every step (the surrogates' training data, the synchronization-avoiding solver's "
                "synchronized phases) are not known; use an exchange that does, e.g. sync='psum'")

    def check_save_every(self, save_every: int) -> int:
        """The steps of the smallest whole chunk: ``save_every``, or with deep halos the
        larger of it and the depth (which must divide one another)."""
        return save_every if self.halo_depth is None else check_save_every(save_every, self.halo_depth)


class DistributedRunner:
    """Advances per-part states of synchronized steps under ``shard_map`` (a
    :class:`jaxsync.solve.executors.Runner`).

    Args:
        problem, system: the problem and its global :class:`ExplicitSystem`.
        partitions: an int n_parts, a :class:`Partition`, or the
            :class:`DistributedParts` of the run (shared with its predicted phase).
        save_every: steps between saved snapshots.
        mode, sync: as for :class:`DistributedParts` (ignored when ``partitions`` is one).
        record_shared: also keep every part's shared-node displacements after EVERY step
            (the surrogates' training data; small), whatever ``save_every``.
    """

    def __init__(self, problem, system: ExplicitSystem, partitions, *, save_every: int,
                 mode="preassembled", sync=None, record_shared: bool = False):
        self.distributed = (partitions if isinstance(partitions, DistributedParts)
                            else DistributedParts(problem, partitions, sync, mode=mode))
        d = self.distributed
        self.partition, self.layout, self.devices = d.partition, d.layout, d.devices
        self.device_mesh, self.sync, self.transport = d.device_mesh, d.sync.name, d.transport  # sync: a label
        self.save_every = save_every
        self.record_shared = bool(record_shared)
        self._unit = d.check_save_every(save_every)
        if record_shared:
            d.check_recordable()
        self.n_nodes = self.partition.n_nodes
        self.n_local = self.layout.n_local
        self.parts = d.put(d.systems(problem, system))
        self._advance = {}

    def put(self, tree):
        """:meth:`DistributedParts.put`."""
        return self.distributed.put(tree)

    def program(self, n_saves: int, *, save_every: int | None = None, synchronize: bool = True,
                record: bool = False):
        """The jitted SPMD program: ``(parts, state) -> (state, saved)`` advancing
        ``n_saves * save_every`` steps. ``synchronize=False`` leaves the exchange out (used
        to time it, paper section 7). ``record=True``: ``saved`` is the pair (full field
        every ``save_every`` steps, shared-node displacements (n_parts, n_steps,
        n_shared_max, 3) after every step; padding slots read 0)."""
        save_every = self.save_every if save_every is None else save_every
        exchange = self.distributed.exchange

        def one_part(part: PartSystems, state: SolverState):
            if not synchronize:
                return synchronized_steps(part.system, state, n_saves, save_every)
            return part_synchronized_steps(part, state, n_saves, save_every, exchange, record=record)

        return self.distributed.spmd(one_part, n_in=2, n_out=2)

    def _compiled(self, n_saves: int):
        if n_saves not in self._advance:
            self._advance[n_saves] = self.program(n_saves, record=self.record_shared)
        return self._advance[n_saves]

    def chunk_steps(self, steps_left: int, preferred: int) -> int:
        if steps_left % self._unit:
            raise ConfigError(f"with deep halos of depth {self.distributed.halo_depth} and save_every="
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
            return state, Chunk(self.merge(to_host(saved)))
        full, shared = (to_host(x) for x in saved)
        return state, Chunk(self.merge(full), self.shared_rows(shared))

    def shared_rows(self, shared) -> list:
        """Per part, (steps, 3 n_shared_p) rows of recorded (P, steps, n_shared_max, 3)."""
        return [shared[p, :, :part.n_shared].reshape(shared.shape[1], -1)
                for p, part in enumerate(self.partition.parts)]

    def merge(self, local, *, mean: bool = False) -> np.ndarray:
        """(P, ..., n_local, 3) host fields of the parts -> the global (..., n_nodes, 3)
        field (:meth:`PartLayout.merge`, on the host)."""
        with jax.default_device(jax.local_devices(backend="cpu")[0]):
            return np.asarray(self.layout.merge(local, mean=mean))

    def to_global(self, state) -> SolverState:
        """The global state of the parts' ``state`` (host numpy)."""
        from ...parallel._element_fields import merge_element_fields

        return SolverState(self.merge(to_host(state.displacement)), self.merge(to_host(state.previous)),
                           int(to_host(state.step)[0]),
                           merge_element_fields(self.layout.parts, jax.tree_util.tree_map(to_host, state.internal),
                                                self.partition.mesh.n_elements,
                                                getattr(self.layout.partition, "element_owner", None)))

    def from_global(self, state: SolverState):
        """The parts' state of a global ``state``, placed on the devices."""
        with jax.default_device(jax.local_devices(backend="cpu")[0]):
            local = jax.tree_util.tree_map(np.asarray, self.layout.split_state(state))
        return self.put(local)


def to_host(x) -> np.ndarray:
    """A (possibly multi-process) array as one host numpy array with all parts.

    One process: ``np.asarray``. Several processes: ``process_allgather`` returns a global
    array (XLA-collective runs) whole, and concatenates the processes' local arrays (MPI
    runs: rank r's parts follow rank r - 1's) along the part axis."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    # device_get: ~10 ms for 50 MB over 2 devices; np.asarray took up to 0.15 s on a fresh
    # sharded array (measured), several us per step of a saved run
    return np.asarray(jax.device_get(x))
