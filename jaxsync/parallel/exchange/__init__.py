"""The exchange between the parts of a distributed run. The modules are private; these
names are the package's interface:

- the owned/shared index maps of the parts and the exchange of shared-node values:
  :class:`Exchange`, :func:`scatter_reverse` / :func:`scatter_forward`,
  :func:`synchronize_forces`, the neighbour exchange (:class:`NeighbourExchange`,
  :func:`neighbour_exchange`) and the axes of the parts (:data:`AXIS`,
  :data:`LOCAL_AXIS`);
- the exchange protocol: :class:`ExchangeStrategy` (``plan(partition, devices)`` gives the
  layout and the exchange, :class:`ExchangePlan`, and its cost, :class:`ExchangeCost`;
  :func:`xla_plan`, :func:`xla_devices`);
- the built-in exchanges (:class:`Psum`, :class:`Ppermute`, :class:`Mpi`, :class:`Halo`;
  :func:`transport` describes one) and the registry of exchanges by name
  (:func:`sync_strategy`, :func:`register_exchange`, :func:`unregister_exchange`,
  :func:`exchange_names`; installed packages name theirs through the entry points of
  :data:`ENTRY_POINT_GROUP`, :class:`EntryPointWarning`);
- deep halos, the exact communication-avoiding scheme for central differences:
  :class:`HaloPartition`, :func:`halo_partition`, :func:`check_halo_depth`,
  :func:`refresh_halo`, :func:`advance_halo`, :func:`check_save_every`.

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
    "._index_maps": ("AXIS", "Exchange", "LOCAL_AXIS", "NeighbourExchange", "neighbour_exchange", "scatter_forward",
                    "scatter_reverse", "synchronize_forces"),
    "._protocol": ("ExchangeCost", "ExchangePlan", "ExchangeStrategy", "xla_devices", "xla_plan"),
    "._builtin": ("ENTRY_POINT_GROUP", "EntryPointWarning", "Halo", "Mpi", "Ppermute", "Psum", "exchange_names",
                 "register_exchange", "sync_strategy", "transport", "unregister_exchange"),
    "._halo": ("HaloPartition", "advance_halo", "check_halo_depth", "check_save_every", "halo_partition",
              "refresh_halo"),
})

if TYPE_CHECKING:
    from ._builtin import (
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
    from ._halo import HaloPartition, advance_halo, check_halo_depth, check_save_every, halo_partition, refresh_halo
    from ._index_maps import (
        AXIS,
        LOCAL_AXIS,
        Exchange,
        NeighbourExchange,
        neighbour_exchange,
        scatter_forward,
        scatter_reverse,
        synchronize_forces,
    )
    from ._protocol import ExchangeCost, ExchangePlan, ExchangeStrategy, xla_devices, xla_plan
