"""The solve layer: runs of the explicit solver. Its modules are private; these names are
its interface.

One entry point, :func:`simulate`, takes a coupling (:mod:`~jaxsync.solve.coupling`:
:class:`Synchronized`, or :class:`SyncAvoiding`; the protocol :class:`Coupling`), which it
lowers into the run's plan: a schedule of phases (:class:`SynchronizedSteps`,
:class:`PredictedSteps`: the pure per-part functions both executors call) and the
coupling's host-side policy (re-synchronization). The plan is run by one of the two
executors of :mod:`~jaxsync.solve.executors`: the host executor (compiled chunks driven
from Python through the one host loop, :class:`Runner`, :class:`Chunk`, :class:`Segment`,
:class:`Progress`, :func:`run_chunks`: progress, divergence checks, checkpoints, error
control; :class:`SingleDeviceRunner`, and the parts of a distributed run,
:class:`DistributedParts`, :class:`DistributedRunner`) or the traced executor (one JAX
program, differentiable, its reverse pass from :func:`advance_recomputing`, segments of
:func:`segment_steps_for_budget` and :func:`step_residual_bytes`).

The options of a run: :class:`SaveAt`, :class:`SolverCheckpoint`, :class:`HostExecutor`,
:class:`TracedExecutor` (:class:`Recompute`, :class:`StoreAll`), :class:`ResyncTolerance`
and the exchanges :class:`Psum`, :class:`Ppermute`, :class:`Mpi`, :class:`Halo`
(:func:`transport` describes one; their registry, :func:`sync_strategy`,
:func:`register_exchange`, :func:`unregister_exchange`, :func:`exchange_names`, is
:mod:`jaxsync.parallel.exchange`'s).

Entry points: :func:`simulate`, :func:`steady_state` (:class:`SteadyState`),
:func:`simulate_sync_avoiding` (the same as ``simulate(coupling=SyncAvoiding(...))``;
:func:`describe_run` and :func:`step_counts` of its runs, :class:`OraclePredictor` to
replay known shared displacements), :func:`ensemble` (its members' setup and systems:
:func:`setup_of_members`, :func:`batched_system`, :func:`member_system`,
:func:`initial_states`; its step: :func:`default_dt`, :func:`member_bounds`),
:func:`simulate_full_system` (one surrogate for every dof), and solver-in-the-loop
fine-tuning of the surrogates (:func:`fine_tune_in_the_loop`, :class:`FineTuneConfig`,
:class:`FineTuneResult`). Resumable checkpoints: :mod:`~jaxsync.io.checkpoint`. The
geometry of an imaged structure before its loads: :func:`zero_pressure_geometry`
(:class:`ZeroPressureGeometry`, :func:`zero_pressure_points`) and its alternative, the
prestress of the imaged geometry, :func:`prestress` (:class:`PrestressResult`,
:func:`out_of_balance`); the static solution as a differentiable function of the law,
:func:`static_displacement`.
"""

from typing import TYPE_CHECKING

from ..lazy import export_lazily

__all__ = ["simulate", "ensemble", "steady_state", "SteadyState", "simulate_sync_avoiding", "simulate_full_system",
           "ResyncTolerance", "OraclePredictor", "describe_run", "step_counts", "Psum", "Ppermute", "Mpi", "Halo",
           "SaveAt", "SolverCheckpoint", "HostExecutor", "TracedExecutor", "Recompute", "StoreAll", "Coupling",
           "Synchronized", "SyncAvoiding", "SynchronizedSteps", "PredictedSteps", "Runner", "Chunk", "Segment",
           "Progress", "run_chunks", "SingleDeviceRunner", "DistributedParts", "DistributedRunner", "transport",
           "sync_strategy", "register_exchange", "unregister_exchange", "exchange_names", "zero_pressure_geometry",
           "zero_pressure_points", "static_displacement", "ZeroPressureGeometry", "prestress", "PrestressResult",
           "setup_of_members", "batched_system", "member_system", "initial_states", "default_dt", "member_bounds",
           "FineTuneConfig", "FineTuneResult", "fine_tune_in_the_loop", "out_of_balance", "advance_recomputing",
           "segment_steps_for_budget", "step_residual_bytes"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    ".coupling": ("Coupling", "Synchronized"),
    ".executors": ("Chunk", "DistributedParts", "DistributedRunner", "PredictedSteps", "Progress", "Runner", "Segment",
                   "SingleDeviceRunner", "SynchronizedSteps", "run_chunks"),
    "._ensemble": ("ensemble",),
    "..parallel.exchange": ("exchange_names", "register_exchange", "sync_strategy", "unregister_exchange"),
    "._full_system": ("simulate_full_system",),
    ".coupling._predictors": ("OraclePredictor",),
    "._prestress": ("PrestressResult", "out_of_balance", "prestress"),
    "._solver": ("SteadyState", "simulate", "steady_state"),
    "._strategies": ("Halo", "HostExecutor", "Mpi", "Ppermute", "Psum", "Recompute", "ResyncTolerance", "SaveAt",
                     "SolverCheckpoint", "StoreAll", "TracedExecutor", "transport"),
    ".coupling._syncavoid": ("SyncAvoiding", "describe_run", "simulate_sync_avoiding", "step_counts"),
    "._zero_pressure": ("ZeroPressureGeometry", "zero_pressure_geometry", "zero_pressure_points"),
    "._static_adjoint": ("static_displacement",),
    "._ensemble_members": ("batched_system", "initial_states", "member_system", "setup_of_members"),
    "._ensemble_stability": ("default_dt", "member_bounds"),
    "._finetune": ("FineTuneConfig", "FineTuneResult", "fine_tune_in_the_loop"),
    "._remat": ("advance_recomputing", "segment_steps_for_budget", "step_residual_bytes"),
})

if TYPE_CHECKING:
    from ..parallel.exchange import exchange_names, register_exchange, sync_strategy, unregister_exchange
    from ._ensemble import ensemble
    from ._ensemble_members import batched_system, initial_states, member_system, setup_of_members
    from ._ensemble_stability import default_dt, member_bounds
    from ._finetune import FineTuneConfig, FineTuneResult, fine_tune_in_the_loop
    from ._full_system import simulate_full_system
    from ._prestress import PrestressResult, out_of_balance, prestress
    from ._remat import advance_recomputing, segment_steps_for_budget, step_residual_bytes
    from ._solver import SteadyState, simulate, steady_state
    from ._static_adjoint import static_displacement
    from ._strategies import (
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
    from ._zero_pressure import ZeroPressureGeometry, zero_pressure_geometry, zero_pressure_points
    from .coupling import Coupling, Synchronized
    from .coupling._predictors import OraclePredictor
    from .coupling._syncavoid import SyncAvoiding, describe_run, simulate_sync_avoiding, step_counts
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
