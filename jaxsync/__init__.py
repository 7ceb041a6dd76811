"""jaxsync: differentiable, distributed explicit finite elements for linear
elastodynamics on tetrahedra, with LSTM surrogates that replace synchronization.

The solver runs in float64: call ``jax.config.update("jax_enable_x64", True)`` before
creating arrays (the command line does this for you); the solver's entry points raise
:class:`PrecisionError` otherwise. Importing jaxsync changes no global configuration, and
imports no numerical library: each name below is imported from its module on first use
(:mod:`jaxsync.lazy`).
"""

from typing import TYPE_CHECKING

from .lazy import export_lazily

__version__ = "0.2.0"

__all__ = [
    "JaxsyncError", "MeshError", "MaterialError", "ProblemError", "StabilityError",
    "ConvergenceError", "CheckpointError", "ConfigError", "OutputError", "PartitionError", "PrecisionError",
    "Partition", "partition",
    "Mesh", "MeshWarning", "read_mesh", "merge_coincident_nodes",
    "box_beam", "vessel_mesh", "vessel_centerline", "coronary_mesh", "devices",
    "LinearElastic", "NeoHookean", "NearlyIncompressibleNeoHookean", "HolzapfelGasserOgden", "helical_fibres",
    "TotalLagrangian", "stable_dt", "check_stable_dt", "inverted_elements",
    "BodyForce", "Pressure", "Traction", "ElasticSupport", "Constant", "Ramp", "StepOff",
    "Periodic",
    "Dirichlet", "Problem", "LockingWarning", "RigidBodyWarning", "SynchronizedRunWarning",
    "cantilever", "coronary", "coronary_waveform", "DEFAULT_WAVEFORM",
    "simulate", "ensemble", "Members", "steady_state", "SteadyState", "cfl_dt", "max_stable_dt", "stable_step",
    "StableStep",
    "mass_scaling", "MassScalingWarning",
    "simulate_sync_avoiding", "simulate_full_system", "ResyncTolerance", "Synchronized", "SyncAvoiding",
    "Trajectory", "RunStats", "SynchronizedStats", "SyncAvoidingStats", "FullSystemStats", "PartHistory", "Result",
    "SaveAt", "Psum", "Ppermute", "Mpi", "Halo", "SolverCheckpoint", "HostExecutor", "TracedExecutor",
    "Recompute", "StoreAll",
    "zero_pressure_geometry", "zero_pressure_points", "ZeroPressureGeometry", "prestress", "PrestressResult",
    "Prestressed", "static_displacement",
]

# where each name of __all__ is imported from on first use: the imports of TYPE_CHECKING below
__getattr__, __dir__ = export_lazily(__name__, {
    ".errors": ("CheckpointError", "ConfigError", "ConvergenceError", "JaxsyncError", "MaterialError", "MeshError",
                "OutputError", "PartitionError", "PrecisionError", "ProblemError", "StabilityError",
                "SynchronizedRunWarning"),
    ".cases": ("DEFAULT_WAVEFORM", "cantilever", "coronary", "coronary_mesh", "coronary_waveform", "vessel_centerline",
               "vessel_mesh"),
    ".fem.materials._hyperelastic": ("HolzapfelGasserOgden", "NearlyIncompressibleNeoHookean", "NeoHookean",
                                    "helical_fibres"),
    ".fem._loads": ("BodyForce", "Constant", "Periodic", "Pressure", "Ramp", "StepOff", "Traction"),
    ".fem.materials._linear_elastic": ("LinearElastic",),
    ".mesh": ("Mesh", "MeshWarning", "box_beam", "merge_coincident_nodes", "read_mesh"),
    ".fem.materials._prestress": ("Prestressed",),
    ".fem._problem": ("Dirichlet", "LockingWarning", "Problem"),
    ".fem._rigid_body": ("RigidBodyWarning",),
    ".fem.forces._support": ("ElasticSupport",),
    ".fem._timestep": ("MassScalingWarning", "StableStep", "cfl_dt", "mass_scaling", "max_stable_dt", "stable_step"),
    ".fem.forces._total_lagrangian": ("TotalLagrangian", "check_stable_dt", "inverted_elements", "stable_dt"),
    ".parallel": ("devices",),
    ".parallel._partitioning": ("Partition", "partition"),
    ".run_stats": ("FullSystemStats", "RunStats", "SyncAvoidingStats", "SynchronizedStats"),
    ".solve.coupling": ("Synchronized",),
    ".solve._ensemble": ("ensemble",),
    ".solve._members": ("Members",),
    ".solve._full_system": ("simulate_full_system",),
    ".solve._solver": ("SteadyState", "simulate", "steady_state"),
    ".solve._strategies": ("Halo", "HostExecutor", "Mpi", "Ppermute", "Psum", "Recompute", "ResyncTolerance",
                          "SaveAt", "SolverCheckpoint", "StoreAll", "TracedExecutor"),
    ".solve._prestress": ("PrestressResult", "prestress"),
    ".solve._static_adjoint": ("static_displacement",),
    ".solve.coupling._syncavoid": ("SyncAvoiding", "simulate_sync_avoiding"),
    ".solve._zero_pressure": ("ZeroPressureGeometry", "zero_pressure_geometry", "zero_pressure_points"),
    ".io.trajectory": ("PartHistory", "Result", "Trajectory"),
})

if TYPE_CHECKING:
    from .cases import (
        DEFAULT_WAVEFORM,
        cantilever,
        coronary,
        coronary_mesh,
        coronary_waveform,
        vessel_centerline,
        vessel_mesh,
    )
    from .errors import (
        CheckpointError,
        ConfigError,
        ConvergenceError,
        JaxsyncError,
        MaterialError,
        MeshError,
        OutputError,
        PartitionError,
        PrecisionError,
        ProblemError,
        StabilityError,
        SynchronizedRunWarning,
    )
    from .fem._loads import BodyForce, Constant, Periodic, Pressure, Ramp, StepOff, Traction
    from .fem._problem import Dirichlet, LockingWarning, Problem
    from .fem._rigid_body import RigidBodyWarning
    from .fem._timestep import MassScalingWarning, StableStep, cfl_dt, mass_scaling, max_stable_dt, stable_step
    from .fem.forces._support import ElasticSupport
    from .fem.forces._total_lagrangian import TotalLagrangian, check_stable_dt, inverted_elements, stable_dt
    from .fem.materials._hyperelastic import (
        HolzapfelGasserOgden,
        NearlyIncompressibleNeoHookean,
        NeoHookean,
        helical_fibres,
    )
    from .fem.materials._linear_elastic import LinearElastic
    from .fem.materials._prestress import Prestressed
    from .io.trajectory import PartHistory, Result, Trajectory
    from .mesh import Mesh, MeshWarning, box_beam, merge_coincident_nodes, read_mesh
    from .parallel import devices
    from .parallel._partitioning import Partition, partition
    from .run_stats import FullSystemStats, RunStats, SyncAvoidingStats, SynchronizedStats
    from .solve._ensemble import ensemble
    from .solve._full_system import simulate_full_system
    from .solve._members import Members
    from .solve._prestress import PrestressResult, prestress
    from .solve._solver import SteadyState, simulate, steady_state
    from .solve._static_adjoint import static_displacement
    from .solve._strategies import (
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
    )
    from .solve._zero_pressure import ZeroPressureGeometry, zero_pressure_geometry, zero_pressure_points
    from .solve.coupling import Synchronized
    from .solve.coupling._syncavoid import SyncAvoiding, simulate_sync_avoiding
