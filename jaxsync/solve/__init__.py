"""The solve layer: runs of the explicit solver.

One entry point, :func:`simulate`, takes a coupling (:mod:`~jaxsync.solve.coupling`:
:class:`Synchronized`, or :class:`SyncAvoiding` of :mod:`~jaxsync.solve.coupling.syncavoid`),
which it lowers into the run's plan: a schedule of phases (synchronized and predicted steps,
the pure per-part functions both executors call) and the coupling's host-side policy
(:mod:`~jaxsync.solve.coupling.resync`: re-synchronization). The plan is run by one of the
two executors of :mod:`~jaxsync.solve.executors`: the host executor (compiled chunks driven
from Python through the one host loop: progress, divergence checks, checkpoints, error
control) or the traced executor (one JAX program, differentiable, its reverse pass from
:mod:`~jaxsync.solve.remat`). The options of a run are the objects of
:mod:`~jaxsync.solve.strategies`.

Entry points: :func:`simulate` (:mod:`~jaxsync.solve.solver`), :func:`simulate_sync_avoiding`
(the same as ``simulate(coupling=SyncAvoiding(...))``), :func:`ensemble`,
:func:`simulate_full_system` (one surrogate for every dof), :func:`steady_state`. The parts
of a distributed run and the predicted phase's runners: :mod:`~jaxsync.solve.executors`;
predictors: :mod:`~jaxsync.solve.coupling.predictors`; resumable checkpoints:
:mod:`~jaxsync.io.checkpoint`. The geometry of an imaged structure before its loads:
:func:`zero_pressure_geometry` (:mod:`~jaxsync.solve.zero_pressure`) and its alternative,
the prestress of the imaged geometry, :func:`prestress` (:mod:`~jaxsync.solve.prestress`); the
static solution as a differentiable function of the law, :func:`static_displacement`
(:mod:`~jaxsync.solve.static_adjoint`).
"""


from typing import TYPE_CHECKING

from ..lazy import export_lazily

__all__ = ["simulate", "ensemble", "steady_state", "SteadyState", "simulate_sync_avoiding", "simulate_full_system",
           "ResyncTolerance", "OraclePredictor", "describe_run", "step_counts",
           "Psum", "Ppermute", "Mpi", "Halo", "SaveAt", "SolverCheckpoint", "HostExecutor", "TracedExecutor",
           "Recompute", "StoreAll", "Coupling", "Synchronized", "SyncAvoiding", "SynchronizedSteps",
           "PredictedSteps",
           "Runner", "Chunk", "Segment", "Progress", "run_chunks", "SingleDeviceRunner",
           "DistributedParts", "DistributedRunner", "transport", "sync_strategy", "register_exchange",
           "unregister_exchange", "exchange_names", "zero_pressure_geometry", "zero_pressure_points",
           "static_displacement",
           "ZeroPressureGeometry", "prestress", "PrestressResult"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    ".coupling": ("Coupling", "Synchronized"),
    ".executors": ("Chunk", "DistributedParts", "DistributedRunner", "PredictedSteps", "Progress", "Runner", "Segment",
                   "SingleDeviceRunner", "SynchronizedSteps", "run_chunks"),
    ".ensemble": ("ensemble",),
    "..parallel.exchange": ("exchange_names", "register_exchange", "sync_strategy", "unregister_exchange"),
    ".full_system": ("simulate_full_system",),
    ".coupling.predictors": ("OraclePredictor",),
    ".prestress": ("PrestressResult", "prestress"),
    ".solver": ("SteadyState", "simulate", "steady_state"),
    ".strategies": ("Halo", "HostExecutor", "Mpi", "Ppermute", "Psum", "Recompute", "ResyncTolerance", "SaveAt",
                    "SolverCheckpoint", "StoreAll", "TracedExecutor", "transport"),
    ".coupling.syncavoid": ("SyncAvoiding", "describe_run", "simulate_sync_avoiding", "step_counts"),
    ".zero_pressure": ("ZeroPressureGeometry", "zero_pressure_geometry", "zero_pressure_points"),
    ".static_adjoint": ("static_displacement",),
})

if TYPE_CHECKING:
    from ..parallel.exchange import exchange_names, register_exchange, sync_strategy, unregister_exchange
    from .coupling import Coupling, Synchronized
    from .coupling.predictors import OraclePredictor
    from .coupling.syncavoid import SyncAvoiding, describe_run, simulate_sync_avoiding, step_counts
    from .ensemble import ensemble
    from .executors import (
        Chunk,
        DistributedParts,
        DistributedRunner,
        PredictedSteps,
        Progress,
        Runner,
        Segment,
        SingleDeviceRunner,
        SynchronizedSteps,
        run_chunks,
    )
    from .full_system import simulate_full_system
    from .prestress import PrestressResult, prestress
    from .solver import SteadyState, simulate, steady_state
    from .static_adjoint import static_displacement
    from .strategies import (
        Halo,
        HostExecutor,
        Mpi,
        Ppermute,
        Psum,
        Recompute,
        ResyncTolerance,
        SaveAt,
        SolverCheckpoint,
        StoreAll,
        TracedExecutor,
        transport,
    )
    from .zero_pressure import ZeroPressureGeometry, zero_pressure_geometry, zero_pressure_points
