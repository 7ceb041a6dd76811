"""The paper's cantilever (Tong & Schiavazzi 2022, section 5.1 and Table 1): a 25 x 1 x 1 cm
linear-elastic beam clamped at x = 0 and bent by a ramped body force."""

from __future__ import annotations

import numpy as np

from ..fem._loads import BodyForce, Ramp, StepOff
from ..fem._problem import Dirichlet, Problem
from ..fem.materials._linear_elastic import LinearElastic
from ..mesh import Mesh, box_beam
from ..options import Element

__all__ = ["cantilever"]


def cantilever(mesh: Mesh | None = None, *, body_force=(0.0, 0.0, -0.5), damping=0.5,
               stiffness_damping=0.0, t_ramp: float = 1.0, t_off: float | None = None,
               material: LinearElastic | None = None, initial_displacement=None,
               initial_velocity=None, element: Element | None = None) -> Problem:
    """The paper's cantilever (Table 1): 25 x 1 x 1 cm beam clamped at x = 0.

    E = 1e6 dyn/cm^2, nu = 0.3, rho = 1 g/cm^3, body force (0, 0, -0.5) dyn/cm^3 ramped
    over ``t_ramp`` s, damping alpha = 0.5 1/s (``stiffness_damping``: beta [s], default 0),
    zero initial conditions. The default mesh
    is the coarse :func:`jaxsync.box_beam` (104 nodes, 150 tetrahedra). Variants: skewed load
    ``body_force=(0, -0.5, -0.5)``; load switched off at ``t_off``; initial conditions.
    The clamp is every node with x equal to the mesh's smallest x; ``element`` as for
    :class:`Problem` (``"P2"``: quadratic tetrahedra).
    """
    mesh = box_beam() if mesh is None else mesh
    material = LinearElastic(1.0e6, 0.3, 1.0) if material is None else material
    x0 = float(mesh.points[:, 0].min())
    tol = 1e-8 * float(np.ptp(mesh.points[:, 0]))

    def nodes_at_min_x(p):
        return np.abs(p[:, 0] - x0) <= tol

    clamp = Dirichlet(where=nodes_at_min_x)
    time = Ramp(t_ramp) if t_off is None else StepOff(t_off, Ramp(t_ramp))
    return Problem(mesh=mesh, material=material, dirichlet=(clamp,),
                   loads=(BodyForce(body_force, time),), damping=damping, stiffness_damping=stiffness_damping,
                   initial_displacement=initial_displacement, initial_velocity=initial_velocity,
                   element=element)
