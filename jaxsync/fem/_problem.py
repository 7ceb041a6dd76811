"""The elastodynamic problem: mesh, material, boundary conditions, loads, damping, ICs.

A :class:`Problem` is immutable; derive variants with :meth:`Problem.replace`. The
material-independent FE operators are assembled once per mesh and carried along by
``replace`` as long as the mesh is the same object, so that changing the material,
loads or damping (for instance with JAX tracers, to differentiate) costs no reassembly.
What a run reads of a problem (lumped mass, nodal loads, prescribed values, damping) is
lowered once per problem, on first use, into :attr:`Problem.discrete`.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import ProblemError
from ..mesh import Mesh
from ..options import Element
from ..pytree import is_traced
from ._assembly import UnitOperators, assemble_unit_operators, body_force_vectors, pressure_vector, traction_vectors
from ._loads import LOADS, BodyForce, Pressure, TimeFunction, Traction
from ._parameter_checks import check_finite_array, check_number
from .forces._support import ElasticSupport
from .materials._law import check_material_law
from .materials._linear_elastic import LinearElastic

__all__ = ["Dirichlet", "Problem", "LockingWarning", "LOCKING_NU"]


@dataclasses.dataclass(frozen=True, eq=False)
class Dirichlet:
    """Prescribed displacement on a set of nodes.

    Attributes:
        where: a facet-set name of the mesh, or a predicate ``f(points (n, 3)) -> (n,) bool``.
        value: (3,) prescribed displacement [cm] (default zero).
        components: which components (0=x, 1=y, 2=z) are prescribed.
        time: None (the value holds at every step), or a time function g(t)
            (:mod:`jaxsync.fem`): the displacement ``value * g(t)``, a prescribed
            history (an inflow boundary driven by a measured motion, say). The run starts
            consistent with it: before the first step the prescribed dofs sit at
            ``value * g(-dt)``, so that the discrete velocity and acceleration at t = 0 are
            those of the history. With a time function, ``value`` may be a JAX tracer
            (differentiable).
    """

    where: str | Callable[[np.ndarray], np.ndarray]
    value: tuple[float, float, float] | Any = (0.0, 0.0, 0.0)
    components: Sequence[int] = (0, 1, 2)
    time: TimeFunction | None = None

    def __post_init__(self):
        if not isinstance(self.where, str) and not callable(self.where):
            raise ProblemError(f"Dirichlet.where must be a facet-set name or a predicate, got {self.where!r}")
        check_finite_array(self.value, "Dirichlet.value [cm]", length=3)
        if not is_traced(self.value) and np.shape(self.value) not in ((), (3,)):
            raise ProblemError(f"Dirichlet.value must have 3 components (x, y, z) [cm] or be one number for all, got "
                               f"shape {np.shape(self.value)}")
        try:
            comps = [int(c) for c in np.atleast_1d(np.asarray(self.components))]
        except (TypeError, ValueError):
            comps = None
        if comps is None or not comps or any(c not in (0, 1, 2) for c in comps):
            raise ProblemError(f"Dirichlet.components must be among 0, 1, 2 (x, y, z), got {self.components!r}")
        if self.time is not None and not isinstance(self.time, TimeFunction):
            raise ProblemError(f"Dirichlet.time must be a time function (jaxsync.Ramp, Periodic...), "
                               f"got {self.time!r}")

    def nodes(self, space) -> np.ndarray:
        """Indices of the constrained nodes of a :class:`~jaxsync.fem.FunctionSpace`
        (or of a mesh's vertices): a facet set's nodes (with P2, its edge nodes too), or
        those whose coordinates satisfy the predicate."""
        if isinstance(self.where, str):
            return space.facet_nodes(self.where)
        if callable(self.where):
            return space.nodes_where(self.where)
        raise ProblemError(f"Dirichlet.where must be a facet-set name or a predicate, got {self.where!r}")


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """Linear elastodynamics M d'' + C d' + K d = f(t) on a tetrahedral mesh.

    Attributes:
        mesh: the mesh.
        material: :class:`LinearElastic` (fields may be JAX tracers), or a hyperelastic law
            (:class:`jaxsync.NeoHookean`, :class:`jaxsync.NearlyIncompressibleNeoHookean`,
            :class:`jaxsync.HolzapfelGasserOgden`): the problem is then one of finite
            strain, M d'' + C d' + f_int(d) = f(t), and every solver computes f_int by the
            total-Lagrangian model (:mod:`jaxsync.fem.forces`) whatever its
            ``mode``: the linear modes have no stiffness of a nonlinear law to store. The
            default step (:attr:`dt`) is that of the law's tangent at rest (the initial
            displacement); a run checks its deformed states between chunks
            (:class:`jaxsync.fem.RunCheck`). Any law implementing
            :class:`jaxsync.fem.materials.MaterialLaw` (a finite-strain law of your own
            deriving from :class:`jaxsync.fem.materials.FiniteStrainLaw`) runs so too.
        element: ``"P1"`` (linear tetrahedra) or ``"P2"`` (quadratic: a node at every
            edge too, :mod:`jaxsync.fem`); default ``"P2"`` on a quadratic
            (``tetra10``) mesh, ``"P1"`` otherwise. Fields are (n_nodes, 3) on the
            element's nodes (:attr:`points`).
        dirichlet: prescribed displacements (:class:`Dirichlet`, constant or following a
            time function); later entries override earlier ones.
        loads: :class:`BodyForce`, :class:`Pressure` and :class:`Traction` terms, summed.
        damping: mass-proportional damping coefficient alpha [1/s] (C = alpha M + beta K
            + the supports' dashpots).
        stiffness_damping: stiffness-proportional damping coefficient beta [s] (Rayleigh
            damping C = alpha M + beta K; default 0). A mode of frequency omega decays at
            the rate (alpha + beta omega^2) / 2: beta damps the fast modes. The explicit
            step takes the damping force beta K v from the backward velocity
            v = (d(n) - d(n-1)) / dt (a hyperelastic law: beta times its tangent applied
            to v, :mod:`jaxsync.fem`), which lowers the stable step to
            sqrt((2 / omega_max)^2 + beta^2) - beta (:func:`jaxsync.fem.damped_bound`;
            the default :attr:`dt` follows it). May be a JAX tracer (differentiable).
        supports: :class:`jaxsync.ElasticSupport` terms (spring-dashpot supports on facet
            sets: :mod:`jaxsync.fem.forces`).
        initial_displacement: (n_nodes, 3) [cm] or None (zero), on :attr:`points`.
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
    supports: tuple = ()
    element: Element | None = None
    stiffness_damping: Any = 0.0
    operators: UnitOperators | None = dataclasses.field(default=None, repr=False)

    def __post_init__(self):
        if not isinstance(self.mesh, Mesh):
            raise ProblemError(f"Problem.mesh must be a jaxsync.Mesh, got {type(self.mesh).__name__}")
        check_material_law(self.material)
        for name in ("dirichlet", "loads", "supports"):  # one entry given alone counts as a list of one
            value = getattr(self, name)
            object.__setattr__(self, name, (value,) if isinstance(value, (Dirichlet, ElasticSupport) + LOADS)
                               else tuple(value))
        for load in self.loads:
            if not isinstance(load, LOADS):
                raise ProblemError(f"unknown load {load!r}: use jaxsync.BodyForce, jaxsync.Pressure or "
                                   "jaxsync.Traction")
            if isinstance(load, (Pressure, Traction)):
                self.mesh.facet_set(load.surface)  # clear error for an unknown tag
            if isinstance(load, Pressure) and load.follower and not self.material.finite_strain:
                raise ProblemError(
                    f"the follower pressure on {load.surface!r} acts on the deformed surface, a finite-strain "
                    f"effect, but the material is the small-strain {type(self.material).__name__}: use a "
                    "hyperelastic law (jaxsync.NeoHookean(E, nu, rho) linearises to LinearElastic(E, nu, rho)), "
                    "or Pressure(..., follower=False) for the dead load on the reference surface")
        for support in self.supports:
            if not isinstance(support, ElasticSupport):
                raise ProblemError(f"unknown support {support!r}: use jaxsync.ElasticSupport")
            self.mesh.facet_set(support.surface)
        check_number(self.damping, "Problem.damping (mass-proportional alpha)", at_least=0.0, unit="1/s")
        check_number(self.stiffness_damping, "Problem.stiffness_damping (stiffness-proportional beta)", at_least=0.0,
                     unit="s", hint="give beta >= 0 (0: no stiffness-proportional damping)")
        from ._space import function_space

        if self.element is None:
            object.__setattr__(self, "element", "P1" if self.mesh.mid_nodes is None else "P2")
        function_space(self.mesh, self.element)  # checks the element
        _warn_about_locking(self)
        n = self.n_nodes
        for name in ("initial_displacement", "initial_velocity"):
            value = getattr(self, name)
            if value is not None and np.shape(value) != (n, 3):
                raise ProblemError(f"{name} must have shape ({n}, 3), got {np.shape(value)}")
            if value is not None:
                check_finite_array(value, f"Problem.{name}")
        if self.density_scale is not None:
            scale = np.asarray(self.density_scale, dtype=float)
            if scale.shape != (self.mesh.n_elements,) or not np.all(scale > 0):
                raise ProblemError("density_scale must hold one positive factor per element, "
                                   f"shape ({self.mesh.n_elements},)")
        if (self.operators is None or self.operators.mesh is not self.mesh
                or self.operators.space is not self.space):
            object.__setattr__(self, "operators", assemble_unit_operators(self.space))
        self.dirichlet_owner()  # validate eagerly
        from ._rigid_body import warn_about_free_motion

        warn_about_free_motion(self, stacklevel=4)

    @property
    def space(self):
        """The :class:`~jaxsync.fem.FunctionSpace` of the solution nodes."""
        from ._space import function_space

        return function_space(self.mesh, self.element)

    @property
    def points(self) -> np.ndarray:
        """(n_nodes, 3) coordinates of the solution nodes [cm]: the mesh's vertices, then
        (P2) the edge nodes."""
        return self.space.points

    @property
    def n_nodes(self) -> int:
        """Solution nodes (the mesh's vertices for P1; vertices and edges for P2)."""
        return self.space.n_nodes

    @property
    def n_dofs(self) -> int:
        return 3 * self.n_nodes

    def replace(self, **changes) -> "Problem":
        """A copy with some fields changed (operators are reused for the same mesh)."""
        return dataclasses.replace(self, **changes)

    @property
    def dt(self):
        """The default time step [s]: the paper's CFL step, or alpha_s times the exact
        stability bound where that is smaller (nearly incompressible materials); see
        :attr:`time_step` for which rule set it and :func:`jaxsync.fem.stable_step`.
        A hyperelastic law: its force model's step at rest, alpha_s times the smaller of
        the element eigenvalue rule and the exact bound of its tangent stiffness
        (:func:`jaxsync.fem.forces.default_step`: the HGO fibres included)."""
        return self.time_step.dt

    @property
    def stiffness_damped(self) -> bool:
        """Whether the problem has stiffness-proportional damping: ``stiffness_damping``
        is not a concrete zero (a traced beta counts, so that its gradient flows)."""
        from ..pytree import concrete_scalar

        return concrete_scalar(self.stiffness_damping) != 0.0

    @property
    def time_step(self):
        """The default step with its rule and both bounds
        (:class:`jaxsync.fem.StableStep`)."""
        from ._timestep import stable_step

        return stable_step(self)

    def element_steps(self) -> np.ndarray:
        """(n_elements,) each element's own stable step [s] (alpha_s = 1), as its material
        law computes it (:meth:`jaxsync.fem.materials.MaterialLaw.element_steps`) and
        :func:`jaxsync.mass_scaling` scales them: for a hyperelastic law at the initial
        displacement, 2 / omega_e, omega_e^2 the largest eigenvalue of the element's
        tangent stiffness over its lumped mass (density scaling included;
        :func:`jaxsync.fem.forces.element_frequencies`); for the linear law the
        paper's CFL step h_e / c_e of each P1 element (:func:`jaxsync.fem.element_dt`).

        Raises:
            ProblemError: a linear law on P2 elements, or a hyperelastic law with traced
                parameters.
        """
        return self.material.element_steps(self)

    @functools.cached_property
    def discrete(self):
        """The problem lowered to the arrays the solver reads
        (:class:`~jaxsync.fem.DiscreteProblem`: lumped mass, nodal loads,
        prescribed dofs and values, damping), computed on first use and kept: every
        consumer (the explicit system, the parts' systems, the error estimate, the
        stability bounds, a checkpoint's fingerprint and the accessors below) reads it."""
        from ._discrete import lower

        return lower(self)

    def dirichlet_dofs(self) -> tuple[np.ndarray, np.ndarray]:
        """(dofs (k,) int64 sorted, values (k,) float64) of all prescribed dofs (a
        condition with a time function at its full ``value``, time factor 1)."""
        return self.discrete.dirichlet_dofs()

    def prescribed(self) -> tuple[np.ndarray, np.ndarray, list]:
        """The prescribed displacements as the stepper applies them: (mask (n_nodes, 3)
        bool, constant values (n_nodes, 3) [cm], and per condition with a time function a
        pair (its values (n_nodes, 3) on the dofs it prescribes [cm], a JAX array when
        traced; its time function))."""
        d = self.discrete
        moving = [] if d.moving is None else list(zip(d.moving, d.moving_times))
        return d.fixed, d.fixed_values, moving

    def dirichlet_owner(self) -> np.ndarray:
        """(n_dofs,) index of the condition that prescribes each dof (the last one that
        names it), -1 for free dofs; checks each condition (its nodes, components, time
        function).

        Raises:
            ProblemError: a condition that selects no node, or with a bad component or
                time function."""
        owner = np.full(self.n_dofs, -1, dtype=np.int64)
        for k, bc in enumerate(self.dirichlet):
            if not isinstance(bc, Dirichlet):
                raise ProblemError(f"Problem.dirichlet entries must be jaxsync.Dirichlet, got {bc!r}")
            nodes = bc.nodes(self.space)
            if len(nodes) == 0:
                raise ProblemError(f"Dirichlet condition {bc.where!r} selects no node; "
                                   "check the predicate or facet-set name")
            comps = [int(c) for c in bc.components]
            if any(c not in (0, 1, 2) for c in comps):
                raise ProblemError(f"Dirichlet components must be among 0, 1, 2, got {comps}")
            if bc.time is not None and not isinstance(bc.time, TimeFunction):
                raise ProblemError(f"Dirichlet time must be a time function (jaxsync.Ramp, Periodic...), "
                                   f"got {bc.time!r}")
            if bc.time is None and is_traced(bc.value):
                raise ProblemError("a traced Dirichlet value needs a time function (time=jaxsync.Constant() "
                                   "for a constant one): constant conditions are applied as numbers")
            for c in comps:
                owner[3 * nodes + c] = k
        return owner

    def load_vectors(self) -> tuple[list, list]:
        """Spatial parts and time functions of the loads.

        Returns ``(vectors, times)``: ``vectors[l]`` is the (n_nodes, 3) nodal load of
        load l at full magnitude (a JAX or NumPy array, traced if the magnitude is) and
        ``times[l]`` its time function. Follower pressures, whose forces depend on the
        displacement, are not among them (:mod:`jaxsync.fem.forces`).
        """
        d = self.discrete
        return list(d.load_vectors), list(d.load_times)

    def load_vector(self, load):
        """(n_nodes, 3) nodal force of one load of this problem's kind at full magnitude,
        on the reference configuration (for a follower pressure: its forces at rest): a
        NumPy array, or a JAX array where the load's vector or magnitude is traced."""
        import jax.numpy as jnp

        derived = self.operators.derived
        if isinstance(load, BodyForce):
            unit = derived("body force", None, lambda: body_force_vectors(self.space))
        elif isinstance(load, Traction):
            unit = derived("traction", load.surface, lambda s=load.surface: traction_vectors(self.space, s))
        else:
            unit = derived("pressure", load.surface, lambda s=load.surface: pressure_vector(self.space, s))
            return load.magnitude * (jnp.asarray(unit) if is_traced(load.magnitude) else unit)
        if is_traced(load.vector):
            return jnp.einsum("dnc,d->nc", unit, jnp.asarray(load.vector, dtype=float))
        import jax

        with jax.ensure_compile_time_eval():  # a concrete load stays concrete inside a traced function
            return np.asarray(jnp.einsum("dnc,d->nc", unit, jnp.asarray(load.vector, dtype=float)))

    def lumped_mass(self):
        """(n_nodes,) lumped nodal mass [g] (rho times the unit lumped mass, density
        scaling included)."""
        return self.discrete.mass

    def summary(self, dt=None) -> str:
        """A few lines describing the problem; ``dt``: the step a run uses instead of the
        default [s], named in the last line."""
        dofs, _ = self.dirichlet_dofs()
        m = self.material
        try:
            step = self.time_step.describe(dt)
        except ProblemError:  # traced nu
            step = "time step: traced"
        moving = sum(bc.time is not None for bc in self.dirichlet)
        kinds = ", ".join(f"{n} {name}" for name, n in (
            ("body force", sum(isinstance(x, BodyForce) for x in self.loads)),
            ("pressure", sum(isinstance(x, Pressure) and not x.follower for x in self.loads)),
            ("follower pressure", sum(isinstance(x, Pressure) and x.follower for x in self.loads)),
            ("traction", sum(isinstance(x, Traction) for x in self.loads))) if n)
        supports = "".join(f"; elastic support on {s.surface!r} (k_s {s.stiffness} dyn/cm^3, c_s {s.damping} "
                           f"dyn s/cm^3{', normal only' if s.normal_only else ''})" for s in self.supports)
        element = (f"; quadratic (P2) elements, {self.n_nodes} nodes"
                   f"{' (isoparametric)' if self.space.curved else ''}" if self.element == "P2" else "")
        return (f"{self.mesh!r}{element}\n"
                f"material: E={m.E} dyn/cm^2, nu={m.nu}, rho={m.rho} g/cm^3; damping alpha={self.damping} 1/s"
                + (f", beta={self.stiffness_damping} s" if self.stiffness_damped else "") + "\n"
                f"Dirichlet dofs: {len(dofs)}" + (f" ({moving} condition{'s' if moving > 1 else ''} following a "
                                                  "time function)" if moving else "")
                + f"; loads: {len(self.loads)}" + (f" ({kinds})" if kinds else "") + supports + f"; {step}")


LOCKING_NU = 0.45
"""From this Poisson ratio on, a P1 problem warns (:class:`LockingWarning`)."""


class LockingWarning(UserWarning):
    """Linear tetrahedra on a nearly incompressible material: the displacements come out
    too small (volumetric locking); quadratic tetrahedra (``element="P2"``) are the remedy
    (measured in ``benchmarks/bench_locking.py``)."""


def _warn_about_locking(problem: "Problem") -> None:
    nu = problem.material.nu
    if problem.element == "P1" and not is_traced(nu) and float(nu) >= LOCKING_NU:
        warnings.warn(f"linear (P1) tetrahedra lock as nu -> 0.5 (nu = {float(nu):g}): displacements come out too "
                      "small, by tens of percent from nu = 0.49 on; quadratic tetrahedra lock far less: use "
                      "element='P2' (jaxsync simulate --element P2, [problem] element = \"P2\")",
                      LockingWarning, stacklevel=4)

