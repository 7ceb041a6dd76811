"""Communication cost model of the force synchronization, and its projection to clusters.

Model. One message of ``b`` bytes between two parts takes

    t_msg(b) = latency + b / bandwidth                                    [s]

(the "alpha-beta" or Hockney model). One synchronization of the distributed explicit
solver (:func:`jaxsync.parallel.exchange.synchronize_forces`) sums the parts' partial forces at
the N_a shared (interface) nodes: S = N_a * 3 dofs * 8 bytes of float64 per part. How
many messages of which size that takes depends on the algorithm (:data:`ALGORITHMS`):

    "allreduce-ring"                ring reduce-scatter + allgather of the whole interface
                                    vector: 2 (p - 1) messages of S / p bytes;
    "allreduce-recursive-doubling"  ceil(log2 p) messages of S bytes (each round
                                    exchanges the whole partially reduced vector);
    "allreduce"                     the cheaper of the two, as MPI libraries choose by
                                    message size (recursive doubling for short vectors,
                                    ring / Rabenseifner for long ones);
    "neighbour"                     each part sends every neighbour (a part it shares
                                    nodes with) the values of the nodes they share,
                                    n_shared_with * 3 * 8 bytes, and receives as much: the
                                    ``ppermute`` neighbour exchange. The messages to
                                    different neighbours go one after another:
                                    t = sum over neighbours of t_msg; the slowest part
                                    sets the time.
    "collective"                    one collective call that moves the whole interface
                                    vector once: latency + S / bandwidth. This is a
                                    reduction done in one step through shared memory:
                                    XLA's psum between devices of one process (the
                                    emulated devices of the tests and benchmarks; there
                                    the "latency" is the cost of all device threads
                                    meeting, which grows with their number, so fit one
                                    Interconnect per device count).
    "collective-permute"            XLA's ``ppermute`` neighbour exchange
                                    (:class:`jaxsync.parallel.exchange.NeighbourExchange`), one
                                    part per device: one collective call per device
                                    offset k at which some parts p and p + k (mod p)
                                    share nodes, each moving the largest such block:
                                    n_offsets * (latency + max bytes / bandwidth).

The counts of the two allreduce algorithms are those of Thakur, Rabenseifner & Gropp,
"Optimization of collective communication operations in MPICH", International Journal
of High Performance Computing Applications 19(1):49-66, 2005 (their ring allgather and
reduce-scatter: (p - 1) steps of n / p each; recursive doubling: lg p steps of n each;
for p not a power of two MPICH adds steps, which this model ignores).

Per step: the synchronized solver costs t_t = t_compute + t_s, the synchronization-
avoiding solver t_t' = t_compute + t_d, with t_compute = t_e + t_m + t_o the measured
local work (:mod:`jaxsync.perf.timing`) and t_d the measured surrogate cost per step
(a refill prediction divided by the n_s n_f steps it serves). Speed-up zeta = t_t / t_t'.
The surrogate pays off while t_d < t_s (the break-even surrogate cost is t_s).

Assumptions (each makes the model optimistic or simple, none is measured here):
- no overlap of communication and computation (the explicit step needs the summed force
  before its update, so the solver cannot overlap it anyway);
- the messages of one part are serialized on one link, full duplex (sending and
  receiving the same amount at once costs one message time);
- bandwidth is per link and per direction; no contention between parts, no switch
  hops, no topology (a fat tree without oversubscription);
- the reduction arithmetic (3 N_a additions) is free next to the messages;
- all parts start the synchronization together (load imbalance shows up in t_compute,
  the max-average part of :mod:`jaxsync.perf.reports`).

Inputs and their sources: the partition's interface (:func:`communication_pattern`,
from :class:`jaxsync.parallel.Partition`); an :class:`Interconnect`, either one of the
typical published figures in :data:`INTERCONNECTS` (vendor spec sheets and OSU
micro-benchmark results, not measured here), or one fitted to measured message times on
this machine with :func:`fit_interconnect`; t_compute and t_d measured by the benchmarks.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Iterable, Mapping

import numpy as np

from ..errors import ConfigError, ProblemError

__all__ = ["Interconnect", "INTERCONNECTS", "CommunicationPattern", "communication_pattern",
           "ALGORITHMS", "sync_time", "fit_interconnect", "InterconnectProjection",
           "Projection", "project", "relative_error"]

ALGORITHMS = ("allreduce", "allreduce-ring", "allreduce-recursive-doubling", "neighbour",
              "collective", "collective-permute")


def _finite(value, what: str, *, error=ConfigError, positive: bool = True) -> float:
    """``value`` as a float, finite and > 0 (``positive``) or >= 0; else ``error``."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise error(f"{what} must be a number, got {value!r}") from None
    if not (math.isfinite(value) and (value > 0 if positive else value >= 0)):
        raise error(f"{what} must be a finite number {'>' if positive else '>='} 0, got {value!r}")
    return value


@dataclasses.dataclass(frozen=True)
class Interconnect:
    """A link between two parts in the latency-bandwidth model.

    Attributes:
        name: short label.
        latency_s: one-way small-message latency [s] (half a ping-pong round trip).
        bandwidth_Bps: large-message bandwidth per direction, per link [bytes/s].
        source: where the numbers come from.

    Raises:
        ConfigError: a latency or bandwidth that is not finite and > 0.
    """

    name: str
    latency_s: float
    bandwidth_Bps: float
    source: str = ""

    def __post_init__(self):
        object.__setattr__(self, "latency_s",
                           _finite(self.latency_s, f"Interconnect {self.name!r} latency_s"))
        object.__setattr__(self, "bandwidth_Bps",
                           _finite(self.bandwidth_Bps, f"Interconnect {self.name!r} bandwidth_Bps"))

    def message_time(self, n_bytes):
        """Time of one message of ``n_bytes`` bytes [s]: latency + n_bytes / bandwidth.

        ``n_bytes`` may be a number or an array (elementwise; a float or a float array
        comes back). A message of 0 bytes is not sent and costs 0.

        Raises:
            ProblemError: negative or non-finite sizes.
        """
        b = np.asarray(n_bytes, dtype=float)
        if not np.all(np.isfinite(b)) or np.any(b < 0):
            raise ProblemError(f"message sizes must be finite and >= 0 bytes, got {n_bytes!r}")
        t = np.where(b > 0, self.latency_s + b / self.bandwidth_Bps, 0.0)
        return float(t) if t.ndim == 0 else t

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# Typical published figures, NOT measured here. Policy: bandwidth is the vendor's nominal
# per-direction line rate (MPI reaches ~90-97 % of it for large messages, so the model is
# slightly optimistic); latency is a typical published small-message one-way MPI (or
# NCCL) latency, half the ping-pong round trip of the OSU micro-benchmark osu_latency.
INTERCONNECTS: dict[str, Interconnect] = {
    ic.name: ic for ic in (
        Interconnect(
            "shared-memory", 0.4e-6, 10e9,
            "MPI between processes on one node (shared-memory transport): typical OSU "
            "osu_latency 0.2-0.5 us and osu_bw 10-20 GB/s on recent x86 servers; the "
            "bandwidth of a message is bounded by a memory copy (numpy copy here: 9.4 GB/s, "
            "DESIGN.md), so 10 GB/s. Typical published figures, not measured here."),
        Interconnect(
            "infiniband-hdr", 1.0e-6, 25e9,
            "InfiniBand HDR, 200 Gb/s = 25 GB/s per direction (NVIDIA/Mellanox ConnectX-6 "
            "spec sheet); MPI osu_latency about 1 us (published OSU results for HDR "
            "clusters). Typical published figures, not measured here."),
        Interconnect(
            "infiniband-ndr", 1.0e-6, 50e9,
            "InfiniBand NDR, 400 Gb/s = 50 GB/s per direction (NVIDIA ConnectX-7 spec "
            "sheet); MPI osu_latency about 1 us (published OSU results). Typical published "
            "figures, not measured here."),
        Interconnect(
            "nvlink-4", 3.0e-6, 450e9,
            "NVLink 4 between H100 GPUs: 900 GB/s bidirectional = 450 GB/s per direction "
            "aggregate (NVIDIA H100 spec sheet; measured GPU-to-GPU copies reach ~370-400 "
            "GB/s); small-message latency through NCCL a few us (published nccl-tests "
            "results), 3 us taken. Typical published figures, not measured here."),
        Interconnect(
            "ethernet-10g", 15e-6, 1.25e9,
            "10 Gigabit Ethernet with TCP: 10 Gb/s = 1.25 GB/s line rate; MPI over the "
            "kernel TCP stack about 10-25 us one-way (published OSU/netperf results), "
            "15 us taken. Typical published figures, not measured here."),
        Interconnect(
            "ethernet-100g", 3e-6, 12.5e9,
            "100 Gigabit Ethernet: 100 Gb/s = 12.5 GB/s line rate; RoCE v2 MPI latency "
            "about 2-3 us, TCP about 5 us or more (published OSU results), 3 us (RoCE) "
            "taken. Typical published figures, not measured here."),
    )
}


@dataclasses.dataclass(frozen=True)
class CommunicationPattern:
    """The messages one synchronization of a partition needs.

    Attributes:
        n_parts: p, number of parts.
        n_interface: N_a, number of shared nodes (the interface).
        neighbours: per part, a tuple of ``(neighbour part, nodes shared with it)`` pairs,
            neighbours in increasing order; two parts are neighbours when they share at
            least one node.
        dofs_per_node: values per node (3 displacement/force components).
        bytes_per_value: bytes per value (8: float64).

    Raises:
        ConfigError: inconsistent sizes (negative counts, a part listing itself, a
            neighbour out of range, a neighbour list per part missing).
    """

    n_parts: int
    n_interface: int
    neighbours: tuple
    dofs_per_node: int = 3
    bytes_per_value: int = 8

    def __post_init__(self):
        for name in ("n_parts", "dofs_per_node", "bytes_per_value"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ConfigError(f"CommunicationPattern.{name} must be a positive integer, got {value!r}")
        if isinstance(self.n_interface, bool) or not isinstance(self.n_interface, (int, np.integer)) \
                or self.n_interface < 0:
            raise ConfigError(f"CommunicationPattern.n_interface must be an integer >= 0, "
                              f"got {self.n_interface!r}")
        neighbours = tuple(tuple((int(q), int(n)) for q, n in row) for row in self.neighbours)
        if len(neighbours) != self.n_parts:
            raise ConfigError(f"CommunicationPattern needs one neighbour list per part: "
                              f"{len(neighbours)} lists for n_parts={self.n_parts}")
        for p, row in enumerate(neighbours):
            for q, n in row:
                if not 0 <= q < self.n_parts or q == p or n < 1:
                    raise ConfigError(
                        f"part {p} lists neighbour ({q}, {n}): a neighbour must be another part "
                        f"in [0, {self.n_parts}) sharing at least 1 node")
        object.__setattr__(self, "neighbours", neighbours)
        for name in ("n_parts", "n_interface", "dofs_per_node", "bytes_per_value"):
            object.__setattr__(self, name, int(getattr(self, name)))

    @property
    def interface_bytes(self) -> int:
        """S, bytes of the whole interface vector: N_a * dofs_per_node * bytes_per_value."""
        return self.n_interface * self.dofs_per_node * self.bytes_per_value

    def neighbour_bytes(self, part: int) -> tuple:
        """Bytes part ``part`` sends to each of its neighbours (in neighbour order)."""
        return tuple(n * self.dofs_per_node * self.bytes_per_value for _, n in self.neighbours[part])

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["neighbours"] = [[list(pair) for pair in row] for row in self.neighbours]
        return out


def communication_pattern(partition, dofs_per_node: int = 3, bytes_per_value: int = 8) -> CommunicationPattern:
    """The :class:`CommunicationPattern` of a :class:`jaxsync.parallel.Partition`.

    Nodes shared by parts p and q are the interface nodes whose ``sharing_parts`` hold
    both; with B the (N_a, p) boolean incidence of interface nodes and parts, the counts
    are the off-diagonal entries of B^T B.
    """
    n_parts = int(partition.n_parts)
    incidence = np.zeros((partition.n_interface, n_parts), dtype=np.int64)
    for k, parts in enumerate(partition.sharing_parts):
        incidence[k, np.asarray(parts, dtype=np.int64)] = 1
    shared_with = incidence.T @ incidence  # [p, q]: nodes shared by p and q
    neighbours = tuple(tuple((q, int(shared_with[p, q])) for q in range(n_parts)
                             if q != p and shared_with[p, q] > 0) for p in range(n_parts))
    return CommunicationPattern(n_parts=n_parts, n_interface=int(partition.n_interface),
                                neighbours=neighbours, dofs_per_node=dofs_per_node,
                                bytes_per_value=bytes_per_value)


def _check_interconnect(interconnect) -> Interconnect:
    if isinstance(interconnect, str):
        if interconnect not in INTERCONNECTS:
            raise ConfigError(f"unknown interconnect {interconnect!r}: use one of "
                              f"{sorted(INTERCONNECTS)} or an Interconnect")
        return INTERCONNECTS[interconnect]
    if not isinstance(interconnect, Interconnect):
        raise ConfigError(f"expected an Interconnect or a preset name, got {interconnect!r}")
    return interconnect


def sync_time(pattern: CommunicationPattern, interconnect, algorithm: str = "allreduce") -> float:
    """Predicted time of one synchronization [s] for the slowest part.

    Args:
        pattern: the partition's messages (:func:`communication_pattern`).
        interconnect: an :class:`Interconnect` or the name of a preset in
            :data:`INTERCONNECTS`.
        algorithm: one of :data:`ALGORITHMS` (formulas in the module docstring).

    Returns:
        Seconds per synchronization (0 for one part or an empty interface).

    Raises:
        ConfigError: unknown algorithm or interconnect.
    """
    if algorithm not in ALGORITHMS:
        raise ConfigError(f"unknown synchronization algorithm {algorithm!r}: use one of {ALGORITHMS}")
    if not isinstance(pattern, CommunicationPattern):
        raise ConfigError(f"expected a CommunicationPattern (see communication_pattern), got {pattern!r}")
    link = _check_interconnect(interconnect)
    p, size = pattern.n_parts, pattern.interface_bytes
    if p == 1 or size == 0:
        return 0.0
    ring = 2 * (p - 1) * link.message_time(size / p)
    doubling = math.ceil(math.log2(p)) * link.message_time(size)
    if algorithm == "allreduce-ring":
        return float(ring)
    if algorithm == "allreduce-recursive-doubling":
        return float(doubling)
    if algorithm == "allreduce":
        return float(min(ring, doubling))
    if algorithm == "collective":
        return float(link.message_time(size))
    if algorithm == "collective-permute":
        largest = {}
        for q, row in enumerate(pattern.neighbours):
            for r, n in row:
                k = (r - q) % p
                largest[k] = max(largest.get(k, 0), n * pattern.dofs_per_node * pattern.bytes_per_value)
        return float(sum(link.message_time(b) for b in largest.values()))
    return float(max(float(np.sum(link.message_time(np.asarray(pattern.neighbour_bytes(q), dtype=float))))
                     for q in range(p)))


def fit_interconnect(n_bytes, seconds, name: str = "fitted",
                     source: str = "least-squares fit to measured (bytes, seconds) message times") -> Interconnect:
    """Fit latency and bandwidth to measured message times: seconds ~ a + n_bytes / B.

    Least squares (``numpy.linalg.lstsq``) of ``seconds`` on ``[1, n_bytes]``; the
    intercept is the latency, the inverse of the slope the bandwidth.

    Args:
        n_bytes: (k,) message sizes [bytes], at least 2 distinct.
        seconds: (k,) measured times [s] (e.g. per-step t_s of a synchronization of that
            many bytes on the emulated devices).
        name, source: labels of the returned :class:`Interconnect`.

    Raises:
        ProblemError: mismatched or non-finite inputs, fewer than 2 distinct sizes, or a
            fit with latency or bandwidth <= 0 (measurements too noisy for the size range).
    """
    x = np.asarray(n_bytes, dtype=float).ravel()
    y = np.asarray(seconds, dtype=float).ravel()
    if x.shape != y.shape:
        raise ProblemError(f"fit_interconnect needs one time per size: {x.size} sizes, {y.size} times")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))) or np.any(x < 0) or np.any(y < 0):
        raise ProblemError("fit_interconnect needs finite sizes >= 0 bytes and times >= 0 s")
    if len(np.unique(x)) < 2:
        raise ProblemError(f"fit_interconnect needs at least 2 distinct message sizes to separate "
                           f"latency from bandwidth, got sizes {np.unique(x).tolist()}: measure "
                           "several sizes (e.g. 8 B to 1 MB)")
    # Scale the size column so that lstsq works on comparable columns.
    scale = float(np.max(x))
    (latency, slope), *_ = np.linalg.lstsq(np.stack([np.ones_like(x), x / scale], axis=1), y, rcond=None)
    slope /= scale
    if not latency > 0 or not slope > 0:
        raise ProblemError(
            f"fitted latency {latency:.3g} s and time per byte {slope:.3g} s/B: both must be > 0. "
            "The measurements are too noisy for their size range: repeat them (keep the best "
            "of many repeats) and include larger messages, so that the size term dominates")
    return Interconnect(name=name, latency_s=float(latency), bandwidth_Bps=float(1.0 / slope),
                        source=source)


@dataclasses.dataclass(frozen=True)
class InterconnectProjection:
    """The predicted per-step costs on one interconnect [s].

    Attributes:
        interconnect: the :class:`Interconnect`.
        t_s: predicted synchronization time per step.
        t_t: synchronized step, t_compute + t_s.
        t_t_prime: synchronization-avoiding step, t_compute + t_surrogate.
        zeta: speed-up t_t / t_t_prime.
        break_even_surrogate: the surrogate cost per step below which zeta > 1 (= t_s).
    """

    interconnect: Interconnect
    t_s: float
    t_t: float
    t_t_prime: float
    zeta: float
    break_even_surrogate: float

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["interconnect"] = self.interconnect.to_dict()
        return out


@dataclasses.dataclass(frozen=True)
class Projection:
    """Projection of a measured step to clusters (see :func:`project`).

    Attributes:
        t_compute: measured local work per step, t_e + t_m + t_o [s].
        t_surrogate: measured surrogate cost per step, t_d (amortized) [s].
        algorithm: the synchronization algorithm of the model.
        pattern: the partition's :class:`CommunicationPattern`.
        rows: one :class:`InterconnectProjection` per interconnect.
    """

    t_compute: float
    t_surrogate: float
    algorithm: str
    pattern: CommunicationPattern
    rows: tuple

    def table(self) -> str:
        """A printable table, times in microseconds per step."""
        p = self.pattern
        lines = [f"Projection of one step: n_c={p.n_parts} parts, N_a={p.n_interface} shared nodes "
                 f"(S={p.interface_bytes} B), algorithm={self.algorithm}; measured t_compute="
                 f"{1e6 * self.t_compute:.2f} us, t_d={1e6 * self.t_surrogate:.2f} us per step",
                 "times in us per step; the surrogate pays off while t_d < t_s",
                 f"{'interconnect':<16} {'latency':>9} {'GB/s':>8} {'t_s':>10} {'t_t':>10} "
                 f"{'t_t_prime':>10} {'zeta':>7}"]
        for r in self.rows:
            ic = r.interconnect
            lines.append(f"{ic.name:<16} {1e6 * ic.latency_s:>9.2f} {ic.bandwidth_Bps / 1e9:>8.2f} "
                         f"{1e6 * r.t_s:>10.3f} {1e6 * r.t_t:>10.3f} {1e6 * r.t_t_prime:>10.3f} "
                         f"{r.zeta:>7.3f}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-ready dict (inverse: :meth:`from_dict`)."""
        return {"kind": "jaxsync-cost-projection", "t_compute": self.t_compute,
                "t_surrogate": self.t_surrogate, "algorithm": self.algorithm,
                "pattern": self.pattern.to_dict(), "rows": [r.to_dict() for r in self.rows]}

    @classmethod
    def from_dict(cls, data: dict) -> "Projection":
        try:
            rows = tuple(InterconnectProjection(**dict(r, interconnect=Interconnect(**r["interconnect"])))
                         for r in data["rows"])
            return cls(t_compute=data["t_compute"], t_surrogate=data["t_surrogate"],
                       algorithm=data["algorithm"], pattern=CommunicationPattern(**data["pattern"]),
                       rows=rows)
        except (KeyError, TypeError) as exc:
            raise ProblemError(f"not a jaxsync cost projection: {exc}") from exc


def project(t_compute: float, t_surrogate: float, pattern: CommunicationPattern,
            interconnects: Mapping[str, Interconnect] | Iterable[Interconnect] = INTERCONNECTS,
            algorithm: str = "allreduce") -> Projection:
    """Predict the synchronized and the synchronization-avoiding step on other links.

    For each interconnect: t_s = :func:`sync_time`, t_t = t_compute + t_s,
    t_t' = t_compute + t_surrogate, zeta = t_t / t_t'.

    Args:
        t_compute: measured local work per step, t_e + t_m + t_o of the max-average part [s].
        t_surrogate: measured surrogate cost per step (refill time / (n_s n_f)) [s].
        pattern: the partition's :class:`CommunicationPattern`.
        interconnects: a dict of name -> :class:`Interconnect` (default: the presets) or
            an iterable of :class:`Interconnect`.
        algorithm: synchronization algorithm (:data:`ALGORITHMS`).

    Raises:
        ProblemError: times that are negative, not finite, or both 0.
        ConfigError: unknown algorithm, no interconnect.
    """
    t_compute = _finite(t_compute, "t_compute [s]", error=ProblemError, positive=False)
    t_surrogate = _finite(t_surrogate, "t_surrogate [s]", error=ProblemError, positive=False)
    if t_compute + t_surrogate <= 0:
        raise ProblemError("t_compute + t_surrogate is 0 s: the speed-up needs a measured step time > 0")
    links = tuple(interconnects.values() if isinstance(interconnects, Mapping) else interconnects)
    if not links:
        raise ConfigError("project needs at least one Interconnect")
    t_prime = t_compute + t_surrogate
    rows = []
    for link in links:
        link = _check_interconnect(link)
        t_s = sync_time(pattern, link, algorithm)
        t_t = t_compute + t_s
        rows.append(InterconnectProjection(interconnect=link, t_s=t_s, t_t=t_t,
                                           t_t_prime=t_prime, zeta=t_t / t_prime,
                                           break_even_surrogate=t_s))
    return Projection(t_compute=t_compute, t_surrogate=t_surrogate, algorithm=algorithm,
                      pattern=pattern, rows=tuple(rows))


def relative_error(predicted_s, measured_s):
    """(predicted - measured) / measured: the model's error against a measurement.

    Works elementwise on arrays (returns a float for scalars). Positive: the model
    overestimates.

    Raises:
        ProblemError: a measured time that is not finite and > 0, or a non-finite prediction.
    """
    predicted = np.asarray(predicted_s, dtype=float)
    measured = np.asarray(measured_s, dtype=float)
    if not np.all(np.isfinite(measured)) or np.any(measured <= 0):
        raise ProblemError(f"measured times must be finite and > 0 s to compare with, got {measured_s!r}")
    if not np.all(np.isfinite(predicted)):
        raise ProblemError(f"predicted times must be finite, got {predicted_s!r}")
    out = (predicted - measured) / measured
    return float(out) if out.ndim == 0 else out
