"""The finite-element layer: meshes, materials, loads, problems, assembly, the explicit
time step and the sparse mat-vec (no devices, no parts).

Meshes are :mod:`jaxsync.mesh`'s (re-exported here); the paper's cases and the generated
vessels, built on this layer, are :mod:`jaxsync.cases`. Modules: :mod:`~jaxsync.fem.material`,
:mod:`~jaxsync.fem.loads` (body forces, pressure, time functions), :mod:`~jaxsync.fem.problem`
(a problem), :mod:`~jaxsync.fem.assembly` (scikit-fem operators),
:mod:`~jaxsync.fem.element_force` (element forces formed every step),
:mod:`~jaxsync.fem.material_law` (the protocol every material law implements),
:mod:`~jaxsync.fem.hyperelastic` (finite-strain laws), :mod:`~jaxsync.fem.viscoelastic` (a finite-strain
standard linear solid, a law with internal variables), :mod:`~jaxsync.fem.total_lagrangian`
(their internal force, total-Lagrangian explicit dynamics), :mod:`~jaxsync.fem.follower`
(pressure on the deformed surface), :mod:`~jaxsync.fem.prestress` (a law with a prestrain
per quadrature point), :mod:`~jaxsync.fem.inverse` (the internal force of an unknown reference
at a known deformed configuration: the zero-pressure problem), :mod:`~jaxsync.fem.inverse_loads`
(the supports and dead loads of that problem, integrals over the unknown reference),
:mod:`~jaxsync.fem.sparse` (block-ELL stiffness), :mod:`~jaxsync.fem.timestep` (CFL step,
stability bound, mass scaling), :mod:`~jaxsync.fem.stepper` (the pure explicit step).
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
    ".hyperelastic": ("HolzapfelGasserOgden", "NearlyIncompressibleNeoHookean", "NeoHookean", "helical_fibres"),
    ".loads": ("BodyForce", "Constant", "Periodic", "Pressure", "Product", "Ramp", "StepOff", "TimeFunction"),
    ".material": ("LinearElastic",),
    ".material_law": ("FiniteStrainLaw", "MaterialLaw"),
    "..mesh": ("Mesh", "MeshWarning", "box_beam", "read_mesh"),
    ".prestress": ("Prestressed",),
    ".problem": ("Dirichlet", "Problem"),
    ".stepper": ("ExplicitSystem", "SolverState", "advance", "build_system", "initial_state", "step"),
    ".timestep": ("MassScalingWarning", "StableStep", "cfl_dt", "damped_bound", "mass_scaling", "max_stable_dt",
                  "stable_step"),
    ".total_lagrangian": ("TotalLagrangian", "check_stable_dt", "inverted_elements", "stable_dt"),
    ".viscoelastic": ("StandardLinearSolid", "ViscoelasticHGO", "ViscoelasticNeoHookean"),
})

if TYPE_CHECKING:
    from ..mesh import Mesh, MeshWarning, box_beam, read_mesh
    from .hyperelastic import HolzapfelGasserOgden, NearlyIncompressibleNeoHookean, NeoHookean, helical_fibres
    from .loads import BodyForce, Constant, Periodic, Pressure, Product, Ramp, StepOff, TimeFunction
    from .material import LinearElastic
    from .material_law import FiniteStrainLaw, MaterialLaw
    from .prestress import Prestressed
    from .problem import Dirichlet, Problem
    from .stepper import ExplicitSystem, SolverState, advance, build_system, initial_state, step
    from .timestep import MassScalingWarning, StableStep, cfl_dt, damped_bound, mass_scaling, max_stable_dt, stable_step
    from .total_lagrangian import TotalLagrangian, check_stable_dt, inverted_elements, stable_dt
    from .viscoelastic import StandardLinearSolid, ViscoelasticHGO, ViscoelasticNeoHookean
