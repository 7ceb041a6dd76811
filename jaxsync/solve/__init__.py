"""The solve layer: runs of the explicit solver, driven by the one host loop.

Modules: :mod:`~jaxsync.solve.driver` (the host loop :func:`run_chunks`, the runner
protocol, progress), :mod:`~jaxsync.solve.solver` (:func:`simulate` on one device or over
parts, checkpoints, :func:`steady_state`), :mod:`~jaxsync.solve.distributed` (the runner
of paper Algorithm 1), :mod:`~jaxsync.solve.predictors` (what predicts the shared nodes),
:mod:`~jaxsync.solve.predicted` (the predicted phase and its runners),
:mod:`~jaxsync.solve.syncavoid` (paper Algorithm 3 with error control),
:mod:`~jaxsync.solve.full_system` (one surrogate for every dof).
"""

from .distributed import DistributedRunner
from .driver import Chunk, Progress, Runner, Segment, run_chunks
from .ensemble import ensemble
from .full_system import simulate_full_system
from .predictors import OraclePredictor
from .solver import SingleDeviceRunner, drive, simulate, steady_state
from .syncavoid import ResyncTolerance, describe_run, simulate_sync_avoiding, step_counts

__all__ = ["simulate", "ensemble", "steady_state", "simulate_sync_avoiding", "simulate_full_system",
           "ResyncTolerance", "OraclePredictor", "describe_run", "step_counts",
           "Runner", "Chunk", "Segment", "Progress", "run_chunks", "drive", "SingleDeviceRunner",
           "DistributedRunner"]
