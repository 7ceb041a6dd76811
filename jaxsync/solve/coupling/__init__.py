"""Couplings: how the parts of a run are coupled at their shared nodes, as objects that run
their own policy (:mod:`.base`: the protocol, :class:`Coupling`, and :class:`Synchronized`).
The synchronization-avoiding coupling of the paper (:mod:`.syncavoid`: :class:`jaxsync.SyncAvoiding`)
brings its host-side policy (:mod:`.resync`: re-synchronization, online learning), the
estimate of its error (:mod:`.error_estimate`) and its predictors (:mod:`.predictors`).
A coupling of your own implements :class:`Coupling`.
"""

from typing import TYPE_CHECKING

from ...lazy import export_lazily

__all__ = ["Coupling", "RunPlan", "Synchronized", "as_coupling", "exchange_of"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    ".base": ("Coupling", "RunPlan", "Synchronized", "as_coupling", "exchange_of"),
})

if TYPE_CHECKING:
    from .base import Coupling, RunPlan, Synchronized, as_coupling, exchange_of
