"""Elastic (Robin) supports: surrounding tissue as a per-area spring and dashpot.

Arterial models clamp little in reality: the vessel rests on the tissue around it, which
pushes back in proportion to the wall's displacement and velocity (Moireau et al. 2012,
the standard of SimVascular's structural solver). On a facet set the support applies the
traction

    t = -k_s u - c_s v          (``normal_only``: -(k_s u.n + c_s v.n) n)

per unit area, k_s [dyn/cm^3] and c_s [dyn s/cm^3]. Its spring is a symmetric surface
stiffness S_k = k_s integral of N_i N_j (I or n n^T) over the surface, added to K (the
partial sums at shared nodes complete with the exchange, like the volume's); its dashpot is
lumped by HRZ (the diagonal blocks of the same surface matrix, scaled facet by facet to its
area: for P1 triangles c_s A / 3 (I or n n^T) at each vertex, the row sums; for P2 a
positive share at every node), and enters the damping C = alpha M + B, so that the
central-difference update stays explicit: a 3x3 solve per node (:mod:`jaxsync.fem`).
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np

from ...errors import ProblemError
from ...pytree import concrete_scalar, pytree_dataclass, static_field
from .._parameter_checks import check_number

__all__ = ["ElasticSupport", "SurfaceSpring", "Dashpot", "surface_spring", "part_surface_springs", "dashpot_blocks",
           "dashpot", "apply_dashpot", "spring_matrix", "spring_ratios", "stiffness_matrix"]


@pytree_dataclass
class ElasticSupport:
    """A spring-dashpot support on the facet set ``surface`` (see the module docstring).

    Attributes:
        stiffness: k_s, spring per unit area [dyn/cm^3] (>= 0; may be a JAX tracer).
        damping: c_s, dashpot per unit area [dyn s/cm^3] (>= 0; may be a JAX tracer).
        surface: the facet set.
        normal_only: True: the support acts along the surface normal only (the wall may
            slide along the tissue); False: in every direction.
    """

    stiffness: Any
    damping: Any = 0.0
    surface: str = static_field(default="support")
    normal_only: bool = static_field(default=False)

    def __post_init__(self):
        check_number(self.stiffness, "ElasticSupport.stiffness", at_least=0.0, unit="dyn/cm^3 (per unit area)")
        check_number(self.damping, "ElasticSupport.damping", at_least=0.0, unit="dyn s/cm^3 (per unit area)")
        if not isinstance(self.surface, str):
            raise ProblemError(f"ElasticSupport.surface must be the name of a facet set, got {self.surface!r}")


@pytree_dataclass
class SurfaceSpring:
    """The supports' springs on the nodes they touch: rows of a block-sparse matrix whose
    columns are the mesh's (or a part's) nodes.

    Attributes:
        rows: (n_rows,) int32 node of each row (padding: an index past the last node, so
            that its contribution is dropped).
        columns: (n_rows, width) int32 column nodes (padding: the row's first column).
        blocks: (n_rows, 3, width, 3) values [dyn/cm] (zero on padding).
    """

    rows: Any
    columns: Any
    blocks: Any

    def matvec(self, u):
        """(n_nodes, 3) spring forces S u [dyn] of displacements ``u`` (n_nodes, 3)."""
        from .._sparse import BlockEll

        local = BlockEll(self.columns, self.blocks).matvec(u)  # rows of S only: not square, not symmetric
        return jnp.zeros_like(u).at[self.rows].add(local, mode="drop")


@pytree_dataclass
class Dashpot:
    """The lumped central-difference update with the supports' dashpots, node by node (all
    (n_nodes, 3, 3)): with A = m (1 + alpha dt / 2) I + dt / 2 B,

    * ``inverse``: A restricted to the node's free components, inverted (identity on its
      prescribed ones), so that the free components see the prescribed ones as known;
    * ``coupling``: dt / 2 B, the dashpot's share of the right-hand side (B d(n-1));
    * ``prescribed``: A's free rows times its prescribed columns (moved to the right-hand
      side with the prescribed values).

    Where no dashpot acts: inverse = I / (m (1 + alpha dt / 2)), the others zero."""

    inverse: Any
    coupling: Any
    prescribed: Any


def _unit_surface_blocks(space, support: ElasticSupport) -> tuple[np.ndarray, np.ndarray]:
    """(element of each facet (n_f,), unit blocks (n_f, 3 k, 3 k)) of integral of N_i N_j
    (I or n n^T) over the support's facets, in the dofs of each facet's element (k nodes
    per element: those of ``space.cells``)."""
    from skfem import BilinearForm
    from skfem.helpers import dot

    from ...mesh import to_skfem
    from .._assembly import boundary_facet_indices

    facets = boundary_facet_indices(space.mesh, to_skfem(space.mesh), support.surface, what="an elastic support")
    # integrand of degree 2 (P1) or 4 (P2): exact
    basis = space.facet_basis(facets, intorder=2 if space.element == "P1" else 4)

    if support.normal_only:
        @BilinearForm
        def form(u, v, w):
            return dot(u, w.n) * dot(v, w.n)
    else:
        @BilinearForm
        def form(u, v, w):
            return dot(u, v)

    blocks = np.asarray(form.elemental(basis).tolocal())  # (n_f, 3 k, 3 k)
    return np.asarray(basis.tind), np.ascontiguousarray(blocks)


def _support_blocks(problem, support):
    """The unit blocks of ``support`` on the problem's mesh, computed once per space."""
    return problem.operators.derived("support blocks", (support.surface, support.normal_only),
                                     lambda: _unit_surface_blocks(problem.space, support))


def _springs(problem) -> list:
    """The supports that have a spring (stiffness not a concrete zero)."""
    return [s for s in problem.supports if concrete_scalar(s.stiffness) != 0.0]


def _spring_entries(problem, supports, elements=None, local_tets=None) -> list:
    """Per support, (rows, cols, unit 3 x 3 blocks) of the node pairs of its facets: all of
    them in the mesh's numbering, or those of a part's ``elements`` (global ids) in its
    local numbering (``local_tets``, one row per element)."""
    tets = problem.space.cells if elements is None else np.asarray(local_tets)
    k = tets.shape[1]
    position = None
    if elements is not None:
        position = np.full(problem.mesh.n_elements, -1, dtype=np.int64)
        position[np.asarray(elements)] = np.arange(len(elements))
    entries = []
    for s in supports:
        tind, blocks = _support_blocks(problem, s)
        if position is not None:
            keep = position[tind] >= 0
            tind, blocks = position[tind[keep]], blocks[keep]
        nodes = tets[tind]  # (n_f, k)
        b = blocks.reshape(-1, k, 3, k, 3).transpose(0, 1, 3, 2, 4)  # node blocks (n_f, k, k, 3, 3)
        entries.append((np.repeat(nodes, k, axis=1).reshape(-1), np.tile(nodes, (1, k)).reshape(-1),
                        b.reshape(-1, 3, 3)))
    return entries


def _spring_rows(entries):
    """(the distinct (row, column) pairs, each entry's pair, row nodes, each pair's row, its
    slot in the row) of ``entries``."""
    pairs = np.concatenate([np.stack([r, c], axis=1) for r, c, _ in entries]) if entries else np.zeros((0, 2), int)
    keys, inverse = np.unique(pairs, axis=0, return_inverse=True)
    row_nodes, row_index = np.unique(keys[:, 0], return_inverse=True)
    slot = np.arange(len(keys)) - np.searchsorted(keys[:, 0], keys[:, 0])  # keys sorted by row
    return keys, inverse.ravel(), row_nodes, row_index, slot


def _spring_layout(entries, supports, n_nodes: int, n_rows: int | None = None, width: int | None = None):
    """The :class:`SurfaceSpring` of ``entries``: rows of (columns, sum_s k_s unit blocks),
    padded to ``n_rows`` rows of ``width`` columns (JAX in the stiffnesses)."""
    keys, inverse, row_nodes, row_index, slot = _spring_rows(entries)
    n_rows = len(row_nodes) if n_rows is None else int(n_rows)
    width = int(slot.max(initial=0)) + 1 if width is None else int(width)
    columns = np.zeros((n_rows, width), dtype=np.int64)
    columns[:len(row_nodes)] = row_nodes[:, None]
    columns[row_index, slot] = keys[:, 1]
    rows = np.full(n_rows, n_nodes, dtype=np.int64)  # padding rows: dropped
    rows[:len(row_nodes)] = row_nodes
    blocks, offset = None, 0
    for s, (r, _, values) in zip(supports, entries):
        unit = np.zeros((n_rows, width, 3, 3))
        sel = inverse[offset:offset + len(r)]
        np.add.at(unit, (row_index[sel], slot[sel]), values)
        offset += len(r)
        term = s.stiffness * jnp.asarray(unit.transpose(0, 2, 1, 3))  # (n_rows, 3, width, 3)
        blocks = term if blocks is None else blocks + term
    return SurfaceSpring(jnp.asarray(rows, dtype=jnp.int32), jnp.asarray(columns, dtype=jnp.int32), blocks)


def surface_spring(problem) -> SurfaceSpring | None:
    """The :class:`SurfaceSpring` of ``problem.supports`` on the whole mesh (None when no
    support has a spring); its values are sum_s k_s S_s, traced when a stiffness is."""
    supports = _springs(problem)
    return None if not supports else _spring_layout(_spring_entries(problem, supports), supports, problem.n_nodes)


def part_surface_springs(problem, parts, n_local: int) -> SurfaceSpring | None:
    """The parts' :class:`SurfaceSpring` (each on the facets of its own elements, in its
    local numbering), stacked on a leading part axis and padded alike; None without
    springs. ``parts``: objects with ``elements`` and ``local_tets``
    (:class:`jaxsync.parallel.Part`)."""
    import jax

    supports = _springs(problem)
    if not supports:
        return None
    entries = [_spring_entries(problem, supports, p.elements, p.local_tets) for p in parts]
    shapes = [_spring_rows(e) for e in entries]
    n_rows = max(max(len(s[2]) for s in shapes), 1)
    width = max(int(s[4].max(initial=0)) + 1 for s in shapes)
    springs = [_spring_layout(e, supports, n_local, n_rows, width) for e in entries]
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *springs)


def spring_matrix(problem, scale: float = 1.0):
    """The supports' springs as a SciPy matrix (n_dofs, n_dofs), sum_s k_s S_s times
    ``scale`` [dyn/cm] (concrete stiffnesses), or None without springs."""
    import scipy.sparse as sp

    supports = _springs(problem)
    if not supports:
        return None
    n = problem.n_dofs
    total = sp.csr_matrix((n, n))
    cells = problem.space.cells
    size = 3 * cells.shape[1]
    for s in supports:
        tind, blocks = _support_blocks(problem, s)
        dofs = (3 * cells[tind][:, :, None] + np.arange(3)).reshape(-1, size)
        rows, cols = np.repeat(dofs, size, axis=1).ravel(), np.tile(dofs, (1, size)).ravel()
        total = total + float(s.stiffness) * scale * sp.coo_matrix((blocks.ravel(), (rows, cols)), shape=(n, n)).tocsr()
    return total


def spring_ratios(problem) -> tuple:
    """(k_s / E for each spring support): with them the exact stability bound of any E and
    rho follows from one eigenvalue (:func:`jaxsync.fem.max_stable_dt`).

    Raises:
        ProblemError: a traced E or stiffness (the bound is an eigenvalue on the host)."""
    supports = _springs(problem)
    if not supports:
        return ()
    from ...pytree import is_traced

    if is_traced(problem.material.E, [s.stiffness for s in supports]):
        raise ProblemError("with elastic supports the default time step depends on k_s / E through the exact "
                           "stability bound, an eigenvalue computed on the host: pass dt= explicitly (the "
                           "problem.dt of the problem at concrete values)")
    return tuple(float(s.stiffness) / float(problem.material.E) for s in supports)


def dashpot_blocks(problem):
    """(n_nodes, 3, 3) lumped dashpot B of ``problem.supports`` [dyn s/cm] (None when no
    support has one): per node, sum_s c_s times the row sums of its unit surface matrix."""
    supports = [s for s in problem.supports if concrete_scalar(s.damping) != 0.0]
    if not supports:
        return None
    total = None
    for s in supports:
        tind, blocks = _support_blocks(problem, s)
        nodes = problem.space.cells[tind]
        k = nodes.shape[1]
        b = blocks.reshape(-1, k, 3, k, 3)
        # HRZ: each facet's diagonal blocks, scaled to the facet's total (for P1 triangles the
        # row sums, a third of the area at each vertex; for P2 every node gets a positive share,
        # where row sums would leave the vertices with none)
        diagonal = np.einsum("fiaib->fiab", b)
        scale = np.einsum("fiaja->f", b) / np.einsum("fiaia->f", b)
        lumped = diagonal * scale[:, None, None, None]
        unit = np.zeros((problem.n_nodes, 3, 3))
        np.add.at(unit, nodes.reshape(-1), lumped.reshape(-1, 3, 3))
        term = s.damping * jnp.asarray(unit)
        total = term if total is None else total + term
    return total


def dashpot(mass, damping, dt, blocks, fixed) -> Dashpot:
    """The :class:`Dashpot` of lumped masses ``mass`` (n_nodes, 3) [g], mass-proportional
    ``damping`` alpha [1/s], step ``dt`` [s], dashpot ``blocks`` B (n_nodes, 3, 3) and the
    prescribed components ``fixed`` (n_nodes, 3) bool."""
    half = 0.5 * dt
    eye = jnp.eye(3, dtype=blocks.dtype)[None]
    lhs = (mass[:, 0] * (1.0 + damping * half))[:, None, None] * eye + half * blocks
    free = ~jnp.asarray(fixed)
    both = free[:, :, None] & free[:, None, :]
    reduced = jnp.where(both, lhs, eye)  # the free block, identity on the prescribed components
    return Dashpot(jnp.linalg.inv(reduced), half * blocks,
                   jnp.where(free[:, :, None] & ~free[:, None, :], lhs, 0.0))


def apply_dashpot(d: Dashpot, rhs, previous, prescribed):
    """(n_nodes, 3) displacement d(n+1) of the right-hand side ``rhs`` (without the
    dashpot's term), d(n-1) ``previous`` and the prescribed values at t_(n+1)."""
    rhs = rhs + jnp.einsum("nij,nj->ni", d.coupling, previous) - jnp.einsum("nij,nj->ni", d.prescribed, prescribed)
    return jnp.einsum("nij,nj->ni", d.inverse, rhs)


def stiffness_matrix(problem):
    """The global stiffness K (scipy CSR, (n_dofs, n_dofs) [dyn/cm]) of a linear elastic
    problem (its small-strain moduli), the elastic supports' springs included."""
    m = problem.material
    K = problem.operators.stiffness(m.lam, m.mu)
    springs = spring_matrix(problem)
    return K if springs is None else (K + springs).tocsr()
