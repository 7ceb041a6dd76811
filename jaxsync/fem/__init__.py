"""The finite-element layer: meshes, materials, loads, problems, assembly, the explicit
time step and the sparse mat-vec (no devices, no parts).

Meshes are :mod:`jaxsync.mesh`'s (re-exported here); the paper's cases and the generated
vessels, built on this layer, are :mod:`jaxsync.cases`.

- :mod:`~jaxsync.fem.materials`: the constitutive laws. :mod:`~jaxsync.fem.materials.law`
  (the protocol every law implements), :mod:`~jaxsync.fem.materials.linear_elastic`,
  :mod:`~jaxsync.fem.materials.hyperelastic` (finite-strain laws),
  :mod:`~jaxsync.fem.materials.viscoelastic` (Prony series: laws with internal variables),
  :mod:`~jaxsync.fem.materials.prestress` (a law with a prestrain per quadrature point).
- :mod:`~jaxsync.fem.forces`: the forces the explicit step asks for.
  :mod:`~jaxsync.fem.forces.internal_force` (the physics seam: which force a run compiles),
  :mod:`~jaxsync.fem.forces.element_force` (element forces formed every step),
  :mod:`~jaxsync.fem.forces.total_lagrangian` (the internal force of a finite-strain law),
  :mod:`~jaxsync.fem.forces.follower` (pressure on the deformed surface),
  :mod:`~jaxsync.fem.forces.support` (tissue springs and dashpots),
  :mod:`~jaxsync.fem.forces.inverse` and :mod:`~jaxsync.fem.forces.inverse_loads` (the
  zero-pressure problem: the forces of an unknown reference at a known deformed state).
- :mod:`~jaxsync.fem.loads` (body forces, pressure, time functions),
  :mod:`~jaxsync.fem.problem` (a problem), :mod:`~jaxsync.fem.space` (P1 and P2 nodes),
  :mod:`~jaxsync.fem.assembly` (scikit-fem operators), :mod:`~jaxsync.fem.sparse`
  (block-ELL stiffness), :mod:`~jaxsync.fem.timestep` (CFL step, stability bound, mass
  scaling), :mod:`~jaxsync.fem.stepper` (the pure explicit step).
"""

from typing import TYPE_CHECKING

from ..lazy import export_lazily

__all__ = ["Mesh", "MeshWarning", "read_mesh", "box_beam", "LinearElastic",
           "TimeFunction", "Constant", "Ramp", "StepOff", "Periodic", "Product", "BodyForce", "Pressure",
           "Dirichlet", "Problem",
           "ExplicitSystem", "SolverState", "build_system",
           "initial_state", "step", "advance", "cfl_dt", "max_stable_dt", "stable_step", "StableStep", "mass_scaling",
           "damped_bound",
           "MassScalingWarning", "NeoHookean", "NearlyIncompressibleNeoHookean", "HolzapfelGasserOgden",
           "helical_fibres", "TotalLagrangian", "stable_dt", "check_stable_dt", "inverted_elements",
           "MaterialLaw", "FiniteStrainLaw", "StandardLinearSolid", "ViscoelasticNeoHookean", "ViscoelasticHGO",
           "Prestressed"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    ".materials.hyperelastic": ("HolzapfelGasserOgden", "NearlyIncompressibleNeoHookean", "NeoHookean",
                                "helical_fibres"),
    ".loads": ("BodyForce", "Constant", "Periodic", "Pressure", "Product", "Ramp", "StepOff", "TimeFunction"),
    ".materials.linear_elastic": ("LinearElastic",),
    ".materials.law": ("FiniteStrainLaw", "MaterialLaw"),
    "..mesh": ("Mesh", "MeshWarning", "box_beam", "read_mesh"),
    ".materials.prestress": ("Prestressed",),
    ".problem": ("Dirichlet", "Problem"),
    ".stepper": ("ExplicitSystem", "SolverState", "advance", "build_system", "initial_state", "step"),
    ".timestep": ("MassScalingWarning", "StableStep", "cfl_dt", "damped_bound", "mass_scaling", "max_stable_dt",
                  "stable_step"),
    ".forces.total_lagrangian": ("TotalLagrangian", "check_stable_dt", "inverted_elements", "stable_dt"),
    ".materials.viscoelastic": ("StandardLinearSolid", "ViscoelasticHGO", "ViscoelasticNeoHookean"),
})

if TYPE_CHECKING:
    from ..mesh import Mesh, MeshWarning, box_beam, read_mesh
    from .forces.total_lagrangian import TotalLagrangian, check_stable_dt, inverted_elements, stable_dt
    from .loads import BodyForce, Constant, Periodic, Pressure, Product, Ramp, StepOff, TimeFunction
    from .materials.hyperelastic import HolzapfelGasserOgden, NearlyIncompressibleNeoHookean, NeoHookean, helical_fibres
    from .materials.law import FiniteStrainLaw, MaterialLaw
    from .materials.linear_elastic import LinearElastic
    from .materials.prestress import Prestressed
    from .materials.viscoelastic import StandardLinearSolid, ViscoelasticHGO, ViscoelasticNeoHookean
    from .problem import Dirichlet, Problem
    from .stepper import ExplicitSystem, SolverState, advance, build_system, initial_state, step
    from .timestep import MassScalingWarning, StableStep, cfl_dt, damped_bound, mass_scaling, max_stable_dt, stable_step
