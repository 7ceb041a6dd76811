"""The elastodynamic problem: mesh, material, boundary conditions, loads, damping, ICs.

A :class:`Problem` is immutable; derive variants with :meth:`Problem.replace`. The
material-independent FE operators are assembled once per mesh and carried along by
``replace`` as long as the mesh is the same object, so that changing the material,
loads or damping (for instance with JAX tracers, to differentiate) costs no reassembly.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import ProblemError
from ..pytree import is_traced
from .assembly import UnitOperators, assemble_unit_operators, body_force_vectors, pressure_vector
from .loads import BodyForce, Pressure, Ramp, StepOff
from .material import LinearElastic
from .mesh import Mesh, box_beam

__all__ = ["Dirichlet", "Problem", "cantilever"]


@dataclasses.dataclass(frozen=True, eq=False)
class Dirichlet:
    """Prescribed displacement on a set of nodes.

    Attributes:
        where: a facet-set name of the mesh, or a predicate ``f(points (n, 3)) -> (n,) bool``.
        value: (3,) prescribed displacement [cm] (default zero; constant in time).
        components: which components (0=x, 1=y, 2=z) are prescribed.
    """

    where: str | Callable[[np.ndarray], np.ndarray]
    value: Sequence[float] = (0.0, 0.0, 0.0)
    components: Sequence[int] = (0, 1, 2)

    def nodes(self, mesh: Mesh) -> np.ndarray:
        """Indices of the constrained nodes of ``mesh``."""
        if isinstance(self.where, str):
            return mesh.facet_nodes(self.where)
        if callable(self.where):
            return mesh.nodes_where(self.where)
        raise ProblemError(f"Dirichlet.where must be a facet-set name or a predicate, got {self.where!r}")


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """Linear elastodynamics M d'' + alpha M d' + K d = f(t) on a tetrahedral mesh.

    Attributes:
        mesh: the mesh.
        material: :class:`LinearElastic` (fields may be JAX tracers).
        dirichlet: prescribed displacements; later entries override earlier ones.
        loads: :class:`BodyForce` and :class:`Pressure` terms, summed.
        damping: mass-proportional damping coefficient alpha [1/s] (C = alpha M).
        initial_displacement: (n_nodes, 3) [cm] or None (zero).
        initial_velocity: (n_nodes, 3) [cm/s] or None (zero).
        density_scale: (n_elements,) element density relative to ``material.rho`` (set
            by artificial mass scaling), or None (uniform).
        operators: assembled unit operators (computed when not given or stale).
    """

    mesh: Mesh
    material: LinearElastic = LinearElastic()
    dirichlet: tuple = ()
    loads: tuple = ()
    damping: Any = 0.0
    initial_displacement: Any = None
    initial_velocity: Any = None
    density_scale: Any = None
    operators: UnitOperators | None = dataclasses.field(default=None, repr=False)

    def __post_init__(self):
        if not isinstance(self.mesh, Mesh):
            raise ProblemError(f"Problem.mesh must be a jaxsync.Mesh, got {type(self.mesh).__name__}")
        if not isinstance(self.material, LinearElastic):
            raise ProblemError("Problem.material must be a jaxsync.LinearElastic")
        object.__setattr__(self, "dirichlet", tuple(self.dirichlet))
        object.__setattr__(self, "loads", tuple(self.loads))
        for load in self.loads:
            if not isinstance(load, (BodyForce, Pressure)):
                raise ProblemError(f"unknown load {load!r}: use jaxsync.BodyForce or jaxsync.Pressure")
            if isinstance(load, Pressure):
                self.mesh.facet_set(load.surface)  # clear error for an unknown tag
        if not is_traced(self.damping) and not float(self.damping) >= 0:
            raise ProblemError(f"damping alpha must be >= 0, got {self.damping}")
        n = self.mesh.n_nodes
        for name in ("initial_displacement", "initial_velocity"):
            value = getattr(self, name)
            if value is not None and np.shape(value) != (n, 3):
                raise ProblemError(f"{name} must have shape ({n}, 3), got {np.shape(value)}")
        if self.density_scale is not None:
            scale = np.asarray(self.density_scale, dtype=float)
            if scale.shape != (self.mesh.n_elements,) or not np.all(scale > 0):
                raise ProblemError("density_scale must hold one positive factor per element, "
                                   f"shape ({self.mesh.n_elements},)")
        if self.operators is None or self.operators.mesh is not self.mesh:
            object.__setattr__(self, "operators", assemble_unit_operators(self.mesh))
        self.dirichlet_dofs()  # validate eagerly

    def replace(self, **changes) -> "Problem":
        """A copy with some fields changed (operators are reused for the same mesh)."""
        return dataclasses.replace(self, **changes)

    @property
    def dt(self):
        """The default time step [s]: the paper's CFL step, or alpha_s times the exact
        stability bound where that is smaller (nearly incompressible materials); see
        :attr:`time_step` for which rule set it and :func:`jaxsync.fem.timestep.stable_step`."""
        return self.time_step.dt

    @property
    def time_step(self):
        """The default step with its rule and both bounds
        (:class:`jaxsync.fem.timestep.StableStep`)."""
        from .timestep import stable_step

        return stable_step(self)

    def dirichlet_dofs(self) -> tuple[np.ndarray, np.ndarray]:
        """(dofs (k,) int64 sorted, values (k,) float64) of all prescribed dofs."""
        values = np.full(self.mesh.n_dofs, np.nan)
        for bc in self.dirichlet:
            if not isinstance(bc, Dirichlet):
                raise ProblemError(f"Problem.dirichlet entries must be jaxsync.Dirichlet, got {bc!r}")
            nodes = bc.nodes(self.mesh)
            if len(nodes) == 0:
                raise ProblemError(f"Dirichlet condition {bc.where!r} selects no node; "
                                   "check the predicate or facet-set name")
            comps = [int(c) for c in bc.components]
            if any(c not in (0, 1, 2) for c in comps):
                raise ProblemError(f"Dirichlet components must be among 0, 1, 2, got {comps}")
            value = np.broadcast_to(np.asarray(bc.value, dtype=float), (3,))
            for c in comps:
                values[3 * nodes + c] = value[c]
        dofs = np.flatnonzero(~np.isnan(values))
        return dofs, values[dofs]

    def load_vectors(self) -> tuple[list, list]:
        """Spatial parts and time functions of the loads.

        Returns ``(vectors, times)``: ``vectors[l]`` is the (n_nodes, 3) nodal load of
        load l at full magnitude (a JAX or NumPy array, traced if the magnitude is) and
        ``times[l]`` its time function.
        """
        import jax.numpy as jnp

        vectors, times = [], []
        unit_body = None
        for load in self.loads:
            if isinstance(load, BodyForce):
                if unit_body is None:
                    unit_body = body_force_vectors(self.mesh)
                vec = jnp.einsum("dnc,d->nc", unit_body, jnp.asarray(load.vector, dtype=float))
            else:
                vec = load.magnitude * jnp.asarray(pressure_vector(self.mesh, load.surface))
            vectors.append(vec)
            times.append(load.time)
        return vectors, times

    def lumped_mass(self):
        """(n_nodes,) lumped nodal mass [g] (rho times the unit lumped mass)."""
        from .assembly import lumped_mass

        return self.material.rho * lumped_mass(self.mesh, self.density_scale)

    def summary(self) -> str:
        """A few lines describing the problem."""
        dofs, _ = self.dirichlet_dofs()
        m = self.material
        try:
            step = self.time_step.describe()
        except ProblemError:  # traced nu
            step = "time step: traced"
        return (f"{self.mesh!r}\n"
                f"material: E={m.E} dyn/cm^2, nu={m.nu}, rho={m.rho} g/cm^3; damping alpha={self.damping} 1/s\n"
                f"Dirichlet dofs: {len(dofs)}; loads: {len(self.loads)}; {step}")


def cantilever(mesh: Mesh | None = None, *, body_force=(0.0, 0.0, -0.5), damping=0.5,
               t_ramp: float = 1.0, t_off: float | None = None,
               material: LinearElastic | None = None, initial_displacement=None,
               initial_velocity=None) -> Problem:
    """The paper's cantilever (Table 1): 25 x 1 x 1 cm beam clamped at x = 0.

    E = 1e6 dyn/cm^2, nu = 0.3, rho = 1 g/cm^3, body force (0, 0, -0.5) dyn/cm^3 ramped
    over ``t_ramp`` s, damping alpha = 0.5 1/s, zero initial conditions. The default mesh
    is the coarse :func:`box_beam` (104 nodes, 150 tetrahedra). Variants: skewed load
    ``body_force=(0, -0.5, -0.5)``; load switched off at ``t_off``; initial conditions.
    The clamp is every node with x equal to the mesh's smallest x.
    """
    mesh = box_beam() if mesh is None else mesh
    material = LinearElastic(1.0e6, 0.3, 1.0) if material is None else material
    x0 = float(mesh.points[:, 0].min())
    tol = 1e-8 * float(np.ptp(mesh.points[:, 0]))
    clamp = Dirichlet(where=lambda p: np.abs(p[:, 0] - x0) <= tol)
    time = Ramp(t_ramp) if t_off is None else StepOff(t_off, Ramp(t_ramp))
    return Problem(mesh=mesh, material=material, dirichlet=(clamp,),
                   loads=(BodyForce(body_force, time),), damping=damping,
                   initial_displacement=initial_displacement, initial_velocity=initial_velocity)
