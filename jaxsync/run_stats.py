"""Run statistics, typed by the kind of run: how a run went, apart from the physics.

Every kind of run records its timing and its devices (:class:`RunStats`, the base); a
synchronized run adds its time per step (:class:`SynchronizedStats`), a
synchronization-avoiding run its step counts, re-synchronizations, online learning and
load jumps (:class:`SyncAvoidingStats`), a full-system run its step counts and the
predictions on the Dirichlet dofs (:class:`FullSystemStats`). A field that another kind of
run records reads None (not measured in this run), so code written for one record with
every field keeps working. In files (``stat_*`` attributes of a trajectory, a command's
``summary.json``) the statistics are the flat dictionary of :meth:`RunStats.to_dict`;
:meth:`RunStats.from_dict` finds the kind from its keys, so files written before the
kinds existed load as the kind they hold.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["RunStats", "SynchronizedStats", "SyncAvoidingStats", "FullSystemStats"]


@dataclasses.dataclass(frozen=True)
class RunStats:
    """What every run records (each field None when not measured).

    - ``compile_seconds``: the time spent compiling [s] (compiled chunks only).
    - Devices: ``n_devices`` (those of every process of the run together),
      ``n_processes`` (None: files written before it was recorded, one process),
      ``device_kind``, ``platform``, ``emulated`` (several CPU devices emulated in one
      process, sharing its cores).

    A field of another kind of run (:class:`SynchronizedStats`,
    :class:`SyncAvoidingStats`, :class:`FullSystemStats`) reads None.
    """

    compile_seconds: float | None = None
    n_devices: int | None = None
    n_processes: int | None = None
    device_kind: str | None = None
    platform: str | None = None
    emulated: bool | None = None

    def __getattr__(self, name: str):
        # called only for names the instance lacks: another kind's field was not measured
        if name in _EVERY_FIELD:
            return None
        raise AttributeError(f"{type(self).__name__} has no field {name!r}")

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.metadata.get("sequence") and value is not None and not isinstance(value, tuple):
                object.__setattr__(self, f.name, tuple(np.asarray(value).tolist()))

    def to_dict(self) -> dict:
        """The measured fields (None left out), as plain Python values."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) is not None}

    @classmethod
    def from_dict(cls, data: dict) -> "RunStats":
        """The inverse of :meth:`to_dict`: the kind (``cls`` or one of its subclasses)
        whose fields hold the most keys of ``data``, the least specific one on a tie; keys
        no kind knows are ignored (files of a newer jaxsync stay readable)."""
        kinds = [cls] + [k for k in _KINDS if issubclass(k, cls) and k is not cls]
        best = max(kinds, key=lambda k: (len(_fields(k) & data.keys()), -len(_fields(k))))
        known = _fields(best)
        return best(**{k: v for k, v in data.items() if k in known})

    def merged(self, **changes) -> "RunStats":
        """A copy with ``changes`` applied (None values leave a field as it is)."""
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})


def _sequence():
    """A field holding a tuple (lists and arrays given to it become tuples)."""
    return dataclasses.field(default=None, metadata={"sequence": True})


@dataclasses.dataclass(frozen=True)
class SynchronizedStats(RunStats):
    """A synchronized run's statistics (:func:`jaxsync.simulate`, :func:`jaxsync.ensemble`):
    :class:`RunStats` and ``us_per_step``, the wall time per step of the compiled chunks
    [us] (for an ensemble, per batched step)."""

    us_per_step: float | None = None


@dataclasses.dataclass(frozen=True)
class SyncAvoidingStats(RunStats):
    """A synchronization-avoiding run's statistics (:class:`jaxsync.SyncAvoiding`):
    :class:`RunStats` and

    - Timing: ``us_per_step_synchronized`` and ``us_per_step_predicted``, the wall time
      per step of the two kinds of steps [us]; ``seconds_discarded``, the time spent on
      predicted steps that were recomputed [s].
    - Steps (``n_synchronized_steps`` + ``n_predicted_steps`` = ``n_steps``): ``n_steps``,
      ``n_cri`` (the last step of the first synchronized stretch),
      ``n_synchronized_steps``, ``n_predicted_steps``, ``n_discarded_steps`` (predicted,
      then recomputed synchronized after a rejected cycle).
    - Error control: ``resync_tolerance`` (as given, e.g. ``"1 %"``),
      ``n_resynchronizations``, ``resynchronized_at`` (the first step of each rejected
      cycle), ``es_hat_trigger`` (its es_hat [cm]), ``error_estimate_trigger`` (its
      estimated error [cm]; NaN where es_hat rejected it before it ran) and
      ``tolerance_cm`` (the tolerance then [cm]).
    - Online learning: ``surrogate_updated_at``, the steps after which the surrogates
      learned from the steps recomputed synchronized, and ``seconds_updating``, the time
      those updates took [s].
    - Load jumps: ``load_jumps``, the steps where a load's time function jumps that the run
      stayed synchronized through (None: predicted through).
    """

    us_per_step_synchronized: float | None = None
    us_per_step_predicted: float | None = None
    seconds_discarded: float | None = None
    n_steps: int | None = None
    n_cri: int | None = None
    n_synchronized_steps: int | None = None
    n_predicted_steps: int | None = None
    n_discarded_steps: int | None = None
    resync_tolerance: str | None = None
    n_resynchronizations: int | None = None
    resynchronized_at: tuple | None = _sequence()
    es_hat_trigger: tuple | None = _sequence()
    tolerance_cm: tuple | None = _sequence()
    error_estimate_trigger: tuple | None = _sequence()
    load_jumps: tuple | None = _sequence()
    surrogate_updated_at: tuple | None = _sequence()
    seconds_updating: float | None = None


@dataclasses.dataclass(frozen=True)
class FullSystemStats(RunStats):
    """A full-system run's statistics (:func:`jaxsync.simulate_full_system`):
    :class:`RunStats`, the step counts ``n_steps``, ``n_cri``, ``n_synchronized_steps``,
    ``n_predicted_steps``, ``us_per_step_predicted`` (the surrogate's wall time per
    predicted step [us]) and ``dirichlet_max_abs_predicted``, the largest |predicted
    value| on the Dirichlet dofs [cm]."""

    us_per_step_predicted: float | None = None
    n_steps: int | None = None
    n_cri: int | None = None
    n_synchronized_steps: int | None = None
    n_predicted_steps: int | None = None
    dirichlet_max_abs_predicted: float | None = None


_KINDS = (RunStats, SynchronizedStats, SyncAvoidingStats, FullSystemStats)


def _fields(kind) -> frozenset:
    return frozenset(f.name for f in dataclasses.fields(kind))


_EVERY_FIELD = frozenset().union(*(_fields(k) for k in _KINDS))
