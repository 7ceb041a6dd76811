"""Reports of the per-step timing breakdown (paper section 7): types, tables and JSON.

Quantities, all in seconds per step (tables print microseconds):

    t_e  element quantities: forming the element geometry, strains, stresses and element
         force vectors (``"recompute"`` mode); 0 in the ``"preassembled"`` mode, where K
         is assembled once before the run (that one-off cost is ``TimingReport.setup_s``,
         never amortized into t_e).
    t_m  the product K d: the ELL mat-vec (``"preassembled"``), or the scatter-add of the
         element forces into the nodes (``"recompute"``).
    t_s  synchronization: the shared-node forces summed over the parts.
    t_d  surrogate (synchronization-avoiding solver only): one refill prediction divided
         by the n_s n_f steps it serves.
    t_o  everything else in a step: external force, central-difference update,
         Dirichlet values, the loop itself.
    t_t  total: the part's own step without synchronization, measured (``t_local``),
         plus t_s (or, synchronization-avoiding, plus t_d).
    r_*  = t_* / t_t. r_e + r_m + r_s + r_d + r_o (``r_sum``) is 1 when the separately
         measured stages add up to the measured whole.

"Max-average" (paper): each quantity is averaged per step over a run, and the part with
the largest t_t is reported (:func:`max_average`). Speed-up zeta = t_t / t_t' of the
whole synchronized and synchronization-avoiding programs (:class:`SpeedupReport`).
How the numbers are measured: :mod:`jaxsync.perf.timing`.
"""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np

from ..errors import CheckpointError, ProblemError
from ..options import Mode

__all__ = ["STAGES", "PartTiming", "max_average", "TimingReport", "SpeedupReport"]

STAGES = ("t_e", "t_m", "t_s", "t_d", "t_o")  # the additive stages of t_t

TIMING_KIND = "jaxsync-timing-report"
SPEEDUP_KIND = "jaxsync-speedup-report"


@dataclasses.dataclass(frozen=True)
class PartTiming:
    """Per-step times of one part [s] (definitions: module docstring).

    Attributes:
        part: part index p.
        n_nodes: local nodes of the part.
        n_elements: elements of the part.
        n_shared: shared nodes of the part.
        t_e, t_m, t_s, t_o: stage times per step [s].
        t_local: the part's whole step without synchronization, measured [s].
        t_t: total per step, t_local + t_s + t_d [s].
        t_d: surrogate cost per step [s] (0 for the synchronized solver).

    Raises:
        ProblemError: a time that is not finite and >= 0.
    """

    part: int
    n_nodes: int
    n_elements: int
    n_shared: int
    t_e: float
    t_m: float
    t_s: float
    t_o: float
    t_local: float
    t_t: float
    t_d: float = 0.0

    def __post_init__(self):
        for name in (*STAGES, "t_local", "t_t"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ProblemError(f"PartTiming.{name} must be a finite time >= 0 s, got {value!r}")

    def ratio(self, name: str) -> float:
        """r_* = t_* / t_t for ``name`` in :data:`STAGES` (0 when t_t is 0)."""
        if name not in STAGES:
            raise ProblemError(f"ratio of {name!r}: use one of {STAGES}")
        return getattr(self, name) / self.t_t if self.t_t > 0 else 0.0

    @property
    def ratios(self) -> dict:
        """{"r_e": ..., "r_m": ..., "r_s": ..., "r_d": ..., "r_o": ...}."""
        return {"r" + name[1:]: self.ratio(name) for name in STAGES}

    @property
    def r_sum(self) -> float:
        """(t_e + t_m + t_s + t_d + t_o) / t_t: 1 when the separately measured stages add up."""
        return sum(self.ratios.values())

    def to_dict(self) -> dict:
        """The fields, the ratios and ``r_sum``."""
        return dict(dataclasses.asdict(self), **self.ratios, r_sum=self.r_sum)


def max_average(rows) -> PartTiming:
    """The paper's "max-average" row: of per-step averages, the part with the largest t_t
    (the first such part on ties)."""
    rows = tuple(rows)
    if not rows:
        raise ProblemError("max_average needs at least one PartTiming row")
    return max(rows, key=lambda r: r.t_t)


def _fields_of(cls, data: dict) -> dict:
    """The entries of ``data`` that are fields of the dataclass ``cls`` (derived entries
    of a ``to_dict`` are left out: they are recomputed)."""
    names = {f.name for f in dataclasses.fields(cls)}
    return {k: v for k, v in data.items() if k in names}


class _JsonReport:
    """JSON of a report dataclass whose ``to_dict`` tags its entries with ``kind =
    cls._kind`` (``cls._what`` names the report in messages)."""

    _kind = ""
    _what = ""

    @classmethod
    def _fields(cls, data: dict) -> dict:
        return _fields_of(cls, data)

    @classmethod
    def from_dict(cls, data: dict):
        """Inverse of ``to_dict`` (derived entries are recomputed, not read)."""
        try:
            return cls(**cls._fields(data))
        except (KeyError, TypeError) as exc:
            raise CheckpointError(f"not a jaxsync {cls._what}: {exc}") from exc

    def save_json(self, path: str | os.PathLike) -> None:
        """Write ``to_dict()`` as JSON; the file appears only when complete."""
        from ..io.atomic import atomic_json

        atomic_json(path, self.to_dict())

    @classmethod
    def load_json(cls, path: str | os.PathLike):
        """Read a report written by :meth:`save_json`."""
        try:
            with open(path) as f:
                data = json.load(f)
        except (OSError, ValueError) as exc:
            raise CheckpointError(f"cannot read {cls._what} {path}: {exc}") from exc
        if not isinstance(data, dict) or data.get("kind") != cls._kind:
            raise CheckpointError(f"{path} is not a jaxsync {cls._what}")
        return cls.from_dict(data)


@dataclasses.dataclass(frozen=True)
class TimingReport(_JsonReport):
    """Timing breakdown of one configuration (one mesh, partition and mode).

    Attributes:
        mode: ``"preassembled"`` or ``"recompute"``.
        n_parts: n_c.
        n_shared_nodes: N_a, the number of shared (interface) nodes of the partition.
        n_nodes, n_elements: size of the mesh.
        n_steps: steps per timed call; repeats: timed calls per variant (best kept).
        dt: time step [s].
        device: description of the devices (platform, count, whether emulated).
        n_devices: devices the distributed program ran on.
        rows: one :class:`PartTiming` per part, in part order.
        t_step: measured per-step time of the whole synchronized SPMD program [s]
            (for one part: the single-part local step).
        t_step_nosync: the same program without synchronization [s].
        setup_s: one-off wall time to build the per-part systems (assembly) [s].
        loadavg: ``os.getloadavg()`` (1, 5, 15 min) when the timing ended.
    """

    mode: Mode
    n_parts: int
    n_shared_nodes: int
    n_nodes: int
    n_elements: int
    n_steps: int
    repeats: int
    dt: float
    device: str
    n_devices: int
    rows: tuple
    t_step: float
    t_step_nosync: float
    setup_s: float
    loadavg: tuple = ()

    _kind = TIMING_KIND
    _what = "timing report"

    def __post_init__(self):
        rows = tuple(r if isinstance(r, PartTiming) else PartTiming(**_fields_of(PartTiming, r))
                     for r in self.rows)
        object.__setattr__(self, "rows", rows)
        object.__setattr__(self, "loadavg", tuple(float(x) for x in self.loadavg))
        if len(rows) != self.n_parts:
            raise ProblemError(f"TimingReport has {len(rows)} rows for n_parts={self.n_parts}")

    @property
    def max_average(self) -> PartTiming:
        """The row of the part with the largest t_t (paper's max-average)."""
        return max_average(self.rows)

    def table(self) -> str:
        """A printable table in microseconds per step: one line per part, then the
        max-average line and the measured whole-program step."""
        head = (f"Timing breakdown, mode={self.mode}: n_c={self.n_parts} parts, "
                f"N_a={self.n_shared_nodes} shared nodes, mesh {self.n_nodes} nodes / "
                f"{self.n_elements} tetrahedra; {self.n_steps} steps x best of {self.repeats}; "
                f"{self.device}")
        cols = (f"{'part':>7} {'nodes':>7} {'elems':>7} {'shared':>6} "
                f"{'t_e':>9} {'t_m':>9} {'t_s':>9} {'t_d':>9} {'t_o':>9} {'t_t':>9}  "
                f"{'r_e':>5} {'r_m':>5} {'r_s':>5} {'r_d':>5} {'r_o':>5} {'sum':>5}")
        lines = [head, "times in us per step", cols]

        def line(label, r):
            return (f"{label:>7} {r.n_nodes:>7} {r.n_elements:>7} {r.n_shared:>6} "
                    + " ".join(f"{1e6 * getattr(r, k):>9.2f}" for k in (*STAGES, "t_t"))
                    + "  " + " ".join(f"{v:>5.3f}" for v in r.ratios.values())
                    + f" {r.r_sum:>5.3f}")

        for r in self.rows:
            lines.append(line(str(r.part), r))
        top = self.max_average
        lines.append(line(f"max@{top.part}", top))
        lines.append(f"whole SPMD program: {1e6 * self.t_step:.2f} us/step synchronized, "
                     f"{1e6 * self.t_step_nosync:.2f} us/step without synchronization; "
                     f"setup (assembly) {self.setup_s:.3f} s; load average "
                     + ", ".join(f"{x:.2f}" for x in self.loadavg))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-ready dict: every field, rows as dicts with their ratios and ``r_sum``,
        and the max-average row under ``"max_average"``."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["rows"] = [r.to_dict() for r in self.rows]
        out["loadavg"] = list(self.loadavg)
        out["max_average"] = self.max_average.to_dict()
        out["kind"] = self._kind
        return out


@dataclasses.dataclass(frozen=True)
class SpeedupReport(_JsonReport):
    """The synchronized and the synchronization-avoiding solver measured in one run.

    Attributes:
        synchronized: per-part breakdown of the synchronized solver with the faster
            synchronization (``sync``); t_d = 0.
        avoiding: the same parts in the synchronization-avoiding solver: t_s = 0 and t_d
            the part's surrogate cost per step; t_e, t_m, t_o are those of the
            synchronized solver's local step (the predicted step also overwrites the
            shared dofs, a gather of n_shared values, inside ``t_step_avoiding``).
        sync: the synchronization of the baseline (the faster of those timed).
        t_step_sync: {sync method: measured per-step time of the whole synchronized SPMD
            program [s]} for every method timed.
        t_step_nosync: the same program without synchronization [s].
        t_step_avoiding: measured per-step time of the whole synchronization-avoiding
            SPMD program (n_s n_f solver steps and one batched refill prediction per part
            per cycle, no collective) [s].
        t_prediction: (n_parts,) wall time of one batched refill prediction of each part,
            alone on one device [s].
        t_prediction_spmd: wall time of one batched refill prediction of every part at
            once, in the SPMD program (parts on their devices) [s]: what the
            synchronization-avoiding program pays per cycle (on devices that share
            cores or memory, more than a part alone).
        n_s, n_past, n_future: the refill geometry; one prediction serves n_s n_future steps.
        architecture: the surrogate's architecture (dict), or {} for another predictor.
        n_steps: steps per timed call of the whole programs; repeats: timed calls (best kept).
        t_step_halo: {halo depth k: measured per-step time of the deep-halo SPMD program
            (:mod:`jaxsync.parallel.exchange`: exact, one exchange every k steps) [s]}; empty
            when none was timed.
    """

    synchronized: TimingReport
    avoiding: TimingReport
    sync: str
    t_step_sync: dict
    t_step_nosync: float
    t_step_avoiding: float
    t_prediction: tuple
    t_prediction_spmd: float
    n_s: int
    n_past: int
    n_future: int
    architecture: dict
    n_steps: int
    repeats: int
    t_step_halo: dict = dataclasses.field(default_factory=dict)

    _kind = SPEEDUP_KIND
    _what = "speed-up report"

    def __post_init__(self):
        object.__setattr__(self, "t_prediction", tuple(float(t) for t in self.t_prediction))
        # JSON keys are strings: the depths are ints again here
        object.__setattr__(self, "t_step_halo", {int(k): float(v) for k, v in self.t_step_halo.items()})
        if self.sync not in self.t_step_sync:
            raise ProblemError(f"SpeedupReport.sync={self.sync!r} is not one of the timed "
                               f"synchronizations {sorted(self.t_step_sync)}")

    @property
    def steps_per_prediction(self) -> int:
        """n_s n_f: the solver steps one refill prediction serves."""
        return self.n_s * self.n_future

    @property
    def t_step_synchronized(self) -> float:
        """Whole-program step of the synchronized baseline at its best [s]."""
        return self.t_step_sync[self.sync]

    @property
    def zeta(self) -> float:
        """Speed-up t_t / t_t' of the whole programs, measured in the same run."""
        return self.t_step_synchronized / self.t_step_avoiding

    @property
    def t_s(self) -> float:
        """Synchronization cost per step of the baseline [s] (whole programs)."""
        return max(self.t_step_synchronized - self.t_step_nosync, 0.0)

    @property
    def t_d(self) -> float:
        """Surrogate cost per step [s]: one SPMD refill prediction of all parts amortized
        over the n_s n_f steps it serves."""
        return self.t_prediction_spmd / self.steps_per_prediction

    @property
    def zeta_halo(self) -> dict:
        """{k: speed-up of deep halos of depth k over the synchronized baseline}: the exact
        communication-avoiding scheme beside the surrogate's ``zeta``."""
        return {k: self.t_step_synchronized / t for k, t in self.t_step_halo.items()}

    @property
    def surrogate_pays(self) -> bool:
        """True when the amortized surrogate cost is below the synchronization it replaces."""
        return self.t_d < self.t_s

    def table(self) -> str:
        """Both breakdowns, then the whole programs in microseconds per step and zeta."""
        lines = [self.synchronized.table(), "", "synchronization-avoiding:", self.avoiding.table(), ""]
        lines.append("whole programs, us per step (same run, best of "
                     f"{self.repeats} calls of {self.n_steps} steps):")
        for method, t in self.t_step_sync.items():
            mark = "  <- baseline" if method == self.sync else ""
            lines.append(f"  synchronized ({method}): {1e6 * t:9.2f}{mark}")
        lines.append(f"  no synchronization:      {1e6 * self.t_step_nosync:9.2f}")
        lines.append(f"  synchronization-avoiding: {1e6 * self.t_step_avoiding:8.2f}")
        lines.append(f"  t_s = {1e6 * self.t_s:.2f} us; surrogate: {1e3 * self.t_prediction_spmd:.3f} ms "
                     f"per prediction of all parts ({1e3 * max(self.t_prediction):.3f} ms for one "
                     f"part alone) = {1e6 * self.t_d:.2f} us per step over n_s n_f = "
                     f"{self.steps_per_prediction} steps; "
                     + ("below" if self.surrogate_pays else "NOT below")
                     + " the synchronization it replaces")
        for k, t in self.t_step_halo.items():
            lines.append(f"  deep halos, depth {k:<3}      {1e6 * t:9.2f}   (exact; zeta {self.zeta_halo[k]:.3f})")
        lines.append(f"  zeta = t_t / t_t' = {self.zeta:.3f}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """JSON-ready dict: every field (both breakdowns as :meth:`TimingReport.to_dict`)
        and the derived zeta, t_s, t_d, steps_per_prediction, t_step_synchronized,
        surrogate_pays."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["synchronized"] = self.synchronized.to_dict()
        out["avoiding"] = self.avoiding.to_dict()
        out["t_prediction"] = list(self.t_prediction)
        for name in ("zeta", "t_s", "t_d", "steps_per_prediction", "t_step_synchronized",
                     "surrogate_pays", "zeta_halo"):
            out[name] = getattr(self, name)
        out["kind"] = self._kind
        return out

    @classmethod
    def _fields(cls, data: dict) -> dict:
        breakdowns = {name: TimingReport.from_dict(data[name]) for name in ("synchronized", "avoiding")}
        return dict(_fields_of(cls, data), **breakdowns)
