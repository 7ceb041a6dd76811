"""The one builder of SPMD programs: a per-part function, vmapped over the parts that
share a device and ``jax.shard_map``-ed over the devices.

Every distributed program of jaxsync (the synchronized chunk, the predicted phase, the
stage timings, the training of the surrogate replicas) is built here, so the axis names
and the way parts map onto devices are defined once:

* the device axis is :data:`AXIS` (``"parts"``): array arguments carry all parts
  stacked on a leading axis, sharded over the devices in order (device d holds parts
  [d k, (d + 1) k), k = n_parts / n_devices);
* inside, the parts of one device form the vmapped axis :data:`LOCAL_AXIS`
  (``"local_parts"``), so a collective over all parts is a ``psum`` over
  ``LOCAL_AXIS`` and then one over ``AXIS``.
"""

from __future__ import annotations

import jax
from jax.sharding import PartitionSpec as P

__all__ = ["AXIS", "LOCAL_AXIS", "spmd_program", "part_spec"]

AXIS = "parts"  # the device axis of the shard_map
LOCAL_AXIS = "local_parts"  # the vmapped axis of several parts on one device


def part_spec() -> P:
    """The partition spec of an array stacked on the part axis."""
    return P(AXIS)


def spmd_program(per_part, device_mesh, *, n_in: int, n_out: int, replicated_in: tuple = (),
                 jit: bool = True):
    """``per_part(*args)`` for one part -> a program over all parts.

    Args:
        per_part: a pure function of one part's arguments (pytrees).
        device_mesh: a ``jax.sharding.Mesh`` with the one axis :data:`AXIS`.
        n_in, n_out: number of positional arguments and of outputs (an output tuple of
            ``n_out`` pytrees; ``n_out=1``: one pytree). Every argument is stacked on a
            leading part axis unless its position is in ``replicated_in`` (then it is the
            same on every part: not vmapped, not sharded).
        jit: wrap the result in ``jax.jit`` (False when the caller jits a larger
            function around it).

    Returns:
        The function of the stacked arguments (part axis first), each output stacked the
        same way.
    """
    replicated = set(replicated_in)
    in_axes = tuple(None if i in replicated else 0 for i in range(n_in))
    body = jax.vmap(per_part, in_axes=in_axes, axis_name=LOCAL_AXIS)
    in_specs = tuple(P() if i in replicated else P(AXIS) for i in range(n_in))
    out_specs = P(AXIS) if n_out == 1 else (P(AXIS),) * n_out
    # check_vma=False: the bodies mix per-part values with psum results (replicated),
    # which the varying-manual-axes check cannot type
    mapped = jax.shard_map(body, mesh=device_mesh, in_specs=in_specs, out_specs=out_specs,
                           check_vma=False)
    return jax.jit(mapped) if jit else mapped
