"""The parallel layer: parts, their index maps and the exchange between them, the one
SPMD builder, devices and processes.

Modules: :mod:`~jaxsync.parallel.partitioning` (METIS parts, owned/shared nodes),
:mod:`~jaxsync.parallel.layout` (padded local numbering, per-part systems, split and merge of
fields), :mod:`~jaxsync.parallel.exchange` (the exchange between the parts: index maps and
``scatter_reverse`` / ``scatter_forward`` of shared-node values, the exchange protocol, the
built-in exchanges and their registry, deep halos), :mod:`~jaxsync.parallel.spmd`
(:func:`spmd_program`, the builder of every SPMD program), :mod:`~jaxsync.parallel.devices`
(emulated CPU devices), :mod:`~jaxsync.parallel.multiprocess` (``mpiexec`` runs).
"""


from typing import TYPE_CHECKING

from ..lazy import export_lazily

__all__ = ["Partition", "Part", "partition", "partition_from_elements", "partition_of",
           "PartLayout", "PartSystems", "part_systems", "Exchange", "scatter_reverse", "scatter_forward",
           "synchronize_forces", "NeighbourExchange", "neighbour_exchange",
           "spmd_program", "AXIS", "LOCAL_AXIS", "devices", "multiprocess",
           "ExchangeStrategy", "ExchangePlan", "ExchangeCost", "xla_plan", "xla_devices"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    ".": ("devices", "multiprocess"),
    ".exchange": ("Exchange", "ExchangeCost", "ExchangePlan", "ExchangeStrategy", "NeighbourExchange",
                  "neighbour_exchange", "scatter_forward", "scatter_reverse", "synchronize_forces", "xla_devices",
                  "xla_plan"),
    ".layout": ("PartLayout", "PartSystems", "part_systems"),
    ".partitioning": ("Part", "Partition", "partition", "partition_from_elements", "partition_of"),
    ".spmd": ("AXIS", "LOCAL_AXIS", "spmd_program"),
})

if TYPE_CHECKING:
    from . import devices, multiprocess
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
    from .layout import PartLayout, PartSystems, part_systems
    from .partitioning import Part, Partition, partition, partition_from_elements, partition_of
    from .spmd import AXIS, LOCAL_AXIS, spmd_program
