"""Couplings: how the parts of a run are coupled at their shared nodes, as objects that run
their own policy. The modules are private; these names are the package's interface.

The protocol is :class:`Coupling` (:func:`as_coupling`, :func:`exchange_of`, and the
:class:`RunPlan` a coupling lowers a run into); :class:`Synchronized` exchanges every
step. The synchronization-avoiding coupling of the paper, :class:`SyncAvoiding`
(:func:`simulate_sync_avoiding`; :func:`describe_run` and :func:`step_counts` of its
runs), brings its host-side policy (re-synchronization, online learning), the estimate of
its error (:class:`ErrorPropagator`: the modal propagation of the force-balance defect,
:data:`DEFAULT_MODES` modes of :func:`linearised_stiffness`; above
:data:`FLEXIBILITY_LIMIT` shared dofs its static remainder is solved for at every probe)
and its predictors (:class:`OraclePredictor`).

A coupling of your own implements :class:`Coupling`.
"""

from typing import TYPE_CHECKING

from ...lazy import export_lazily

__all__ = ["Coupling", "RunPlan", "Synchronized", "as_coupling", "exchange_of", "SyncAvoiding",
           "simulate_sync_avoiding", "describe_run", "step_counts", "OraclePredictor", "ErrorPropagator",
           "DEFAULT_MODES", "FLEXIBILITY_LIMIT", "linearised_stiffness"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    "._base": ("Coupling", "RunPlan", "Synchronized", "as_coupling", "exchange_of"),
    "._syncavoid": ("SyncAvoiding", "describe_run", "simulate_sync_avoiding", "step_counts"),
    "._predictors": ("OraclePredictor",),
    "._error_estimate": ("DEFAULT_MODES", "ErrorPropagator", "FLEXIBILITY_LIMIT", "linearised_stiffness"),
})

if TYPE_CHECKING:
    from ._base import Coupling, RunPlan, Synchronized, as_coupling, exchange_of
    from ._error_estimate import DEFAULT_MODES, FLEXIBILITY_LIMIT, ErrorPropagator, linearised_stiffness
    from ._predictors import OraclePredictor
    from ._syncavoid import SyncAvoiding, describe_run, simulate_sync_avoiding, step_counts
