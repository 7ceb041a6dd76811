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

Parts are padded to equal sizes (:mod:`jaxsync.parallel`) so that one SPMD program
serves all. With n_parts a multiple of the device count, each device carries several
parts (a vmapped axis); the sum then runs over both the local part axis and the devices.
An :class:`Exchange` holds what a program needs to call these verbs: the interface size,
how values cross devices and processes, and the halo depth of deep halos.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import PartitionError
from ...pytree import pytree_dataclass, static_field
from .._partitioning import Partition
from .._spmd import AXIS, LOCAL_AXIS

__all__ = ["Exchange", "synchronize_forces", "scatter_reverse", "scatter_forward", "NeighbourExchange",
           "neighbour_exchange", "AXIS", "LOCAL_AXIS"]


@dataclasses.dataclass(frozen=True, eq=False)
class Exchange:
    """How the parts of one SPMD program complete their shared values.

    Attributes:
        n_interface: interface nodes (of the partition, or of a halo's exchanged nodes).
        across: how the interface vector summed over a device's parts is summed across
            devices: None (``jax.lax.psum`` over the device axis), a
            :class:`NeighbourExchange`, or an MPI Allreduce
            (:func:`jaxsync.parallel.multiprocess.make_allreduce`).
        halo_depth: None (the parts sum their forces every step) or k, deep halos
            (:mod:`jaxsync.parallel.exchange`: both displacement levels every k steps).
        n_element_interface: elements whose internal variables deep halos exchange (0:
            none).
    """

    n_interface: int
    across: Callable | None = None
    halo_depth: int | None = None
    n_element_interface: int = 0

    def force_sum(self, part) -> Callable:
        """One part's shared-node force sum (the ``synchronize`` of
        :func:`jaxsync.fem.step`), for ``part`` a
        :class:`jaxsync.parallel.PartSystems` of one part."""
        return functools.partial(synchronize_forces, shared_local=part.shared_local,
                                 shared_interface=part.shared_interface, n_interface=self.n_interface,
                                 across=self.across)


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
