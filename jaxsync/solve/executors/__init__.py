"""The executors that run a run's plan (:mod:`jaxsync.solve`): the host executor (compiled
chunks driven from Python through the one host loop: progress, divergence checks,
checkpoints, error control) and the traced executor (the whole schedule as one JAX program,
differentiable). Both run the same phases, the pure per-part functions of the synchronized
and predicted steps. Their modules are private; these names are the executors' interface
for couplings, exchanges and tests:

- the host loop: :class:`Runner`, :class:`Chunk`, :class:`Segment`, :class:`Progress`,
  :func:`run_chunks` (:class:`Diverged`, :class:`Stopped`);
- the host executor: :func:`run_on_host`, :class:`SingleDeviceRunner`, the parts of a
  distributed run (:class:`DistributedParts`, :class:`DistributedRunner`) and the runners of
  the predicted phase (:class:`PredictedPhase`, :class:`PredictedRunner`,
  :class:`MonitoredRunner`);
- the traced executor: :func:`run_traced`;
- the phases both run (:class:`SynchronizedSteps`, :class:`PredictedSteps` and their pure
  functions) and the trajectory a run records (:func:`synchronized_trajectory`,
  :func:`online_trajectory`).
"""

from typing import TYPE_CHECKING

from ...lazy import export_lazily

__all__ = [
    "DistributedParts", "DistributedRunner", "to_host", "Runner", "Chunk", "Segment", "Progress", "Diverged",
    "Stopped", "run_chunks", "divergence_limit", "chunk_of_saves", "run_on_host", "SingleDeviceRunner",
    "FirstPhase", "run_summary", "HostRun", "SynchronizedSteps", "PredictedSteps", "synchronized_steps",
    "part_synchronized_steps", "check_recordable", "predict_cycle", "overwritten_steps", "defect_probe",
    "refill_steps", "predicted_cycles", "PredictedPhase", "PredictedRunner", "MonitoredRunner", "CycleRejected",
    "DisagreementMonitor", "synchronized_trajectory", "online_trajectory", "run_parameters", "part_histories",
    "known_load_jumps", "load_signal_fields", "run_traced", "TracedRun",
]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    "._distributed": ("DistributedParts", "DistributedRunner", "to_host"),
    "._driver": ("Chunk", "Diverged", "Progress", "Runner", "Segment", "Stopped", "chunk_of_saves",
                 "divergence_limit", "run_chunks"),
    "._host": ("FirstPhase", "HostRun", "SingleDeviceRunner", "run_on_host", "run_summary"),
    "._phases": ("PredictedSteps", "SynchronizedSteps", "check_recordable", "defect_probe", "overwritten_steps",
                 "part_synchronized_steps", "predict_cycle", "predicted_cycles", "refill_steps",
                 "synchronized_steps"),
    "._predicted": ("CycleRejected", "DisagreementMonitor", "MonitoredRunner", "PredictedPhase", "PredictedRunner"),
    "._record": ("known_load_jumps", "load_signal_fields", "online_trajectory", "part_histories", "run_parameters",
                 "synchronized_trajectory"),
    "._traced": ("TracedRun", "run_traced"),
})

if TYPE_CHECKING:
    from ._distributed import DistributedParts, DistributedRunner, to_host
    from ._driver import (
        Chunk,
        Diverged,
        Progress,
        Runner,
        Segment,
        Stopped,
        chunk_of_saves,
        divergence_limit,
        run_chunks,
    )
    from ._host import FirstPhase, HostRun, SingleDeviceRunner, run_on_host, run_summary
    from ._phases import (
        PredictedSteps,
        SynchronizedSteps,
        check_recordable,
        defect_probe,
        overwritten_steps,
        part_synchronized_steps,
        predict_cycle,
        predicted_cycles,
        refill_steps,
        synchronized_steps,
    )
    from ._predicted import CycleRejected, DisagreementMonitor, MonitoredRunner, PredictedPhase, PredictedRunner
    from ._record import (
        known_load_jumps,
        load_signal_fields,
        online_trajectory,
        part_histories,
        run_parameters,
        synchronized_trajectory,
    )
    from ._traced import TracedRun, run_traced
