"""The built-in exchanges of a distributed run (``sync=``) and the registry of their names.

Every exchange implements :class:`jaxsync.parallel.exchange.ExchangeStrategy`: its
:meth:`plan` gives the part layout on the devices, the exchange the compiled step calls
and its cost (:class:`jaxsync.parallel.exchange.ExchangePlan`), and :meth:`transport` one
printable line. The solvers, the timings and the cost model read the plan and never ask
which exchange it is, so a new exchange is one class (``docs/guides/extending-exchanges.md``).

* :class:`Psum`: ``jax.lax.psum`` of the whole interface every step;
* :class:`Ppermute`: ``jax.lax.ppermute`` of the nodes neighbouring devices share;
* :class:`Mpi`: an MPI Allreduce inside the compiled step, one device per process;
* :class:`Halo`: deep halos, both displacement levels every k steps (exact).

Names. The command line's ``--sync`` strings and :func:`sync_strategy` map names onto
exchanges through one registry: :func:`register_exchange` adds a name (a user's exchange
too), :func:`exchange_names` lists them. ``"name:argument"`` passes the text after the
colon to the factory (``"halo:4"`` is ``Halo(4)``).
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import TYPE_CHECKING, Any, Callable

from ...errors import ConfigError

if TYPE_CHECKING:  # the command line builds its --sync choices from this module without JAX
    from ._protocol import ExchangePlan, ExchangeStrategy

__all__ = ["Psum", "Ppermute", "Mpi", "Halo", "sync_strategy", "transport", "register_exchange",
           "unregister_exchange", "exchange_names", "ENTRY_POINT_GROUP", "EntryPointWarning"]


def _devices(value):
    return None if value is None else tuple(value)


def _cost_algorithm() -> str:
    """How the cost model prices an XLA psum: one collective through shared memory in one
    process, an allreduce between processes."""
    from ..multiprocess import process_count

    return "collective" if process_count() == 1 else "allreduce"


@dataclasses.dataclass(frozen=True)
class Psum:
    """The parts sum their shared-node forces with ``jax.lax.psum`` over all devices every
    step (emulated devices in one process, gloo between CPU processes, NCCL between GPUs).

    Attributes:
        devices: the devices of the run (default: as many of ``jax.devices()`` as divide
            the part count; across processes all of them).
    """

    devices: tuple | None = None

    def __post_init__(self):
        object.__setattr__(self, "devices", _devices(self.devices))

    name = "psum"
    synchronizes_every_step = True

    def plan(self, partition, devices=None) -> ExchangePlan:
        """All parts in one SPMD program; ``psum`` over the device axis
        (:class:`~jaxsync.parallel.exchange.ExchangePlan`)."""
        from ._protocol import xla_devices, xla_plan

        devices = xla_devices(partition.n_parts, self.devices if devices is None else devices)
        return xla_plan(partition, devices, None, algorithm=_cost_algorithm())

    def transport(self, n_parts: int | None = None) -> str:
        """One line: how a run of ``n_parts`` parts exchanges (:func:`transport`)."""
        from ..multiprocess import collective_text

        return collective_text("psum", self.devices, n_parts)


@dataclasses.dataclass(frozen=True)
class Ppermute:
    """Each device sends only the nodes it shares with each neighbouring device
    (``jax.lax.ppermute``; :class:`jaxsync.parallel.exchange.NeighbourExchange`): cheaper
    than a psum of the whole interface when each device has few neighbours.

    Attributes:
        devices: as for :class:`Psum`.
    """

    devices: tuple | None = None

    def __post_init__(self):
        object.__setattr__(self, "devices", _devices(self.devices))

    name = "ppermute"
    synchronizes_every_step = True

    def plan(self, partition, devices=None) -> ExchangePlan:
        """All parts in one SPMD program; the neighbour exchange of ``partition`` over the
        devices (:func:`jaxsync.parallel.exchange.neighbour_exchange`)."""
        from ._index_maps import neighbour_exchange
        from ._protocol import xla_devices, xla_plan

        devices = xla_devices(partition.n_parts, self.devices if devices is None else devices)
        return xla_plan(partition, devices, neighbour_exchange(partition, len(devices)),
                        algorithm="collective-permute")

    def transport(self, n_parts: int | None = None) -> str:
        """One line: how a run of ``n_parts`` parts exchanges (:func:`transport`)."""
        from ..multiprocess import collective_text

        return collective_text("ppermute (neighbouring devices only)", self.devices, n_parts)


@dataclasses.dataclass(frozen=True)
class Mpi:
    """One device per process; the shared-node forces are summed by an MPI Allreduce
    called from inside the compiled step (processes started by ``mpiexec``).

    Attributes:
        allreduce: ``"mpi4jax"`` (mpi4jax's XLA custom call into MPI), ``"ctypes"``
            (jaxsync's own XLA FFI handler calling the MPI library that mpi4py loaded),
            ``"callback"`` (a host callback into mpi4py, slow) or ``"auto"`` (mpi4jax when
            importable, else ctypes, else the callback):
            :func:`jaxsync.parallel.multiprocess.make_allreduce`.
        comm: the mpi4py communicator (default a duplicate of ``COMM_WORLD``); rank r runs
            parts [r k, (r + 1) k), k = n_parts / size.
        devices: the one device of this process that runs its parts (default
            ``jax.local_devices()``, which must then be one).
    """

    allreduce: str = "auto"
    comm: Any = None
    devices: tuple | None = None

    def __post_init__(self):
        object.__setattr__(self, "devices", _devices(self.devices))
        from ..multiprocess import ALLREDUCE_BACKENDS

        if self.allreduce not in ALLREDUCE_BACKENDS:
            raise ConfigError(f"Mpi(allreduce=...) must be one of {ALLREDUCE_BACKENDS}, got {self.allreduce!r}")

    name = "mpi"
    synchronizes_every_step = True

    def plan(self, partition, devices=None) -> ExchangePlan:
        """This process's parts (rank r of the communicator: parts [r k, (r + 1) k)) on its
        one device; the interface summed by the MPI Allreduce of ``allreduce``."""
        import jax

        from ...errors import PartitionError
        from .. import multiprocess
        from ._protocol import ExchangePlan

        chosen = self.devices if devices is None else devices
        local = list(jax.local_devices() if chosen is None else chosen)
        if len(local) != 1 or local[0].process_index != jax.process_index():
            raise ConfigError(
                f"sync='mpi' runs each process's parts on one device of that process, got "
                f"{len(local)} devices; start one process per device (mpiexec -n N_devices), "
                "or use sync='psum'")
        comm = multiprocess.world().Dup() if self.comm is None else self.comm  # the step's collectives, apart
        size, rank = comm.Get_size(), comm.Get_rank()
        if size > 1 and jax.process_count() != size:
            raise ConfigError(
                f"sync='mpi' over {size} MPI ranks needs jax.distributed joined across them "
                f"(JAX sees {jax.process_count()} process); call "
                "jaxsync.parallel.multiprocess.initialize() at the start of every rank")
        n_parts = partition.n_parts
        if n_parts % size:
            raise PartitionError(f"n_parts={n_parts} must be a multiple of the {size} MPI "
                                 f"ranks; use a multiple of {size} parts")
        per_rank = n_parts // size
        return ExchangePlan.of(partition, local, multiprocess.make_allreduce(comm, self.allreduce),
                               algorithm="allreduce", part_slice=slice(rank * per_rank, (rank + 1) * per_rank),
                               transport="mpi")

    def transport(self, n_parts: int | None = None) -> str:
        """One line: how the processes sum (:func:`transport`)."""
        from ..multiprocess import allreduce_text

        return allreduce_text(self.allreduce)


@dataclasses.dataclass(frozen=True)
class Halo:
    """Deep halos (:mod:`jaxsync.parallel.exchange`), the exact communication-avoiding scheme:
    every part grown by ``depth`` layers of its neighbours' elements steps alone and
    exchanges both displacement levels of its halo every ``depth`` steps (through a psum
    in one process and across GPUs, through MPI across CPU processes). The same trajectory
    as the synchronized solver to round-off.

    Attributes:
        depth: k, the steps between two exchanges; ``save_every`` and k must divide one
            another.
        devices: as for :class:`Psum`.
    """

    depth: int = 1
    devices: tuple | None = None

    def __post_init__(self):
        from ...options import check_halo_depth

        object.__setattr__(self, "depth", check_halo_depth(self.depth))
        object.__setattr__(self, "devices", _devices(self.devices))

    name = "halo"
    synchronizes_every_step = False

    def carrier(self) -> ExchangeStrategy:
        """The exchange that moves the halos: the default one of this setting
        (:func:`jaxsync.parallel.multiprocess.default_sync`: a psum, MPI across CPU
        processes) on this halo's devices."""
        return dataclasses.replace(sync_strategy(None), devices=self.devices)

    def plan(self, partition, devices=None) -> ExchangePlan:
        """The parts grown by ``depth`` layers (:func:`jaxsync.parallel.exchange.halo_partition`)
        laid out by :meth:`carrier`, exchanging both displacement levels every ``depth``
        steps."""
        from ._halo import halo_partition

        return self.carrier().plan(halo_partition(partition, self.depth), devices).with_halo_depth(self.depth)

    def transport(self, n_parts: int | None = None) -> str:
        """One line: how the halos are exchanged (:func:`transport`)."""
        every = f"deep halos of depth {self.depth}, both displacement levels exchanged every {self.depth} steps"
        inner = self.carrier().transport(n_parts)
        return f"deep halos on {inner}" if inner.startswith("one device") else f"{every} by {inner}"

    @classmethod
    def of_text(cls, depth: str | None = None) -> "Halo":
        """The factory of the name ``"halo"`` (``"halo:k"``: depth k)."""
        if depth is None:
            return cls()
        try:
            return cls(int(depth))
        except ValueError:
            raise ConfigError(f"sync='halo:{depth}': the depth after 'halo:' must be a whole number of steps, "
                              "e.g. 'halo:4'") from None


# --------------------------------------------------------------------------- names

_REGISTRY: dict[str, Callable[..., ExchangeStrategy]] = {
    "psum": Psum, "ppermute": Ppermute, "mpi": Mpi, "halo": Halo.of_text}
class EntryPointWarning(UserWarning):
    """An installed package's exchange entry point that cannot be imported: it is left out
    of the registry (the other names keep working); the message names the package's entry
    point and the error."""


ENTRY_POINT_GROUP = "jaxsync.exchanges"
"""Installed packages name their exchanges here: an entry point ``name = "module:factory"``
of this group is registered as ``name`` on the first lookup of a name (so that
``jaxsync simulate --sync name`` finds it without code)."""
_ENTRY_POINTS_READ = []  # [True] once the installed entry points are registered


def _registry() -> dict:
    """The registry, with the installed packages' entry points registered once."""
    if not _ENTRY_POINTS_READ:
        from importlib.metadata import entry_points

        _ENTRY_POINTS_READ.append(True)
        for point in entry_points(group=ENTRY_POINT_GROUP):
            if point.name not in _REGISTRY:
                try:
                    _REGISTRY[point.name] = point.load()
                except Exception as exc:  # noqa: BLE001 - a broken plugin must not break the other names
                    warnings.warn(f"the exchange {point.name!r} of the installed entry point {point.value!r} "
                                  f"(group {ENTRY_POINT_GROUP!r}) cannot be imported and is left out: "
                                  f"{type(exc).__name__}: {exc}; fix or uninstall that package",
                                  EntryPointWarning, stacklevel=3)
    return _REGISTRY


def register_exchange(name: str, factory: Callable[..., ExchangeStrategy], *, replace: bool = False) -> None:
    """Name an exchange, so that ``sync="name"`` (and ``jaxsync simulate --sync name``)
    makes it: the one registry of exchange names (the built-in ``psum``, ``ppermute``,
    ``mpi`` and ``halo`` are registered the same way).

    Args:
        name: letters, digits, ``-`` and ``_``.
        factory: ``factory()`` makes the exchange with its defaults; ``"name:text"``
            calls ``factory("text")`` (e.g. ``"halo:4"``). A class whose fields all have
            defaults is a factory.
        replace: allow replacing a registered name (else a ConfigError).

    The registry lives in this process; register at import time of the module that defines
    the exchange (every MPI rank imports it)."""
    if not isinstance(name, str) or not name or not all(c.isalnum() or c in "-_" for c in name):
        raise ConfigError(f"register_exchange: name {name!r} must be a non-empty string of letters, digits, "
                          "'-' and '_'")
    if not callable(factory):
        raise ConfigError(f"register_exchange({name!r}, ...): factory must be callable (a class or a function "
                          f"that returns the exchange), got {factory!r}")
    if name in _registry() and not replace and _REGISTRY[name] is not factory:
        raise ConfigError(f"register_exchange: {name!r} is already registered; pass replace=True to replace it")
    _REGISTRY[name] = factory


def unregister_exchange(name: str) -> None:
    """Remove a name registered by :func:`register_exchange` (the built-in names stay)."""
    if name in ("psum", "ppermute", "mpi", "halo"):
        raise ConfigError(f"unregister_exchange: {name!r} is a built-in exchange and stays registered")
    _REGISTRY.pop(name, None)


def exchange_names() -> tuple:
    """The registered exchange names, in registration order (the built-in ones first, then
    those of installed packages' :data:`ENTRY_POINT_GROUP` entry points)."""
    return tuple(_registry())


def sync_strategy(value=None) -> ExchangeStrategy:
    """The exchange of a distributed run: an exchange object as it is (anything with
    :class:`~jaxsync.parallel.exchange.ExchangeStrategy`'s methods), a registered name
    (``"psum"``, ``"ppermute"``, ``"mpi"``, ``"halo"``, ``"halo:k"``, or a name given to
    :func:`register_exchange`: the exchange with its defaults), or None:
    :func:`jaxsync.parallel.multiprocess.default_sync` (psum in one process, MPI across
    CPU processes).

    Raises:
        ConfigError: an unknown name (the message lists the registered ones), or an
            object that is not an exchange."""
    from ..multiprocess import default_sync

    if value is None:
        value = default_sync()
    if not isinstance(value, str):
        from ._protocol import ExchangeStrategy

        if not isinstance(value, ExchangeStrategy):
            raise ConfigError(f"sync={value!r} is not an exchange: give one of {', '.join(map(repr, _REGISTRY))} "
                              "or an object with the methods of jaxsync.parallel.exchange.ExchangeStrategy "
                              "(name, synchronizes_every_step, plan, transport)")
        return value
    name, colon, argument = value.partition(":")
    if name not in _registry():
        raise ConfigError(f"sync must be one of {', '.join(map(repr, _REGISTRY))}, got {value!r} "
                          "(jaxsync.solve.register_exchange names another)")
    return _REGISTRY[name](argument) if colon else _REGISTRY[name]()


def transport(sync=None, n_parts: int | None = None) -> str:
    """One line that says how the parts of a distributed run exchange their shared-node
    values: the synchronization ``sync`` (an exchange, a name, or None:
    :func:`sync_strategy`) of a run of ``n_parts`` parts in this process's setting (the
    devices and processes of JAX, the MPI backend that ``"auto"`` resolves to).
    ``jaxsync simulate`` prints it in its header. For example::

        XLA psum over 2 emulated CPU devices in one process
        MPI Allreduce inside the compiled step (mpi4jax) between 2 processes
        MPI Allreduce inside the compiled step (jaxsync's ctypes FFI handler) between 2 processes
        gloo psum between 2 processes (slow, ~0.2-1 ms per exchange: --sync mpi calls MPI inside the step)

    Reads only what JAX and mpi4py report (no collective): any rank may call it."""
    return sync_strategy(sync).transport(n_parts)
