"""Owned/shared index maps of the parts and the exchange of shared-node values.

Each part computes the internal force of its own elements at its local nodes, so at
shared nodes it holds a partial sum. The exchange has two directions, named as in
dolfinx's index maps:

* :func:`scatter_reverse` (collective): every part adds its shared-node values into one
  interface vector (global shared numbering); the vectors of all parts are summed
  (``jax.lax.psum``, an MPI Allreduce or a :class:`NeighbourExchange`).
* :func:`scatter_forward` (local): every part reads the summed interface values back
  into its shared nodes.

:func:`synchronize_forces` is the two in sequence (paper Algorithm 1): after it every
part holds the full force at all its local nodes, and the update of a shared node is
identical on every part that holds it.

Parts are padded to equal sizes (nodes, elements, neighbours, shared nodes) so that one
SPMD program serves all; padding nodes have unit mass, zero stiffness and are fixed at
zero. With n_parts a multiple of the device count, each device carries several parts
(a vmapped axis); the sum then runs over both the local part axis and the devices.

Two ways to form the internal force (paper Remark 2): ``"preassembled"``, the part's
sparse stiffness stored once (node-blocked ELL), and ``"recompute"``, where the element
geometry, strains and stresses are formed every step (standing in for nonlinear
materials).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from ..errors import PartitionError, ProblemError
from ..fem.element_force import ElementStiffness
from ..fem.sparse import BlockEll, block_ell_values, node_adjacency, pad_block_ell
from ..fem.stepper import ExplicitSystem
from ..options import Mode, check_option
from ..pytree import pytree_dataclass, static_field
from .partitioning import Partition
from .spmd import AXIS, LOCAL_AXIS

__all__ = ["PartSystems", "build_part_systems", "synchronize_forces", "scatter_reverse",
           "scatter_forward", "NeighbourExchange", "neighbour_exchange", "AXIS", "LOCAL_AXIS"]


@pytree_dataclass
class PartSystems:
    """Per-part explicit systems stacked on a leading part axis (all arrays (n_parts, ...)).

    Attributes:
        system: :class:`ExplicitSystem` in local numbering, padded to n_local_max nodes.
        shared_local: (n_parts, n_shared_max) local index of each shared node (padding:
            n_local_max, out of range, so that scatters drop it).
        shared_interface: (n_parts, n_shared_max) interface index (padding: n_interface).
        owned: (n_parts, n_local_max) bool, the nodes each part owns, for deep halos
            (:mod:`jaxsync.parallel.halo`); None for an element partition.
    """

    system: ExplicitSystem
    shared_local: Any
    shared_interface: Any
    owned: Any = None

    def shared_displacement(self, state):
        """One part's (n_shared_max, 3) displacements at its shared nodes in ``state``
        (padding slots read 0): what the distributed solver records after every step, the
        surrogates' training data and input history."""
        return state.displacement.at[self.shared_local].get(mode="fill", fill_value=0.0)


def _pad_to(arrays, length, fill, axis=0):
    out = []
    for a in arrays:
        pad = [(0, 0)] * a.ndim
        pad[axis] = (0, length - a.shape[axis])
        out.append(np.pad(a, pad, constant_values=fill))
    return np.stack(out)


def build_part_systems(problem, system: ExplicitSystem, partition: Partition, mode: str) -> PartSystems:
    """Split the global ``system`` into padded, stacked per-part systems (numpy-backed).

    ``partition``: a :class:`Partition`, or a :class:`jaxsync.parallel.halo.HaloPartition`
    (its grown parts, its halo interface and its owned nodes)."""
    from ..fem.assembly import element_blocks

    check_option("mode", mode, Mode, error=ProblemError)
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
        stiffness = BlockEll(columns.astype(np.int32), blocks, symmetric=True)
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
    owned = None
    if getattr(partition, "owned_local", None) is not None:
        owned = np.zeros((n_parts, n_local), dtype=bool)
        for p, local in enumerate(partition.owned_local):
            owned[p, local] = True
    return PartSystems(stacked, shared_local, shared_interface, owned)


def scatter_reverse(local, shared_local, shared_interface, n_interface: int, across=None):
    """Sum the parts' values at shared nodes into the interface vector. Collective: every
    part of every device must call it in the same step.

    ``local`` is a part's (n_local_max, c) array (partial forces [dyn], c = 3; or both
    displacement levels of deep halos, c = 6); returns the (n_interface + 1, c) interface
    vector summed over all parts (the last slot receives
    the padding entries, index n_interface, and is never read back). The sum runs over
    the parts on this device (the vmapped axis), then across devices: ``jax.lax.psum``
    over the mesh axis when ``across`` is None, else ``across(interface)`` (the MPI
    Allreduce of :func:`jaxsync.parallel.multiprocess.make_allreduce` with one device per
    process, or a :class:`NeighbourExchange`)."""
    interface = jnp.zeros((n_interface + 1,) + local.shape[1:], local.dtype)
    interface = interface.at[shared_interface].add(local[shared_local], mode="clip")
    total = jax.lax.psum(interface, LOCAL_AXIS)  # parts on this device first
    return jax.lax.psum(total, AXIS) if across is None else across(total)


def scatter_forward(local, interface, shared_local, shared_interface):
    """A part's (n_local_max, c) array with its shared nodes set to the interface values
    (n_interface + 1, c) of :func:`scatter_reverse` (local: no communication)."""
    return local.at[shared_local].set(interface[shared_interface], mode="drop")


def synchronize_forces(internal, shared_local, shared_interface, n_interface: int, across=None):
    """Sum the parts' partial forces at shared nodes (paper Algorithm 1):
    :func:`scatter_reverse` then :func:`scatter_forward`. Collective."""
    total = scatter_reverse(internal, shared_local, shared_interface, n_interface, across)
    return scatter_forward(internal, total, shared_local, shared_interface)


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
