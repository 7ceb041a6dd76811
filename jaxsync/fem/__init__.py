"""The finite-element layer: meshes, materials, loads, problems, assembly, the explicit
time step and the sparse mat-vec (no devices, no parts). Its modules are private; these
names are its interface.

Meshes are :mod:`jaxsync.mesh`'s (:class:`Mesh`, :class:`MeshWarning`, :func:`read_mesh`,
:func:`box_beam`, re-exported here); the paper's cases and the generated vessels, built on
this layer, are :mod:`jaxsync.cases`.

- :mod:`~jaxsync.fem.materials`: the constitutive laws (the :class:`MaterialLaw` protocol,
  :class:`FiniteStrainLaw`, :class:`LinearElastic`, the hyperelastic laws
  :class:`NeoHookean`, :class:`NearlyIncompressibleNeoHookean` and
  :class:`HolzapfelGasserOgden` with :func:`helical_fibres`, the viscoelastic laws
  :class:`StandardLinearSolid`, :class:`ViscoelasticNeoHookean` and
  :class:`ViscoelasticHGO`, and :class:`Prestressed`, re-exported here).
- :mod:`~jaxsync.fem.forces`: the forces the explicit step asks for (the force model a run
  compiles, element forces, follower pressure, elastic supports, the forces of the
  zero-pressure problem); the total-Lagrangian force of finite-strain laws
  (:class:`TotalLagrangian`) and its stable step (:func:`stable_dt`,
  :func:`check_stable_dt`, :func:`inverted_elements`) are re-exported here.
- Loads: body forces and pressure (:class:`BodyForce`, :class:`Pressure`), their time
  functions (:class:`TimeFunction`, :class:`Constant`, :class:`Ramp`, :class:`StepOff`,
  :class:`Periodic`, :class:`Product`) and the steps where they jump
  (:func:`load_jumps`); the known load signals a load-aware surrogate reads
  (:class:`LoadSignals`, :class:`RecordedLoadSignals`, :class:`LoadInput`,
  :func:`load_inputs_of`, :func:`check_load_inputs`, :func:`record_load_signal`,
  :func:`time_function_form`, :func:`describe_time_function`).
- A problem: :class:`Problem`, :class:`Dirichlet`, :class:`LockingWarning`; the problem
  lowered to the arrays a run reads, once (:class:`DiscreteProblem`,
  ``Problem.discrete``); the rigid-body motions that nothing holds
  (:func:`free_rigid_motions`, :class:`RigidBodyWarning`).
- Nodes and operators: the P1 and P2 spaces (:class:`FunctionSpace`,
  :func:`function_space`, :func:`vtk_cells`, :data:`VTK_TETRA10_ORDER`), scikit-fem
  operators (:class:`UnitOperators`, :func:`assemble_unit_operators`, :func:`lumped_mass`,
  :func:`consistent_mass`, :func:`body_force_vectors`, :func:`pressure_vector`,
  :func:`element_blocks`, :func:`boundary_facet_indices`) and the block-ELL stiffness
  (:class:`BlockEll`, :class:`GroupedEll`, :func:`node_adjacency`,
  :func:`block_ell_values`, :func:`row_degrees`, :func:`degree_widths`,
  :func:`grouped_layout`, :func:`split_diagonal`, :func:`in_compact_form`).
- The time step: the CFL step and the stability bound (:func:`cfl_dt`,
  :func:`max_stable_dt`, :func:`stable_step`, :class:`StableStep`, :func:`damped_bound`,
  :func:`check_dt`, :func:`element_size`, :func:`element_dt`, :func:`small_strain_step`,
  :data:`DENSE_EIGEN_DOFS`), mass scaling (:func:`mass_scaling`,
  :class:`MassScalingWarning`) and the checks of a hyperelastic run (:class:`RunCheck`).
- The pure explicit step: :func:`build_system` (:class:`ExplicitSystem`),
  :func:`initial_state` (:class:`SolverState`, :func:`start_levels`), :func:`step`,
  :func:`advance` (:class:`Probe`, :data:`STEP_UNROLL`), :func:`central_difference`,
  :func:`apply_dirichlet`.
"""

from typing import TYPE_CHECKING

from ..lazy import export_lazily

__all__ = ["Mesh", "MeshWarning", "read_mesh", "box_beam", "LinearElastic", "TimeFunction", "Constant", "Ramp",
           "StepOff", "Periodic", "Product", "BodyForce", "Pressure", "Dirichlet", "Problem", "DiscreteProblem",
           "ExplicitSystem", "SolverState", "build_system", "initial_state", "step", "advance", "cfl_dt",
           "max_stable_dt", "stable_step", "StableStep", "mass_scaling", "damped_bound", "MassScalingWarning",
           "NeoHookean", "NearlyIncompressibleNeoHookean", "HolzapfelGasserOgden", "helical_fibres", "TotalLagrangian",
           "stable_dt", "check_stable_dt", "inverted_elements", "MaterialLaw", "FiniteStrainLaw",
           "StandardLinearSolid", "ViscoelasticNeoHookean", "ViscoelasticHGO", "Prestressed", "UnitOperators",
           "assemble_unit_operators", "consistent_mass", "lumped_mass", "body_force_vectors", "pressure_vector",
           "boundary_facet_indices", "element_blocks", "LoadInput", "LoadSignals", "RecordedLoadSignals",
           "load_inputs_of", "check_load_inputs", "time_function_form", "describe_time_function", "record_load_signal",
           "load_jumps", "RigidBodyWarning", "free_rigid_motions", "RunCheck", "function_space", "VTK_TETRA10_ORDER",
           "vtk_cells", "BlockEll", "GroupedEll", "node_adjacency", "block_ell_values", "degree_widths",
           "grouped_layout", "row_degrees", "split_diagonal", "in_compact_form", "Probe", "STEP_UNROLL",
           "apply_dirichlet", "central_difference", "check_dt", "element_size", "DENSE_EIGEN_DOFS", "LockingWarning",
           "FunctionSpace", "start_levels", "element_dt", "small_strain_step"]

# where each name of __all__ is imported from on first use (jaxsync.lazy): the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    ".materials._hyperelastic": ("HolzapfelGasserOgden", "NearlyIncompressibleNeoHookean", "NeoHookean",
                                 "helical_fibres"),
    "._loads": ("BodyForce", "Constant", "Periodic", "Pressure", "Product", "Ramp", "StepOff", "TimeFunction",
                "load_jumps"),
    ".materials._linear_elastic": ("LinearElastic",),
    ".materials._law": ("FiniteStrainLaw", "MaterialLaw"),
    "..mesh": ("Mesh", "MeshWarning", "box_beam", "read_mesh"),
    ".materials._prestress": ("Prestressed",),
    "._problem": ("Dirichlet", "LockingWarning", "Problem"),
    "._discrete": ("DiscreteProblem",),
    "._stepper": ("ExplicitSystem", "Probe", "STEP_UNROLL", "SolverState", "advance", "apply_dirichlet", "build_system",
                  "central_difference", "initial_state", "start_levels", "step"),
    "._timestep": ("DENSE_EIGEN_DOFS", "MassScalingWarning", "StableStep", "cfl_dt", "check_dt", "damped_bound",
                   "element_dt", "element_size", "mass_scaling", "max_stable_dt", "small_strain_step", "stable_step"),
    ".forces._total_lagrangian": ("TotalLagrangian", "check_stable_dt", "inverted_elements", "stable_dt"),
    ".materials._viscoelastic": ("StandardLinearSolid", "ViscoelasticHGO", "ViscoelasticNeoHookean"),
    "._assembly": ("UnitOperators", "assemble_unit_operators", "body_force_vectors", "boundary_facet_indices",
                   "consistent_mass", "element_blocks", "lumped_mass", "pressure_vector"),
    "._load_signals": ("LoadInput", "LoadSignals", "RecordedLoadSignals", "check_load_inputs", "describe_time_function",
                       "load_inputs_of", "record_load_signal", "time_function_form"),
    "._rigid_body": ("RigidBodyWarning", "free_rigid_motions"),
    "._run_check": ("RunCheck",),
    "._space": ("FunctionSpace", "VTK_TETRA10_ORDER", "function_space", "vtk_cells"),
    "._sparse": ("BlockEll", "GroupedEll", "block_ell_values", "degree_widths", "grouped_layout", "in_compact_form",
                 "node_adjacency", "row_degrees", "split_diagonal"),
})

if TYPE_CHECKING:
    from ..mesh import Mesh, MeshWarning, box_beam, read_mesh
    from ._assembly import (
        UnitOperators,
        assemble_unit_operators,
        body_force_vectors,
        boundary_facet_indices,
        consistent_mass,
        element_blocks,
        lumped_mass,
        pressure_vector,
    )
    from ._discrete import DiscreteProblem
    from ._load_signals import (
        LoadInput,
        LoadSignals,
        RecordedLoadSignals,
        check_load_inputs,
        describe_time_function,
        load_inputs_of,
        record_load_signal,
        time_function_form,
    )
    from ._loads import BodyForce, Constant, Periodic, Pressure, Product, Ramp, StepOff, TimeFunction, load_jumps
    from ._problem import Dirichlet, LockingWarning, Problem
    from ._rigid_body import RigidBodyWarning, free_rigid_motions
    from ._run_check import RunCheck
    from ._space import VTK_TETRA10_ORDER, FunctionSpace, function_space, vtk_cells
    from ._sparse import (
        BlockEll,
        GroupedEll,
        block_ell_values,
        degree_widths,
        grouped_layout,
        in_compact_form,
        node_adjacency,
        row_degrees,
        split_diagonal,
    )
    from ._stepper import (
        STEP_UNROLL,
        ExplicitSystem,
        Probe,
        SolverState,
        advance,
        apply_dirichlet,
        build_system,
        central_difference,
        initial_state,
        start_levels,
        step,
    )
    from ._timestep import (
        DENSE_EIGEN_DOFS,
        MassScalingWarning,
        StableStep,
        cfl_dt,
        check_dt,
        damped_bound,
        element_dt,
        element_size,
        mass_scaling,
        max_stable_dt,
        small_strain_step,
        stable_step,
    )
    from .forces._total_lagrangian import TotalLagrangian, check_stable_dt, inverted_elements, stable_dt
    from .materials._hyperelastic import (
        HolzapfelGasserOgden,
        NearlyIncompressibleNeoHookean,
        NeoHookean,
        helical_fibres,
    )
    from .materials._law import FiniteStrainLaw, MaterialLaw
    from .materials._linear_elastic import LinearElastic
    from .materials._prestress import Prestressed
    from .materials._viscoelastic import StandardLinearSolid, ViscoelasticHGO, ViscoelasticNeoHookean
