"""Total-Lagrangian explicit dynamics (TLED): the internal force of a hyperelastic law.

Everything is referred to the reference configuration (Miller et al. 2007): with the
shape-function gradients grad N_a of the reference element and u the nodal displacements,

    F = I + sum_a u_a (x) grad N_a,    f_a = sum_q w_q P(F_q) grad N_a(x_q)    [dyn],

P the first Piola-Kirchhoff stress of the law (:mod:`jaxsync.fem.materials`) and w_q the
quadrature weights times the reference Jacobian [cm^3]: one point for P1 (F is constant in
the element), the 4-point degree-2 rule for P2 (shape functions and the rule from
scikit-fem). The reference gradients and weights are formed once, when the operator is
built (TLED's precomputation); each step gathers u, forms F and P at every point and sums
the element forces at the nodes (``segment_sum``). The same code serves the whole mesh
and, padded, every part of a partition (:class:`TotalLagrangian`, the physics seam of
:mod:`jaxsync.fem.forces`).

Stable step. The explicit step of a nonlinear law changes as the body deforms, so it is
checked during a run on the current state (:func:`stable_dt`, :func:`check_stable_dt`):

* ``rule="cfl"`` (P1, the default there): alpha_s min_e h_e / c_e with h_e = 2 (shortest
  edge) / sqrt(24) of the DEFORMED element (the paper's code's size rule) and c_e the
  fastest plane wave of the current tangent: c^2 = max over unit n of the largest
  eigenvalue of the acoustic tensor q_ik(n) = a_ijkl n_j n_l / rho_0 with
  a_ijkl = F_jJ F_lL A_iJkL (A = dP/dF): at F = I it is (lam + 2 mu) / rho;
* ``rule="element"`` (the default for P2, whose nodes the paper's size rule does not
  describe): alpha_s min_e 2 / omega_e with omega_e^2 the largest eigenvalue of the element's
  tangent stiffness over its lumped mass; the assembled omega_max never exceeds the
  largest omega_e (Irons' element eigenvalue bound), so this step is never above the exact
  bound 2 / omega_max. It includes the geometric (stress) stiffness.

:func:`inverted_elements` lists the elements with J = det F <= 0 at a quadrature point.
:class:`RunCheck` applies both checks to the state of a run between its chunks (the host
executor, :mod:`jaxsync.solve.executors`). :func:`tangent_matrix` assembles the exact tangent
stiffness (the element Hessians of the stored energy) for Newton's method
(:func:`jaxsync.steady_state`).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import ProblemError, StabilityError
from ...pytree import pytree_dataclass
from .._kinematics import determinant
from .._reference_element import element_unit_mass, n_quadrature_points, quadrature_order, reference_geometry
from .._timestep import ALPHA_S, StableStep, element_size, hyperelastic_step

__all__ = ["HyperelasticForce", "TotalLagrangian", "reference_geometry", "stable_dt", "check_stable_dt",
           "exact_stable_dt", "element_wave_speeds", "inverted_elements", "strain_energy",
           "STABLE_STEP_RULES", "element_stiffness", "element_frequencies", "tangent_matrix",
           "default_step", "quadrature_order", "n_quadrature_points"]

STABLE_STEP_RULES = ("cfl", "element")
"""The rules of :func:`stable_dt` (module docstring)."""


@pytree_dataclass
class HyperelasticForce:
    """The internal force f_int(u) of a hyperelastic law on reference elements (a pytree).

    Attributes:
        cells: (n_elements, k) int32 each element's nodes (k = 4 for P1, 10 for P2).
        gradients: (n_elements, n_q, k, 3) reference shape-function gradients at the
            quadrature points [1/cm].
        weights: (n_elements, n_q) quadrature weight times the reference Jacobian [cm^3]
            (0 on the padding elements of a part).
        material: the law (:mod:`jaxsync.fem.materials`; fibres held here, not in it).
        fibres: (n_elements, 2, 3) reference fibre directions, or None (isotropic laws).
        points: (n_nodes, 3) reference node coordinates [cm] (for the deformed element size).
        unit_mass: (n_elements, k) each element's lumped mass at its nodes per unit
            density [cm^3] (density scaling included; P1 V/4, P2 HRZ).
        state: a law with constant internal variables (a prestress,
            :class:`jaxsync.Prestressed`): {name: (n_elements, n_q, ...)}, the state every
            stress of this operator is computed with (``stress_update``); None otherwise.

    A part's operator (:meth:`TotalLagrangian.part_operators`) has a leading part axis on
    every leaf (the material's too) and is used one part at a time (under ``vmap`` or
    ``shard_map``).
    """

    cells: Any
    gradients: Any
    weights: Any
    material: Any
    fibres: Any
    points: Any
    unit_mass: Any
    state: Any = None

    def gradient(self, u):
        """(n_elements, n_q, 3, 3) grad u = du_i/dX_J at the quadrature points of a nodal
        field u (n_nodes, 3) (displacements [cm] -> [1]; velocities [cm/s] -> F-dot [1/s])."""
        ue = u[self.cells]
        # a sum of k broadcast products, not an einsum: XLA:CPU fuses it into one loop, while
        # the einsum's batched 3 x k x 3 products ran 5x slower (P2, 60 000 elements: 50 -> 10 ms)
        return sum(ue[:, a, None, :, None] * self.gradients[:, :, a, None, :] for a in range(ue.shape[1]))

    def deformation_gradient(self, u):
        """(n_elements, n_q, 3, 3) F = I + grad u at the quadrature points of u (n_nodes, 3) [cm]."""
        grad_u = self.gradient(u)
        return grad_u + jnp.eye(3, dtype=grad_u.dtype)[None, None]

    def viscous_stress(self, F, velocity, beta):
        """(n_elements, n_q, 3, 3) the stiffness-proportional damping stress beta dP/dF[F-dot]
        [dyn/cm^2] at F (n_elements, n_q, 3, 3): the law's tangent applied to the rate
        F-dot = grad v of the velocity v (n_nodes, 3) [cm/s] (a ``jax.jvp`` of its
        ``first_piola``, the instantaneous response of a law with internal variables), beta
        [s]. Its nodal forces are beta K_T(u) v without any global tangent."""
        return beta * self._stress_and_rate(F, velocity)[1]

    def _stress_and_rate(self, F, velocity):
        """(P(F), dP/dF[grad v]) of one ``jax.jvp`` of the law's ``first_piola``."""
        fibres = self.fibres_at_points()
        return jax.jvp(lambda G: self.material.first_piola(G, fibres), (F,), (self.gradient(velocity),))

    def fibres_at_points(self):
        """(n_elements, 1, 2, 3) the fibres broadcast over the quadrature points, or None."""
        return None if self.fibres is None else self.fibres[:, None]

    def element_forces(self, u):
        """(n_elements, k, 3) each element's nodal forces [dyn]."""
        return self._nodal_forces(self.stress(self.deformation_gradient(u)))

    def stress(self, F):
        """(n_elements, n_q, 3, 3) P [dyn/cm^2] at the quadrature points' F: the law's
        ``first_piola``, or its ``stress_update`` with the constant :attr:`state`."""
        if self.state is None:
            return self.material.first_piola(F, self.fibres_at_points())
        return self.material.stress_update(F, self.fibres_at_points(), self.state, 0.0)[0]

    def _nodal_forces(self, P):
        """(n_elements, k, 3) sum_q w_q P_q grad N_a [dyn] of P (n_elements, n_q, 3, 3)."""
        # an einsum here (a sum of k products would be fused with P and recompute it k times)
        return jnp.einsum("mqij,mqkj->mki", P * self.weights[:, :, None, None], self.gradients)

    def _assembled(self, forces, n_nodes: int):
        return jax.ops.segment_sum(forces.reshape(-1, 3), self.cells.reshape(-1), num_segments=n_nodes)

    def matvec(self, u):
        """f_int(u) (n_nodes, 3) [dyn] of displacements u (n_nodes, 3) [cm]."""
        return self._assembled(self.element_forces(u), u.shape[0])

    def damped_matvec(self, u, velocity, beta):
        """f_int(u) + beta K_T(u) v (n_nodes, 3) [dyn]: the internal force of u plus the
        stiffness-proportional damping force of the velocity v (n_nodes, 3) [cm/s], beta
        [s], summed in one element kernel (P + :meth:`viscous_stress` at each point)."""
        P, rate = self._stress_and_rate(self.deformation_gradient(u), velocity)
        return self._assembled(self._nodal_forces(P + beta * rate), u.shape[0])

    def update(self, u, internal, dt, velocity=None, beta=None):
        """(f_int(u) (n_nodes, 3) [dyn], the law's internal variables after it) of a law
        with state: its ``stress_update`` at every quadrature point
        (:meth:`jaxsync.fem.materials.FiniteStrainLaw.stress_update`), ``internal``
        {name: (n_elements, n_q, ...)} its variables before, dt [s] the step. With a
        ``velocity`` v (n_nodes, 3) [cm/s] and beta [s], the force includes the
        stiffness-proportional damping force (:meth:`viscous_stress`, from the law's
        instantaneous tangent)."""
        F = self.deformation_gradient(u)
        P, internal = self.material.stress_update(F, self.fibres_at_points(), internal, dt)
        if velocity is not None:
            P = P + self.viscous_stress(F, velocity, beta)
        return self._assembled(self._nodal_forces(P), u.shape[0]), internal

    def energy(self, u):
        """The stored strain energy sum_e sum_q w_q psi(F_q) [erg] (its gradient in u is f_int)."""
        F, fibres = self.deformation_gradient(u), self.fibres_at_points()
        psi = self.material.energy(F, fibres) if self.state is None else self.material.energy(F, fibres, self.state)
        return jnp.sum(self.weights * psi)

    def jacobians(self, u):
        """(n_elements, n_q) J = det F at the quadrature points."""
        return determinant(self.deformation_gradient(u))


def _material_and_fibres(problem):
    """(the law without its fibres, fibres (n_elements, 2, 3) or None), checked."""
    material = problem.material
    if not material.finite_strain:
        raise ProblemError(f"the total-Lagrangian force model needs a hyperelastic material, got "
                           f"{type(material).__name__}: use jaxsync.NeoHookean(E, nu, rho) (the finite-strain law "
                           "that linearises to LinearElastic(E, nu, rho)), or mode='preassembled' for the linear law")
    fibres = getattr(material, "fibres", None)
    if not hasattr(material, "fibres"):
        return material, None
    if fibres is None:
        raise ProblemError("HolzapfelGasserOgden needs fibre directions: give fibres= (n_elements, 2, 3), for "
                           "instance jaxsync.helical_fibres(mesh.points[mesh.tets].mean(axis=1), axis, angle)")
    if np.shape(fibres) != (problem.mesh.n_elements, 2, 3):
        raise ProblemError(f"HolzapfelGasserOgden.fibres has shape {np.shape(fibres)}, the mesh has "
                           f"{problem.mesh.n_elements} elements: give (n_elements, 2, 3)")
    return material.replace(fibres=None), jnp.asarray(fibres)


def _constant_state(problem, material):
    """(the law as the operator holds it, its constant state or None)."""
    if not getattr(material, "constant_state", False):
        return material, None
    return material.stateless(), material.internal_variables(problem.mesh.n_elements,
                                                              n_quadrature_points(problem.space))


@dataclasses.dataclass(frozen=True)
class TotalLagrangian:
    """The total-Lagrangian force model of a hyperelastic problem (module docstring), a
    :class:`jaxsync.fem.forces.ForceModel`: ``mode=TotalLagrangian()`` (or
    ``mode="total-lagrangian"``) in :func:`jaxsync.simulate` and every solver.

    A problem with a hyperelastic material needs no ``mode``: the linear modes
    (``"preassembled"``, ``"recompute"``, whose stiffness does not exist for a nonlinear
    law) hand such a problem to this model.
    """

    name: str = dataclasses.field(default="total-lagrangian", init=False)

    def operator(self, problem) -> HyperelasticForce:
        """The :class:`HyperelasticForce` of the whole mesh (the problem's P1 or P2 nodes)."""
        material, fibres = _material_and_fibres(problem)
        material, state = _constant_state(problem, material)
        space = problem.space
        gradients, weights = reference_geometry(space)
        return HyperelasticForce(
            cells=jnp.asarray(space.cells, dtype=jnp.int32), gradients=jnp.asarray(gradients),
            weights=jnp.asarray(weights), material=material, fibres=fibres, points=jnp.asarray(space.points),
            unit_mass=jnp.asarray(element_unit_mass(space, problem.density_scale)), state=state)

    def part_operators(self, problem, parts: Sequence, n_local: int) -> HyperelasticForce:
        """The parts' :class:`HyperelasticForce` stacked on a leading part axis: elements
        padded to the largest part (padding repeats the part's element 0 with weight 0),
        nodes to ``n_local``; the material's parameters broadcast to every part."""
        material, fibres = _material_and_fibres(problem)
        material, state = _constant_state(problem, material)
        space = problem.space
        gradients, weights = reference_geometry(space)
        unit_mass = element_unit_mass(space, problem.density_scale)
        n_parts, k = len(parts), space.nodes_per_cell
        m = max(len(p.elements) for p in parts)
        cells = np.zeros((n_parts, m, k), dtype=np.int32)
        index = np.zeros((n_parts, m), dtype=np.int64)  # global element of every slot
        real = np.zeros((n_parts, m))
        points = np.zeros((n_parts, n_local, 3))
        for p, part in enumerate(parts):
            m_p = len(part.elements)
            cells[p, :m_p], cells[p, m_p:] = part.local_tets, part.local_tets[0]
            index[p, :m_p], index[p, m_p:] = part.elements, part.elements[0]
            real[p, :m_p] = 1.0
            points[p, :part.n_local] = space.points[part.nodes]
        broadcast = lambda x: jnp.broadcast_to(x, (n_parts,) + jnp.shape(x))  # noqa: E731
        return HyperelasticForce(
            cells=jnp.asarray(cells), gradients=jnp.asarray(gradients[index]),
            weights=jnp.asarray(weights[index] * real[:, :, None]),
            material=jax.tree_util.tree_map(broadcast, material),
            fibres=None if fibres is None else fibres[jnp.asarray(index)], points=jnp.asarray(points),
            unit_mass=jnp.asarray(unit_mass[index] * real[:, :, None]),
            state=None if state is None else jax.tree_util.tree_map(lambda x: jnp.asarray(x)[index], state))

    def max_stable_dt(self, problem):
        """The exact bound 2 / omega_max [s] of the tangent stiffness at the initial
        displacement (zero if none) over the lumped mass, on the free dofs, springs of
        elastic supports included (:func:`exact_stable_dt`)."""
        u0 = problem.initial_displacement
        return exact_stable_dt(problem, None if u0 is None else np.asarray(u0, dtype=float))


def default_step(problem, alpha_s: float = ALPHA_S) -> StableStep:
    """The default time step of a hyperelastic problem (``Problem.dt``, ``Problem.time_step``):
    ``alpha_s * min(element rule, exact bound)`` of its tangent at the initial displacement
    (zero if none), the element rule :func:`stable_dt` (``rule="element"``, alpha_s = 1,
    never above the exact bound without springs) and the exact bound :func:`exact_stable_dt`
    (springs included; the bound :func:`jaxsync.fem.check_dt` refuses to exceed).
    Memoised on the problem's operators, per law (type, parameters, fibres), initial
    displacement, density scaling, Dirichlet set and supports.

    Raises:
        ProblemError: traced material parameters or initial displacement (pass dt=).
    """
    from ...pytree import is_traced

    m, u0 = problem.material, problem.initial_displacement
    if is_traced(m, u0):
        raise ProblemError(
            f"the default time step of a {type(m).__name__} problem comes from its tangent stiffness at rest, "
            "an eigenvalue computed on the host, so it cannot follow traced material parameters: pass dt= "
            "explicitly (for instance the problem.dt of the problem at concrete parameters)")
    law = m.parameters()
    fixed, _ = problem.dirichlet_dofs()
    scale = problem.density_scale
    key = (*law.key(), fixed.tobytes(),
           None if scale is None else np.asarray(scale, dtype=float).tobytes(),
           None if u0 is None else np.asarray(u0, dtype=float).tobytes(),
           tuple((s.surface, float(s.stiffness), s.normal_only) for s in problem.supports))
    u = None if u0 is None else np.asarray(u0, dtype=float)
    rule, exact = problem.operators.stability_bound(
        "finite strain at rest", key,
        lambda: (stable_dt(problem, u, alpha_s=1.0, rule="element"), exact_stable_dt(problem, u)))
    return hyperelastic_step(rule, exact, alpha_s, element=problem.element, law=law.name)


def _operator(problem_or_operator) -> HyperelasticForce:
    if isinstance(problem_or_operator, HyperelasticForce):
        if np.ndim(problem_or_operator.weights) != 2:
            raise ProblemError("this is a partition's stacked operator: pass the problem (or the whole mesh's "
                               "operator, TotalLagrangian().operator(problem))")
        return problem_or_operator
    return TotalLagrangian().operator(problem_or_operator)


def strain_energy(problem_or_operator, u):
    """The stored strain energy [erg] of displacements u (n_nodes, 3) [cm]."""
    return _operator(problem_or_operator).energy(jnp.asarray(u, dtype=float))


def inverted_elements(problem_or_operator, u) -> np.ndarray:
    """Sorted indices (int64) of the elements with J = det F <= 0 (or not finite) at some
    quadrature point of displacements u (n_nodes, 3) [cm]: inverted (or degenerate)
    elements, where the hyperelastic energy is undefined."""
    J = np.asarray(_operator(problem_or_operator).jacobians(jnp.asarray(u, dtype=float)))
    return np.flatnonzero(~np.all(np.isfinite(J) & (J > 0), axis=1)).astype(np.int64)


def _acoustic_maximum(a, starts, sweeps: int = 3):
    """(...,) max over unit n of the largest eigenvalue of q(n)_ik = a_ijkl n_j n_l, by
    alternating maximisation of the biquadratic form v_i n_j a_ijkl v_k n_l (each half-step
    an eigenvector of a symmetric 3 x 3 matrix, so the value never decreases) from the
    ``starts`` (..., s, 3) directions; returns the best value reached."""
    a = a[..., None, :, :, :, :]
    n = starts
    best = None
    for _ in range(sweeps):
        q = jnp.einsum("...ijkl,...j,...l->...ik", a, n, n)
        values, vectors = jnp.linalg.eigh(0.5 * (q + jnp.swapaxes(q, -1, -2)))
        v = vectors[..., :, -1]
        best = values[..., -1] if best is None else jnp.maximum(best, values[..., -1])
        r = jnp.einsum("...ijkl,...i,...k->...jl", a, v, v)
        values, vectors = jnp.linalg.eigh(0.5 * (r + jnp.swapaxes(r, -1, -2)))
        n = vectors[..., :, -1]
        best = jnp.maximum(best, values[..., -1])
    return jnp.max(best, axis=-1)


def element_wave_speeds(problem_or_operator, u) -> np.ndarray:
    """(n_elements,) the fastest plane-wave speed of each element's current tangent [cm/s]
    (module docstring: the acoustic tensor of a = F F A, maximised over directions; the
    largest over the element's quadrature points)."""
    op = _operator(problem_or_operator)
    return np.asarray(_wave_speeds(op, jnp.asarray(u, dtype=float)))


@jax.jit
def _wave_speeds(op, u):
    F = op.deformation_gradient(u)  # (m, q, 3, 3)
    A = op.material.tangent(F, op.fibres_at_points())
    a = jnp.einsum("mqjJ,mqlL,mqiJkL->mqijkl", F, F, A)  # J times the spatial tangent
    # start from the principal directions of b = F F^T, the axes and the fibres' current directions
    _, principal = jnp.linalg.eigh(jnp.einsum("mqiJ,mqjJ->mqij", F, F))
    starts = [jnp.swapaxes(principal, -1, -2), jnp.broadcast_to(jnp.eye(3), F.shape)]
    if op.fibres is not None:
        fa = jnp.einsum("mqij,mfj->mqfi", F, op.fibres)
        starts.append(fa / jnp.linalg.norm(fa, axis=-1, keepdims=True))
    modulus = _acoustic_maximum(a, jnp.concatenate(starts, axis=-2))  # (m, q) [dyn/cm^2]
    density = op.material.rho * jnp.sum(op.unit_mass, axis=1) / jnp.sum(op.weights, axis=1)  # scaled rho_e
    return jnp.sqrt(jnp.max(modulus, axis=1) / density)


@jax.jit
def element_stiffness(op, u):
    """(n_elements, 3k, 3k) each element's tangent stiffness d f_e / d u_e [dyn/cm] at
    displacements u (n_nodes, 3) [cm]: forward-mode derivative (``jax.jacfwd``) of the
    element's nodal forces, vmapped over the elements; dofs node-interleaved (node a,
    component i: 3 a + i)."""
    def element_force(ue, gradients, weights, fibres, state):
        F = jnp.einsum("ka,qkj->qaj", ue, gradients) + jnp.eye(3)[None]
        fibres = None if fibres is None else fibres[None]
        P = (op.material.first_piola(F, fibres) if state is None
             else op.material.stress_update(F, fibres, state, 0.0)[0])
        return jnp.einsum("q,qij,qkj->ki", weights, P, gradients).reshape(-1)

    def stiffness(ue, gradients, weights, fibres, state):
        return jax.jacfwd(lambda x: element_force(x.reshape(ue.shape), gradients, weights, fibres, state))(
            ue.reshape(-1))

    return jax.vmap(stiffness)(u[op.cells], op.gradients, op.weights, op.fibres, op.state)


def tangent_matrix(problem_or_operator, u):
    """The assembled tangent stiffness K_T(u) = d f_int / d u (scipy CSR, (3 n_nodes,
    3 n_nodes) [dyn/cm], dofs node-interleaved) of displacements u (n_nodes, 3) [cm]: the
    element blocks of :func:`element_stiffness` summed at the nodes (exact: the Hessian of
    the stored energy, symmetric up to round-off). The elastic supports' springs are not
    included."""
    import scipy.sparse as sp

    op = _operator(problem_or_operator)
    u = jnp.asarray(u, dtype=float)
    blocks = np.asarray(element_stiffness(op, u))
    cells = np.asarray(op.cells)
    dofs = (3 * cells[:, :, None] + np.arange(3)).reshape(len(cells), -1)
    size = dofs.shape[1]
    rows = np.broadcast_to(dofs[:, :, None], (len(cells), size, size)).ravel()
    cols = np.broadcast_to(dofs[:, None, :], (len(cells), size, size)).ravel()
    n = 3 * int(u.shape[0])
    return sp.coo_matrix((blocks.ravel(), (rows, cols)), shape=(n, n)).tocsr()


@jax.jit
def element_frequencies(op, u):
    """(n_elements,) omega_e^2: the largest eigenvalue of each element's tangent stiffness
    over its lumped mass [1/s^2]."""
    K = element_stiffness(op, u)  # (m, 3k, 3k)
    s = 1.0 / jnp.sqrt(jnp.repeat(op.material.rho * op.unit_mass, 3, axis=1))
    K = 0.5 * (K + jnp.swapaxes(K, 1, 2)) * s[:, :, None] * s[:, None, :]
    return jnp.linalg.eigvalsh(K)[:, -1]


def stable_dt(problem_or_operator, u=None, *, alpha_s: float = ALPHA_S, rule: str | None = None) -> float:
    """The stable step [s] of the current state u (n_nodes, 3) [cm] (zero if None), by
    ``rule`` (module docstring): ``"cfl"`` alpha_s min h_e / c_e with the deformed element
    size and the tangent's wave speed (P1 only; the default for P1), ``"element"``
    alpha_s min 2 / omega_e from the element tangent stiffnesses (never above the exact
    bound; the default for P2). Check it every so many steps during a run: compression
    stiffens most laws and shrinks the elements.

    Raises:
        StabilityError: an inverted element (J <= 0), where no step is stable.
        ProblemError: an unknown rule, or ``"cfl"`` on P2 elements.
    """
    op = _operator(problem_or_operator)
    k = int(op.cells.shape[1])
    rule = ("cfl" if k == 4 else "element") if rule is None else rule
    if rule not in STABLE_STEP_RULES:
        raise ProblemError(f"rule must be one of {', '.join(map(repr, STABLE_STEP_RULES))}, got {rule!r}")
    u = jnp.zeros(op.points.shape) if u is None else jnp.asarray(u, dtype=float)
    bad = inverted_elements(op, u)
    if len(bad):
        raise StabilityError(f"{len(bad)} inverted element(s) (J <= 0), e.g. element {int(bad[0])}: no time step is "
                             "stable; reduce dt or the load, or refine the mesh where the elements fold")
    if rule == "element":
        return float(alpha_s * 2.0 / np.sqrt(float(jnp.max(element_frequencies(op, u)))))
    if k != 4:
        raise ProblemError("rule='cfl' uses the size of linear (P1) tetrahedra; P2 elements take rule='element' "
                           "(the element eigenvalue bound)")
    cells = np.asarray(op.cells)
    h = element_size(np.asarray(op.points) + np.asarray(u), cells)
    c = element_wave_speeds(op, u)
    return float(alpha_s * np.min(h / c))


def check_stable_dt(problem_or_operator, u, dt: float, *, rule: str | None = None) -> float:
    """Refuse a time step above the stable step of the current state: returns the bound
    (:func:`stable_dt` with alpha_s = 1) [s] when ``dt`` is at most it.

    Raises:
        StabilityError: ``dt`` above the bound of the current (deformed) state, or an
            inverted element; the message names the step to use.
    """
    dt = float(dt)
    if not dt > 0 or not np.isfinite(dt):
        raise StabilityError(f"time step must be positive and finite, got dt={dt}")
    bound = stable_dt(problem_or_operator, u, alpha_s=1.0, rule=rule)
    if dt > bound:
        raise StabilityError(f"dt={dt:.4e} s is above the stable step {bound:.4e} s of the current deformed state "
                             f"(its tangent stiffness): continue with dt <= {ALPHA_S * bound:.4e} s "
                             f"(alpha_s = {ALPHA_S}), or check the state again after fewer steps")
    return bound


@jax.jit
def _tangent_product(op, u, v):
    """K_T(u) v [dyn]: the directional derivative of f_int at u (a ``jax.jvp``)."""
    return jax.jvp(op.matvec, (u,), (v,))[1]


def exact_stable_dt(problem, u=None, *, tol: float = 1e-10, max_iter: int = 20000, seed: int = 0) -> float:
    """The exact bound 2 / omega_max [s] of the central difference scheme at displacement u
    (zero if None): omega_max^2 the largest eigenvalue of M^-1/2 K_T(u) M^-1/2 on the free
    dofs, K_T the tangent of f_int (a ``jax.jvp`` per product) plus the supports' springs,
    M the lumped mass; dense up to 400 free dofs, else Lanczos (ARPACK)."""
    from ._support import spring_matrix

    op = TotalLagrangian().operator(problem)
    n = problem.n_nodes
    u = jnp.zeros((n, 3)) if u is None else jnp.asarray(u, dtype=float)
    fixed, _ = problem.dirichlet_dofs()
    free = np.setdiff1d(np.arange(3 * n), fixed)
    if len(free) == 0:
        raise StabilityError("every dof is prescribed: there is no free motion to bound")
    mass = np.repeat(np.asarray(problem.lumped_mass(), dtype=float), 3)
    s = 1.0 / np.sqrt(mass[free])
    springs = spring_matrix(problem)
    tangent = lambda v: _tangent_product(op, u, v)  # noqa: E731 (compiled once per mesh size)

    def product(x):
        v = np.zeros(3 * n)
        v[free] = s * np.asarray(x).ravel()
        out = np.asarray(tangent(jnp.asarray(v.reshape(n, 3)))).ravel()
        if springs is not None:
            out = out + springs @ v
        return s * out[free]

    if len(free) <= 400:
        import scipy.linalg

        dense = np.stack([product(e) for e in np.eye(len(free))], axis=1)
        largest = float(scipy.linalg.eigvalsh(0.5 * (dense + dense.T))[-1])
    else:
        import scipy.sparse.linalg as sla

        A = sla.LinearOperator((len(free),) * 2, matvec=product, dtype=float)
        v0 = np.random.default_rng(seed).standard_normal(len(free))
        largest = float(sla.eigsh(A, k=1, which="LA", tol=tol, maxiter=max_iter, v0=v0,
                                  return_eigenvectors=False)[0])
    return float(2.0 / np.sqrt(largest))
