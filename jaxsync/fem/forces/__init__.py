"""The forces the explicit step asks of the physics. The modules are private; these names
are the package's interface:

- the seam: the force model a run compiles (:class:`ForceModel`, :func:`force_model`,
  :func:`run_force_model`, the modes :data:`MODES`), preassembled (:class:`Preassembled`,
  :data:`COMPACT_SLOT_STEPS`) or formed every step (:class:`ElementRecompute`), and the
  :class:`InternalForce` it gives;
- element forces of small-strain laws: :class:`ElementStiffness`, :func:`element_forces`;
- the total-Lagrangian internal force of finite-strain laws: :class:`TotalLagrangian`,
  :class:`HyperelasticForce`, its stable step (:func:`default_step`, :func:`stable_dt`,
  :func:`check_stable_dt`, :func:`exact_stable_dt`, :func:`element_wave_speeds`,
  :func:`element_frequencies`), :func:`inverted_elements`, :func:`strain_energy` and
  :func:`tangent_matrix`;
- follower pressure (on the deformed surface): :class:`FollowerPressure`,
  :func:`follower_pressure`, :func:`facet_nodes`, :func:`load_stiffness`;
- elastic supports, tissue springs and dashpots: :class:`ElasticSupport`
  (:class:`SurfaceSpring`, :class:`Dashpot`), :func:`stiffness_matrix`;
- the forces of the zero-pressure problem's unknown reference at a known deformed state:
  :class:`InverseForce` (:func:`inverse_operator`), :class:`InverseLoads`
  (:func:`inverse_loads`).
"""

from typing import TYPE_CHECKING

from ...lazy import export_lazily

__all__ = ["InternalForce", "ForceModel", "Preassembled", "ElementRecompute", "force_model", "run_force_model",
           "COMPACT_SLOT_STEPS", "ElementStiffness", "element_forces", "MODES", "TotalLagrangian", "HyperelasticForce",
           "stable_dt", "check_stable_dt", "exact_stable_dt", "inverted_elements", "element_wave_speeds",
           "strain_energy", "tangent_matrix", "FollowerPressure", "follower_pressure", "facet_nodes", "load_stiffness",
           "ElasticSupport", "stiffness_matrix", "InverseForce", "inverse_operator", "InverseLoads", "inverse_loads",
           "element_frequencies", "default_step", "SurfaceSpring", "Dashpot"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    "._internal_force": ("COMPACT_SLOT_STEPS", "ElementRecompute", "ForceModel", "InternalForce", "Preassembled",
                         "force_model", "run_force_model"),
    "._element_force": ("ElementStiffness", "MODES", "element_forces"),
    "._total_lagrangian": ("HyperelasticForce", "TotalLagrangian", "check_stable_dt", "default_step",
                           "element_frequencies", "element_wave_speeds", "exact_stable_dt", "inverted_elements",
                           "stable_dt", "strain_energy", "tangent_matrix"),
    "._follower": ("FollowerPressure", "facet_nodes", "follower_pressure", "load_stiffness"),
    "._support": ("Dashpot", "ElasticSupport", "SurfaceSpring", "stiffness_matrix"),
    "._inverse": ("InverseForce", "inverse_operator"),
    "._inverse_loads": ("InverseLoads", "inverse_loads"),
})

if TYPE_CHECKING:
    from ._element_force import MODES, ElementStiffness, element_forces
    from ._follower import FollowerPressure, facet_nodes, follower_pressure, load_stiffness
    from ._internal_force import (
        COMPACT_SLOT_STEPS,
        ElementRecompute,
        ForceModel,
        InternalForce,
        Preassembled,
        force_model,
        run_force_model,
    )
    from ._inverse import InverseForce, inverse_operator
    from ._inverse_loads import InverseLoads, inverse_loads
    from ._support import Dashpot, ElasticSupport, SurfaceSpring, stiffness_matrix
    from ._total_lagrangian import (
        HyperelasticForce,
        TotalLagrangian,
        check_stable_dt,
        default_step,
        element_frequencies,
        element_wave_speeds,
        exact_stable_dt,
        inverted_elements,
        stable_dt,
        strain_energy,
        tangent_matrix,
    )
