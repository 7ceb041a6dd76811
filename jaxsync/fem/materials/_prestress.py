"""A prestressed law: the imaged geometry as reference, with the deformation from the
stress-free state stored at every quadrature point (Gee, Foerster & Wall 2010).

Instead of computing the zero-pressure geometry, keep the imaged geometry x as the
reference and store at each quadrature point a prestrain F0, the deformation gradient from
a stress-free state to x. A displacement u from x then has the total deformation
F_tot = F F0, F = I + grad_x u, and the stress of the law psi on the imaged reference is
the Piola transform of its stress on the stress-free one:

    psi_0(F) = psi(F F0) / J0,    P_0(F) = P(F F0) F0^T / J0,    J0 = det F0.

When F0 is the deformation gradient of the imaged geometry over a zero-pressure geometry
(:func:`jaxsync.prestress` with ``method="zero-pressure"``), the prestressed problem is the
forward problem from that geometry written on the imaged one: their responses agree.
F0 from the MULF iteration (``method="mulf"``) makes the imaged geometry an equilibrium
without a compatible stress-free geometry behind it.

F0 is the law's internal variable (:meth:`Prestressed.internal_variables`, ``{"F0"}``),
constant in time: it rides in the solver state of every executor, is split with the
elements of a partition and checkpointed, and the static solver, the stable step and the
run checks see it through the total-Lagrangian operator
(:attr:`jaxsync.fem.forces.HyperelasticForce.state`).
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from ...errors import MaterialError, ProblemError
from ...pytree import is_traced, pytree_dataclass
from .._kinematics import determinant
from ._law import FiniteStrainLaw, MaterialParameters

__all__ = ["Prestressed"]


@pytree_dataclass
class Prestressed(FiniteStrainLaw):
    """A hyperelastic ``law`` with a prestrain F0 at every quadrature point
    (module docstring), a :class:`jaxsync.fem.materials.MaterialLaw`.

    Attributes:
        law: the stress-free law (:class:`jaxsync.NeoHookean`,
            :class:`jaxsync.NearlyIncompressibleNeoHookean`,
            :class:`jaxsync.HolzapfelGasserOgden`, or an elastic law of your own); a fibre
            law's directions are those of the stress-free state, element by element (as
            the zero-pressure geometry's law has them), and ``fibres`` reads them.
        prestrain: (n_elements, n_q, 3, 3) F0 at the quadrature points of the problem's
            element (P1: n_q = 1; P2 on a straight mesh: 4), det F0 > 0; None: the
            identity (no prestress).

    The law's parameters may be JAX tracers, and so may the prestrain.
    """

    law: Any
    prestrain: Any = None

    constant_state: ClassVar[bool] = True
    """Its internal variable (F0) never changes: the total-Lagrangian operator holds it."""

    def __post_init__(self):
        if not getattr(self.law, "finite_strain", False) or not hasattr(self.law, "first_piola"):
            raise MaterialError(f"Prestressed needs a hyperelastic law (jaxsync.NeoHookean, "
                                f"NearlyIncompressibleNeoHookean), got {type(self.law).__name__}")
        if self.law.internal_variables(1, 1):
            raise MaterialError(f"Prestressed takes an elastic law without internal variables; "
                                f"{type(self.law).__name__} has a state of its own")
        F0 = self.prestrain
        if isinstance(F0, (np.ndarray, jax.Array)) and not is_traced(F0):  # not a pytree's placeholder leaf
            if F0.ndim != 4 or F0.shape[-2:] != (3, 3):
                raise MaterialError(f"Prestressed.prestrain must have shape (n_elements, n_q, 3, 3), got {F0.shape}")
            if not np.all(np.linalg.det(np.asarray(F0, dtype=float)) > 0):
                raise MaterialError("Prestressed.prestrain has a deformation gradient with det F0 <= 0 (an inverted "
                                    "stress-free state): compute it with jaxsync.prestress")

    E = property(lambda self: self.law.E)
    nu = property(lambda self: self.law.nu)
    rho = property(lambda self: self.law.rho)
    mu = property(lambda self: self.law.mu)
    lam = property(lambda self: self.law.lam)

    def __getattr__(self, name):
        # a fibre law's directions are the inner law's (those of the stress-free state,
        # element by element); an isotropic inner law has none, and neither has this law
        if name == "fibres" and "law" in self.__dict__ and hasattr(self.law, "fibres"):
            return self.law.fibres
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def replace(self, **changes):
        """A copy with some fields changed; ``fibres=`` changes the inner law's."""
        if "fibres" in changes:
            changes["law"] = self.law.replace(fibres=changes.pop("fibres"))
        return dataclasses.replace(self, **changes)

    def stateless(self) -> "Prestressed":
        """The law without its stored prestrain (the operator holds that as its state)."""
        return Prestressed(self.law, None)

    def internal_variables(self, n_elements: int, n_points: int) -> dict:
        """{"F0": (n_elements, n_points, 3, 3)} the prestrain (the identity where None)."""
        if self.prestrain is None:
            return {"F0": jnp.broadcast_to(jnp.eye(3), (n_elements, n_points, 3, 3))}
        if np.shape(self.prestrain) != (n_elements, n_points, 3, 3):
            raise ProblemError(f"Prestressed.prestrain has shape {np.shape(self.prestrain)}, the problem has "
                               f"{n_elements} elements with {n_points} quadrature points each: give "
                               f"({n_elements}, {n_points}, 3, 3), computed on this mesh and element "
                               "(jaxsync.prestress)")
        return {"F0": jnp.asarray(self.prestrain)}

    def stress_update(self, F, fibres, internal, dt):
        """(P_0(F) = P(F F0) F0^T / J0 (..., 3, 3) [dyn/cm^2], the state unchanged)."""
        F0 = internal["F0"]
        P = self.law.first_piola(F @ F0, fibres)
        return P @ jnp.swapaxes(F0, -1, -2) / determinant(F0)[..., None, None], internal

    def energy(self, F, fibres=None, internal=None):
        """psi(F F0) / J0 (...,) [erg/cm^3] per unit imaged volume, with ``internal`` the
        state ({"F0"}) of the points of F."""
        F0 = self._prestrain(internal)
        return self.law.energy(F @ F0, fibres) / determinant(F0)

    def first_piola(self, F, fibres=None):
        """P_0(F) with the stored prestrain (F of the shape (n_elements, n_q, 3, 3))."""
        return self.stress_update(F, fibres, {"F0": self._prestrain(None)}, 0.0)[0]

    def _prestrain(self, internal):
        if internal is not None:
            return internal["F0"]
        if self.prestrain is None:
            return jnp.eye(3)
        raise ProblemError("the stress of a Prestressed law depends on the prestrain of each quadrature point: "
                           "compute it through the total-Lagrangian operator (its state), e.g. "
                           "jaxsync.steady_state, jaxsync.simulate, stable_dt(..., rule='element')")

    def parameters(self) -> MaterialParameters:
        """The inner law's class and parameters, and the sha256 of the prestrain (and of
        the inner law's fibres)."""
        inner = self.law.parameters()
        digest = None if self.prestrain is None else hashlib.sha256(
            np.ascontiguousarray(np.asarray(self.prestrain, dtype=float)).tobytes()).hexdigest()
        if inner.fibres is not None:
            digest = hashlib.sha256(f"{digest}:{inner.fibres}".encode()).hexdigest()
        return MaterialParameters(f"Prestressed[{inner.name}]", dict(inner.values), digest)
