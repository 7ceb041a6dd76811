"""The parallel layer: parts, their index maps and the exchange between them, the one
SPMD builder, devices and processes. The implementation modules are private; these names
are its interface:

- parts, with their owned and shared nodes (METIS): :func:`partition`, :class:`Partition`,
  :class:`Part`, :func:`partition_from_elements`, :func:`partition_of`;
- the padded local numbering and the per-part systems: :class:`PartLayout`,
  :class:`PartSystems`, :func:`part_systems`; the order of a part's local nodes:
  :func:`local_order`, :func:`ordered_parts`;
- :mod:`~jaxsync.parallel.exchange`: the exchange between the parts (index maps and
  ``scatter_reverse`` / ``scatter_forward`` of shared-node values, the exchange protocol,
  the built-in exchanges and their registry, deep halos; its main names are re-exported
  here);
- :func:`spmd_program`, the builder of every SPMD program (:data:`AXIS`,
  :data:`LOCAL_AXIS`, :func:`part_spec`);
- two modules used as namespaces: :mod:`~jaxsync.parallel.devices` (emulated CPU devices,
  ``jaxsync.devices.request_cpu_devices(2)``) and :mod:`~jaxsync.parallel.multiprocess`
  (``mpiexec`` runs).
"""

from typing import TYPE_CHECKING

from ..lazy import export_lazily

__all__ = ["Partition", "Part", "partition", "partition_from_elements", "partition_of", "PartLayout", "PartSystems",
           "part_systems", "Exchange", "scatter_reverse", "scatter_forward", "synchronize_forces", "NeighbourExchange",
           "neighbour_exchange", "spmd_program", "AXIS", "LOCAL_AXIS", "devices", "multiprocess", "ExchangeStrategy",
           "ExchangePlan", "ExchangeCost", "xla_plan", "xla_devices", "local_order", "ordered_parts", "part_spec"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    ".": ("devices", "multiprocess"),
    ".exchange": ("Exchange", "ExchangeCost", "ExchangePlan", "ExchangeStrategy", "NeighbourExchange",
                  "neighbour_exchange", "scatter_forward", "scatter_reverse", "synchronize_forces", "xla_devices",
                  "xla_plan"),
    "._layout": ("PartLayout", "PartSystems", "local_order", "ordered_parts", "part_systems"),
    "._partitioning": ("Part", "Partition", "partition", "partition_from_elements", "partition_of"),
    "._spmd": ("AXIS", "LOCAL_AXIS", "part_spec", "spmd_program"),
})

if TYPE_CHECKING:
    from . import devices, multiprocess
    from ._layout import PartLayout, PartSystems, local_order, ordered_parts, part_systems
    from ._partitioning import Part, Partition, partition, partition_from_elements, partition_of
    from ._spmd import AXIS, LOCAL_AXIS, part_spec, spmd_program
    from .exchange import (
        Exchange,
        ExchangeCost,
        ExchangePlan,
        ExchangeStrategy,
        NeighbourExchange,
        neighbour_exchange,
        scatter_forward,
        scatter_reverse,
        synchronize_forces,
        xla_devices,
        xla_plan,
    )
