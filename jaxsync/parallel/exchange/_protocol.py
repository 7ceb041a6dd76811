"""The exchange protocol: how a distributed run's parts are laid out on the devices and how
they exchange their shared-node values.

An *exchange* is any object with the methods of :class:`ExchangeStrategy`; the built-in
ones are :class:`jaxsync.Psum`, :class:`jaxsync.Ppermute`, :class:`jaxsync.Mpi` and
:class:`jaxsync.Halo`, and a run takes any other as ``sync=`` (a name on the command line
through :func:`jaxsync.solve.register_exchange`). Its :meth:`~ExchangeStrategy.plan`
turns the element partition of a run into an :class:`ExchangePlan`, which holds all that
the solvers need of it:

* the part geometry (``parts``: the partition, or its grown parts for deep halos) and its
  padded :class:`~jaxsync.parallel.PartLayout`;
* the devices, the parts this process holds and whether values cross processes through
  MPI;
* the :class:`~jaxsync.parallel.exchange.Exchange` that runs inside the compiled step
  (its ``across`` function sums the interface vector across devices);
* its :class:`ExchangeCost`: bytes and messages of one exchange, how often it exchanges,
  and the cost model's algorithm for it (:mod:`jaxsync.perf.costmodel`).

Nothing outside the plan asks which exchange it is: the solvers, the timings and the cost
model read the plan. :func:`xla_plan` builds the plan of any exchange whose values cross
devices through XLA's collectives inside one SPMD program, so that a new exchange only
writes its ``across`` function (``docs/guides/extending-exchanges.md``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Protocol, runtime_checkable

import jax

from ...errors import ConfigError, PartitionError
from ...perf.costmodel import ALGORITHMS, CommunicationPattern, communication_pattern, sync_time
from .._layout import PartLayout
from ._index_maps import Exchange

__all__ = ["ExchangeStrategy", "ExchangePlan", "ExchangeCost", "xla_plan", "xla_devices"]


@dataclasses.dataclass(frozen=True)
class ExchangeCost:
    """The communication of one exchange, for the timings and the cost model.

    Attributes:
        pattern: the messages of one exchange
            (:class:`jaxsync.perf.costmodel.CommunicationPattern`: the interface size, the
            nodes each part shares with each neighbour, values per node: 3 for forces, 6
            for both displacement levels of deep halos).
        algorithm: how the cost model prices one exchange, one of
            :data:`jaxsync.perf.costmodel.ALGORITHMS`.
        every: steps between two exchanges (1: every step; k for deep halos of depth k).
    """

    pattern: CommunicationPattern
    algorithm: str = "allreduce"
    every: int = 1

    def __post_init__(self):
        if self.algorithm not in ALGORITHMS:
            raise ConfigError(f"ExchangeCost.algorithm={self.algorithm!r}: use one of {ALGORITHMS}")
        if isinstance(self.every, bool) or not isinstance(self.every, int) or self.every < 1:
            raise ConfigError(f"ExchangeCost.every must be a positive integer (steps between exchanges), "
                              f"got {self.every!r}")

    @property
    def bytes_per_exchange(self) -> int:
        """S, bytes of the whole interface vector one exchange sums."""
        return self.pattern.interface_bytes

    @property
    def bytes_per_step(self) -> float:
        """S / every: interface bytes per solver step."""
        return self.pattern.interface_bytes / self.every

    @property
    def messages_per_part(self) -> int:
        """The most neighbours one part exchanges with (the messages of a neighbour exchange)."""
        return max((len(row) for row in self.pattern.neighbours), default=0)

    def time_per_exchange(self, interconnect) -> float:
        """Predicted seconds of one exchange on ``interconnect`` (an
        :class:`~jaxsync.perf.costmodel.Interconnect` or a preset name):
        :func:`jaxsync.perf.costmodel.sync_time`."""
        return sync_time(self.pattern, interconnect, self.algorithm)

    def time_per_step(self, interconnect) -> float:
        """Predicted seconds per solver step: one exchange spread over ``every`` steps."""
        return self.time_per_exchange(interconnect) / self.every


@dataclasses.dataclass(frozen=True, eq=False)
class ExchangePlan:
    """What a partitioned run needs of its exchange (built on the host, static).

    Attributes:
        parts: the part geometry the programs hold: the element
            :class:`~jaxsync.parallel.Partition`, or a
            :class:`~jaxsync.parallel.exchange.HaloPartition` (parts grown by deep halos).
        layout: the padded :class:`~jaxsync.parallel.PartLayout` of ``parts``.
        exchange: the :class:`~jaxsync.parallel.exchange.Exchange` the compiled step calls.
        devices: the devices of the run's mesh, in order (device d holds parts
            [d k, (d + 1) k), k = n_parts / n_devices).
        cost: the :class:`ExchangeCost` of one exchange.
        part_slice: the parts this process holds and places (MPI: its own; else all).
        transport: ``"xla"`` (XLA's collectives over ``devices``) or ``"mpi"`` (one device
            per process, values cross processes through MPI inside the step; such a run is
            driven by the host executor of every process).
    """

    parts: Any
    layout: PartLayout
    exchange: Exchange
    devices: tuple
    cost: ExchangeCost
    part_slice: slice = dataclasses.field(default_factory=lambda: slice(None))
    transport: str = "xla"

    @classmethod
    def of(cls, parts, devices, across: Callable | None = None, *, algorithm: str = "collective",
           part_slice: slice = slice(None), transport: str = "xla") -> "ExchangePlan":
        """The plan of ``parts`` on ``devices`` whose exchange sums the interface vector with
        ``across`` (:func:`xla_plan`) every step; its cost from the parts' interface
        (:func:`jaxsync.perf.costmodel.communication_pattern`) priced by ``algorithm``.

        Raises:
            PartitionError: a part count that is not a multiple of the device count."""
        devices = tuple(devices)
        if parts.n_parts % len(devices):
            raise PartitionError(f"n_parts={parts.n_parts} must be a multiple of the number of devices "
                                 f"({len(devices)})")
        cost = ExchangeCost(communication_pattern(parts), algorithm)
        return cls(parts=parts, layout=PartLayout.of(parts), exchange=Exchange(parts.n_interface, across),
                   devices=devices, cost=cost, part_slice=part_slice, transport=transport)

    def with_halo_depth(self, depth: int) -> "ExchangePlan":
        """The same plan exchanging both displacement levels (6 values per node) every
        ``depth`` steps instead of forces every step: deep halos
        (:mod:`jaxsync.parallel.exchange`; ``parts`` the grown parts of that depth)."""
        pattern = dataclasses.replace(self.cost.pattern, dofs_per_node=6)
        exchange = dataclasses.replace(self.exchange, halo_depth=depth,
                                       n_element_interface=getattr(self.parts, "n_element_interface", 0))
        return dataclasses.replace(self, exchange=exchange,
                                   cost=dataclasses.replace(self.cost, pattern=pattern, every=depth))

    @property
    def halo_depth(self) -> int | None:
        """k of deep halos (steps between two exchanges of displacements), else None."""
        return self.exchange.halo_depth

    @property
    def n_parts(self) -> int:
        return self.parts.n_parts


@runtime_checkable
class ExchangeStrategy(Protocol):
    """How the parts of a distributed run exchange: the protocol of ``sync=``.

    Implement it with a frozen dataclass (its fields are the exchange's options) and pass
    an instance as ``sync=`` to :func:`jaxsync.simulate`,
    :func:`jaxsync.simulate_sync_avoiding` and the timings, or register a factory with
    :func:`jaxsync.solve.register_exchange` to name it on the command line.

    Attributes:
        name: a short label, printed and written to reports; never used to choose
            behaviour.
        synchronizes_every_step: True when after every step every part holds the
            synchronized values at all its shared nodes (a force sum every step): only
            such an exchange can record every step's shared-node history (the
            surrogates' training data) and serve the synchronized stretches of a
            synchronization-avoiding run. False for deep halos.
    """

    name: str
    synchronizes_every_step: bool

    def plan(self, partition, devices=None) -> ExchangePlan:
        """The :class:`ExchangePlan` of a run of ``partition`` (an element
        :class:`~jaxsync.parallel.Partition`) on ``devices`` (None: the
        exchange's own choice, e.g. its ``devices`` field or :func:`xla_devices`)."""
        ...

    def transport(self, n_parts: int | None = None) -> str:
        """One line that says how a run of ``n_parts`` parts exchanges in this process's
        setting (``jaxsync simulate`` prints it; :func:`jaxsync.solve.transport`)."""
        ...


def xla_devices(n_parts: int, devices=None) -> tuple:
    """The devices of an XLA-collective run of ``n_parts`` parts: ``devices`` (default
    ``jax.devices()``), in one process the first d of them, d the largest count <= n_parts
    that divides n_parts; across processes all of them (each process must hold parts).

    Raises:
        PartitionError: across processes, n_parts not a multiple of the device count."""
    available = tuple(jax.devices() if devices is None else devices)
    if jax.process_count() > 1:
        if n_parts % len(available):
            raise PartitionError(
                f"n_parts={n_parts} must be a multiple of the {len(available)} devices of the "
                f"{jax.process_count()} processes; use a multiple of {len(available)} parts")
        return available
    n = max(d for d in range(1, min(len(available), n_parts) + 1) if n_parts % d == 0)
    return available[:n]


def xla_plan(parts, devices, across: Callable | None = None, *, algorithm: str = "collective") -> ExchangePlan:
    """The plan of an exchange through XLA's collectives inside one SPMD program
    (:meth:`ExchangePlan.of` with ``transport="xla"``).

    Args:
        parts: the part geometry (a :class:`~jaxsync.parallel.Partition`).
        devices: the devices, one SPMD program over all of them (:func:`xla_devices`).
        across: ``across(total) -> summed``, called inside the compiled step under
            ``jax.shard_map`` over the device axis :data:`jaxsync.parallel.AXIS`: ``total``
            is the (n_interface + 1, c) interface vector summed over this device's parts
            (c = 3 forces, or 6 for deep halos), the result the same summed over all
            devices. None: ``jax.lax.psum`` over the device axis.
        algorithm: the cost model's algorithm for one exchange
            (:data:`jaxsync.perf.costmodel.ALGORITHMS`).
    """
    return ExchangePlan.of(parts, devices, across, algorithm=algorithm)
