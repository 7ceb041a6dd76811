"""The exchange between the parts of a distributed run.

- :mod:`.index_maps`: the owned/shared index maps of the parts and the exchange of
  shared-node values (:class:`Exchange`, ``scatter_reverse`` / ``scatter_forward``, the
  neighbour exchange);
- :mod:`.protocol`: the exchange protocol (:class:`ExchangeStrategy`: ``plan(partition,
  devices)`` gives the layout and the exchange, :class:`ExchangePlan`, and its cost);
- :mod:`.builtin`: the built-in exchanges (:class:`Psum`, :class:`Ppermute`, :class:`Mpi`,
  :class:`Halo`) and the registry of exchanges by name (:func:`register_exchange`, entry
  points);
- :mod:`.halo`: deep halos, the exact communication-avoiding scheme for central differences.

An exchange of your own is one module implementing :class:`ExchangeStrategy` and one
:func:`register_exchange` (the guide Adding an exchange).
"""

from typing import TYPE_CHECKING

from ...lazy import export_lazily

__all__ = [
    "Exchange", "synchronize_forces", "scatter_reverse", "scatter_forward", "NeighbourExchange",
    "neighbour_exchange", "AXIS", "LOCAL_AXIS", "ExchangeStrategy", "ExchangePlan", "ExchangeCost", "xla_plan",
    "xla_devices", "Psum", "Ppermute", "Mpi", "Halo", "sync_strategy", "transport", "register_exchange",
    "unregister_exchange", "exchange_names", "ENTRY_POINT_GROUP", "EntryPointWarning", "HaloPartition",
    "halo_partition", "check_halo_depth", "refresh_halo", "advance_halo", "check_save_every",
]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    ".index_maps": ("AXIS", "Exchange", "LOCAL_AXIS", "NeighbourExchange", "neighbour_exchange", "scatter_forward",
                    "scatter_reverse", "synchronize_forces"),
    ".protocol": ("ExchangeCost", "ExchangePlan", "ExchangeStrategy", "xla_devices", "xla_plan"),
    ".builtin": ("ENTRY_POINT_GROUP", "EntryPointWarning", "Halo", "Mpi", "Ppermute", "Psum", "exchange_names",
                 "register_exchange", "sync_strategy", "transport", "unregister_exchange"),
    ".halo": ("HaloPartition", "advance_halo", "check_halo_depth", "check_save_every", "halo_partition",
              "refresh_halo"),
})

if TYPE_CHECKING:
    from .builtin import (
        ENTRY_POINT_GROUP,
        EntryPointWarning,
        Halo,
        Mpi,
        Ppermute,
        Psum,
        exchange_names,
        register_exchange,
        sync_strategy,
        transport,
        unregister_exchange,
    )
    from .halo import HaloPartition, advance_halo, check_halo_depth, check_save_every, halo_partition, refresh_halo
    from .index_maps import (
        AXIS,
        LOCAL_AXIS,
        Exchange,
        NeighbourExchange,
        neighbour_exchange,
        scatter_forward,
        scatter_reverse,
        synchronize_forces,
    )
    from .protocol import ExchangeCost, ExchangePlan, ExchangeStrategy, xla_devices, xla_plan
