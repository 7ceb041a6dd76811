"""Couplings: how the parts of a run are coupled at their shared nodes, as objects that
run their own policy.

:func:`jaxsync.simulate` takes one ``coupling=``:

* :class:`Synchronized` (the default): every step completes the parts' shared-node forces
  through the run's exchange (paper Algorithm 1; one device needs none);
* :class:`jaxsync.SyncAvoiding` (:mod:`jaxsync.solve.coupling`): synchronized up to
  n_cri, then surrogates predict the shared-node displacements and the parts do not
  exchange (paper Algorithm 3), with its error control and load-jump policy.

A coupling is lowered once per run by :meth:`Coupling.plan` into a :class:`RunPlan`: the
schedule of phases (:mod:`jaxsync.solve.executors`), the run's parts, the predictor, and the
two things the executors ask of it -- :meth:`RunPlan.finish_on_host` (what follows the first
synchronized phase on the host: a synchronized run's trajectory, or the predicted phase
with re-synchronization) and :meth:`RunPlan.traced_trajectory` (the trajectory of a traced
run). So the executors run schedules and never ask which coupling they run.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ...errors import ProblemError
from ...io.trajectory import Result
from ...pytree import pytree_dataclass
from ...run_stats import SynchronizedStats
from ..executors._phases import SynchronizedSteps

__all__ = ["Coupling", "RunPlan", "Synchronized", "as_coupling", "exchange_of"]


class Coupling:
    """The base of the couplings of :func:`jaxsync.simulate`: a coupling is a frozen pytree
    dataclass (its arrays, a surrogate's weights, are leaves, so a run can be differentiated
    in them) with one method, :meth:`plan`."""

    def plan(self, problem, n_steps: int, *, dt, save, partitions, exchange, mode: str, executor) -> "RunPlan":
        """The run's :class:`RunPlan`, its inputs checked: ``n_steps`` already a multiple
        of ``save.every``; ``partitions``, ``exchange`` and ``mode`` as given to
        :func:`jaxsync.simulate`; ``executor`` the one chosen (host or traced)."""
        raise NotImplementedError(f"{type(self).__name__} must implement plan()")


@dataclasses.dataclass(frozen=True)
class RunPlan:
    """A coupling lowered for one run (:meth:`Coupling.plan`).

    Attributes:
        schedule: the phases, ``(SynchronizedSteps(n),)`` or ``(SynchronizedSteps(n_cri),
            PredictedSteps(m))`` (:mod:`jaxsync.solve.executors`).
        distributed: the run's :class:`~jaxsync.solve.executors.DistributedParts`, or
            None for one device.
        predictor: the surrogates of a predicted phase (stacked on the part axis), or None.
        records_shared: the first phase records every part's shared-node values after every
            step (the surrogates' input history).
        label: the progress bar's label of the first phase.
    """

    schedule: tuple
    distributed: object = None
    predictor: object = None
    records_shared: bool = False
    label: str = "simulate"

    def finish_on_host(self, run) -> object:
        """The :class:`jaxsync.Trajectory` of a host run from its first synchronized phase
        (``run``: a :class:`jaxsync.solve.executors.HostRun`)."""
        raise NotImplementedError(f"{type(self).__name__} must implement finish_on_host(run)")

    def traced_trajectory(self, problem, dt, system, state, run, save) -> object:
        """The :class:`jaxsync.Trajectory` of a traced run at time step ``dt`` (``run``: the
        :class:`~jaxsync.solve.executors.TracedRun` of :attr:`schedule` from ``state``, with
        ``system`` the global system)."""
        raise NotImplementedError(f"{type(self).__name__} must implement traced_trajectory(...)")


@dataclasses.dataclass(frozen=True)
class _SynchronizedPlan(RunPlan):
    """The plan of a :class:`Synchronized` run: after its one phase, its trajectory with
    its shared-node histories and a :class:`jaxsync.SynchronizedStats`."""

    def finish_on_host(self, run):
        from ..executors._host import run_summary
        from ..executors._record import synchronized_trajectory

        first = run.first
        segment = first.segment
        stats = SynchronizedStats(**run_summary(segment, run.runner),
                                  us_per_step=1e6 * segment.seconds / segment.n_steps if segment.n_steps else None)
        return synchronized_trajectory(run.problem, np.concatenate(first.snapshots), run.dt, run.save,
                                       None if self.distributed is None else self.distributed.partition,
                                       first.shared, stats=stats, result=Result.SUCCESSFUL)

    def traced_trajectory(self, problem, dt, system, state, run, save):
        import jax.numpy as jnp

        from ..executors._record import synchronized_trajectory

        recorded = None
        if run.recorded is not None:  # per part, rows from step 0
            recorded = [jnp.concatenate([state.displacement[None, part.shared_nodes],
                                         run.recorded[p, :, :part.n_shared]]).reshape(-1, 3 * part.n_shared)
                        for p, part in enumerate(self.distributed.partition.parts)]
        displacement = jnp.concatenate([state.displacement[None], run.saved])
        return synchronized_trajectory(problem, displacement, dt, save,
                                       None if self.distributed is None else self.distributed.partition, recorded,
                                       result=run.result)


@pytree_dataclass
class Synchronized(Coupling):
    """Every step synchronized (paper Algorithm 1): each part's shared-node forces are
    completed through the run's exchange (``exchange=`` of :func:`jaxsync.simulate`) every
    step, or with deep halos every k steps (exact). The default coupling; a single-device
    run (``partitions=None``) has no exchange."""

    def plan(self, problem, n_steps: int, *, dt, save, partitions, exchange, mode: str, executor) -> RunPlan:
        if partitions is None and save.records_every_step:
            raise ProblemError("shared_every needs a distributed run (partitions=...): a single-device "
                               "run has no shared nodes")
        if partitions is None and exchange is not None:
            raise ProblemError(f"exchange={exchange!r} needs a distributed run: pass partitions=n_parts")
        distributed = None
        if partitions is not None:
            from ..executors._distributed import DistributedParts

            distributed = DistributedParts(problem, partitions, exchange, mode=mode)
            if save.records_every_step:
                distributed.check_recordable()
            unit = distributed.check_save_every(save.every)  # save.every, or whole exchange cycles of deep halos
            if n_steps % unit:
                raise ProblemError(f"with halo depth {distributed.halo_depth} and save_every={save.every}, n_steps "
                                   f"must be a multiple of {unit}; use n_steps={n_steps - n_steps % unit + unit}")
        return _SynchronizedPlan((SynchronizedSteps(n_steps),), distributed)


def as_coupling(coupling) -> Coupling:
    """``coupling`` checked: a :class:`Coupling` (None: :class:`Synchronized`)."""
    if coupling is None:
        return Synchronized()
    if isinstance(coupling, Coupling):
        return coupling
    if isinstance(coupling, type) and issubclass(coupling, Coupling):
        raise ProblemError(f"coupling={coupling.__name__} is the class: pass an instance, e.g. "
                           f"coupling=jaxsync.{coupling.__name__}(...)")
    raise ProblemError(f"coupling={coupling!r} is not a coupling: pass jaxsync.Synchronized() (every step "
                       "synchronized, the default) or jaxsync.SyncAvoiding(surrogates, n_cri=...) (surrogates "
                       "replace the exchange after n_cri)")


def exchange_of(exchange, sync):
    """The run's exchange from ``exchange=`` and its alias ``sync=`` (at most one given)."""
    if sync is not None and exchange is not None:
        raise ProblemError(f"exchange={exchange!r} and sync={sync!r} both given: sync= is another name for "
                           "exchange=; pass one of them")
    return exchange if exchange is not None else sync
