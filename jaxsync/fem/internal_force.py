"""The physics seam: what the explicit step asks of the physics.

Above :mod:`jaxsync.fem`, nothing knows the element or the material law. A *force
model* turns a problem (mesh and material) into

* the internal-force operator of the whole mesh (:meth:`ForceModel.operator`): a pytree
  with ``matvec(u) -> f_int(u)``, (n_nodes, 3) -> (n_nodes, 3) [cm -> dyn], traced in
  the material's parameters (differentiable);
* the same for every part of a partition (:meth:`ForceModel.part_operators`), stacked
  on a leading part axis and padded to the largest part, each part's force computed
  on its own elements only (a partial sum at shared nodes, which the distributed solver
  completes by its exchange);
* its stable-step bound (:meth:`ForceModel.max_stable_dt`).

The runners, deep halos, the executors, gradients and surrogates work through these
three only. Two models implement the linear elastic law today (paper Remark 2):
:class:`Preassembled` (K stored once, the fast path) and :class:`ElementRecompute`
(element quantities formed every step, standing in for laws whose element quantities
change, such as hyperelastic ones). :func:`force_model` maps the command line's names
(``"preassembled"``, ``"recompute"``) onto them.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol, Sequence

import jax.numpy as jnp
import numpy as np

from ..errors import ProblemError
from ..options import Mode, check_option

__all__ = ["InternalForce", "ForceModel", "Preassembled", "ElementRecompute", "force_model", "PartGeometry"]


class InternalForce(Protocol):
    """A pytree that computes the internal force of displacements ``u``."""

    def matvec(self, u): ...


class PartGeometry(Protocol):
    """What a force model reads of one part (:class:`jaxsync.parallel.partitioning.Part`
    and the parts of a :class:`jaxsync.parallel.halo.HaloPartition` have it)."""

    elements: np.ndarray  # (n_elements_p,) global element ids
    nodes: np.ndarray  # (n_local_p,) global node ids
    local_tets: np.ndarray  # (n_elements_p, 4) connectivity in local numbering

    @property
    def n_local(self) -> int: ...


class ForceModel(Protocol):
    """How the internal force of a problem is computed (see the module docstring)."""

    name: str

    def operator(self, problem) -> InternalForce: ...

    def part_operators(self, problem, parts: Sequence[PartGeometry], n_local: int) -> InternalForce: ...

    def max_stable_dt(self, problem): ...


def _max_stable_dt(problem):
    from .timestep import max_stable_dt

    return max_stable_dt(problem)


@dataclasses.dataclass(frozen=True)
class Preassembled:
    """The stiffness K = lambda K_lambda + mu K_mu assembled once from scikit-fem's element
    blocks and stored in node-blocked ELL form (:class:`jaxsync.fem.sparse.BlockEll`,
    symmetric: its product has its own reverse pass). The unit operators K_lambda and
    K_mu do not depend on the material, so a traced lambda or mu costs no reassembly."""

    name: str = dataclasses.field(default="preassembled", init=False)

    def operator(self, problem):
        """:class:`~jaxsync.fem.sparse.BlockEll` of the whole mesh, (n_nodes, 3, width, 3)."""
        from .sparse import BlockEll

        adjacency, K_lambda, K_mu, _ = problem.operators.block_ell
        m = problem.material
        return BlockEll(jnp.asarray(adjacency), m.lam * jnp.asarray(K_lambda) + m.mu * jnp.asarray(K_mu),
                        symmetric=True)

    def part_operators(self, problem, parts, n_local: int):
        """The parts' :class:`~jaxsync.fem.sparse.BlockEll` stacked on a leading part axis,
        padded to ``n_local`` rows and the widest part's width (padding rows and slots
        point at their own row with zero blocks)."""
        from .sparse import BlockEll

        columns, K_lambda, K_mu = _part_unit_blocks(problem.mesh, parts, n_local)
        m = problem.material
        return BlockEll(jnp.asarray(columns), m.lam * jnp.asarray(K_lambda) + m.mu * jnp.asarray(K_mu),
                        symmetric=True)

    def max_stable_dt(self, problem):
        """The exact bound 2 / omega_max of M^-1 K [s] (:func:`jaxsync.fem.timestep.max_stable_dt`)."""
        return _max_stable_dt(problem)


@dataclasses.dataclass(frozen=True)
class ElementRecompute:
    """The paper's element-recompute mode (Remark 2): each step forms every element's
    geometry, strain and stress and sums the element forces at the nodes
    (:class:`jaxsync.fem.element_force.ElementStiffness`); nothing but the mesh is stored."""

    name: str = dataclasses.field(default="recompute", init=False)

    def operator(self, problem):
        """:class:`~jaxsync.fem.element_force.ElementStiffness` of the whole mesh."""
        from .element_force import ElementStiffness

        mesh, m = problem.mesh, problem.material
        return ElementStiffness(jnp.asarray(mesh.points), jnp.asarray(mesh.tets, dtype=jnp.int32),
                                jnp.ones(mesh.n_elements), m.lam, m.mu)

    def part_operators(self, problem, parts, n_local: int):
        """The parts' :class:`~jaxsync.fem.element_force.ElementStiffness` stacked on a
        leading part axis; padding elements repeat the part's element 0 with weight 0."""
        from .element_force import ElementStiffness

        n_parts = len(parts)
        n_elements = max(len(p.elements) for p in parts)
        tets = np.zeros((n_parts, n_elements, 4), dtype=np.int32)
        weight = np.zeros((n_parts, n_elements))
        points = np.zeros((n_parts, n_local, 3))
        for k, part in enumerate(parts):
            m_k = len(part.elements)
            tets[k, :m_k], tets[k, m_k:] = part.local_tets, part.local_tets[0]
            weight[k, :m_k] = 1.0
            points[k, :part.n_local] = problem.mesh.points[part.nodes]
        m = problem.material
        return ElementStiffness(jnp.asarray(points), jnp.asarray(tets), jnp.asarray(weight),
                                jnp.broadcast_to(m.lam, (n_parts,)), jnp.broadcast_to(m.mu, (n_parts,)))

    def max_stable_dt(self, problem):
        """The same bound as :class:`Preassembled` (the same K)."""
        return _max_stable_dt(problem)


_MODELS = {"preassembled": Preassembled, "recompute": ElementRecompute}


def force_model(mode: Mode | ForceModel = "preassembled") -> ForceModel:
    """The force model of ``mode``: ``"preassembled"`` (:class:`Preassembled`),
    ``"recompute"`` (:class:`ElementRecompute`), or a force model, returned as it is.

    Raises:
        ProblemError: any other value, naming the allowed ones.
    """
    if not isinstance(mode, str) and all(hasattr(mode, a) for a in ("operator", "part_operators", "max_stable_dt")):
        return mode
    return _MODELS[check_option("mode", mode, Mode, error=ProblemError)]()


def _part_unit_blocks(mesh, parts, n_local: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(columns (P, n_local, width) int32, K_lambda and K_mu blocks (P, n_local, 3, width, 3))
    of the parts' own elements, material-independent (numpy)."""
    import scipy.sparse as sp

    from .assembly import element_blocks
    from .sparse import block_ell_values, node_adjacency, pad_block_ell

    k_lambda, k_mu = element_blocks(mesh)
    columns, lambdas, mus = [], [], []
    for part in parts:
        dofs = (3 * part.local_tets[:, :, None] + np.arange(3)).reshape(-1, 12)
        rows, cols = np.repeat(dofs, 12, axis=1).ravel(), np.tile(dofs, (1, 12)).ravel()
        adjacency = node_adjacency(part.local_tets, part.n_local)
        columns.append(adjacency)
        for unit, out in ((k_lambda, lambdas), (k_mu, mus)):
            K = sp.coo_matrix((unit[part.elements].ravel(), (rows, cols)), shape=(3 * part.n_local,) * 2).tocsr()
            out.append(block_ell_values(K, adjacency))
    width = max(c.shape[1] for c in columns)
    padded = [(pad_block_ell(c, a, n_local, width), pad_block_ell(c, b, n_local, width)[1])
              for c, a, b in zip(columns, lambdas, mus)]
    return (np.stack([c for (c, _), _ in padded]).astype(np.int32),
            np.stack([a for (_, a), _ in padded]), np.stack([b for _, b in padded]))

