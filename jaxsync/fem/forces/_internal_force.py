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
three only. Two models implement the linear elastic law (paper Remark 2):
:class:`Preassembled` (K stored once, the fast path) and :class:`ElementRecompute`
(element quantities formed every step); a third, :class:`~jaxsync.fem.forces.TotalLagrangian`,
the finite-strain hyperelastic laws (:mod:`jaxsync.fem.materials`). :func:`force_model`
maps the command line's names (``"preassembled"``, ``"recompute"``, ``"total-lagrangian"``)
onto them.

The material law says which model runs it
(:meth:`jaxsync.fem.materials.MaterialLaw.force_model`): a finite-strain law has no
stiffness K to store, so the linear models hand its problem to
:class:`~jaxsync.fem.forces.TotalLagrangian` (the default ``mode="preassembled"``
of every solver runs the law the problem states, never its linearisation).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple, Protocol, Sequence

import jax.numpy as jnp
import numpy as np

from ...errors import ProblemError
from ...options import Mode, check_option

__all__ = ["InternalForce", "ForceModel", "Preassembled", "ElementRecompute", "force_model", "PartGeometry"]


class InternalForce(Protocol):
    """A pytree that computes the internal force of displacements ``u``, and (for
    stiffness-proportional damping, ``Problem.stiffness_damping``) that force plus the
    damping force beta K_T(u) v of a velocity v (:mod:`jaxsync.fem`)."""

    def matvec(self, u): ...

    def damped_matvec(self, u, velocity, beta): ...


class PartGeometry(Protocol):
    """What a force model reads of one part (:class:`jaxsync.parallel.Part`
    and the parts of a :class:`jaxsync.parallel.exchange.HaloPartition` have it)."""

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
    from .._timestep import max_stable_dt

    return max_stable_dt(problem)


def _finite_strain(problem, model):
    """The force model the problem's material law runs instead of ``model`` (a
    finite-strain law: :class:`~jaxsync.fem.forces.TotalLagrangian`), or None
    when it runs ``model`` itself (:meth:`jaxsync.fem.materials.MaterialLaw.force_model`;
    a setting of ``model`` that only a stored stiffness has is refused there)."""
    runs = problem.material.force_model(model)
    return None if runs is model else runs


class _Lame(NamedTuple):
    """Lame parameters alone (no E): the moduli of a unit operator
    (:meth:`Preassembled.unit_operators`)."""

    lam: float
    mu: float


LAYOUTS = ("grouped", "ell")
BLOCK_DTYPES = ("float64", "float32")
PRODUCTS = ("auto", "fused", "compact")
COMPACT_SLOT_STEPS = 2e8
"""The run length, in stored slots times steps, below which ``Preassembled(product="auto")``
computes K u in the compact form (:attr:`Preassembled.product`)."""


@dataclasses.dataclass(frozen=True)
class Preassembled:
    """The stiffness K = lambda K_lambda + mu K_mu assembled once from scikit-fem's element
    blocks and stored in node-blocked ELL form, symmetric (its product has its own
    reverse pass). The unit operators K_lambda and K_mu do not depend on the material, so
    a traced lambda or mu costs no reassembly.

    When Young's modulus E is traced (``jax.grad`` in E) and the Poisson ratio is a
    concrete number, K = E K_1 with K_1 = K(E=1, nu) a constant: on meshes (parts) of
    ``scale_min_nodes`` nodes or more the operator then holds K_1's blocks (numpy, built
    here) and E as its :attr:`~jaxsync.fem.BlockEll.scale`, so that reverse mode
    through the time loop sums one scalar per step, <K_1 y_bar, u>, instead of carrying a
    cotangent as large as K (the blocks') across every step and contracting it with
    K_lambda and K_mu. With nu traced too, the blocks are lambda K_lambda + mu K_mu,
    traced (as on smaller meshes); with a concrete material the blocks are K's and no
    scale exists (forward runs unchanged).

    Attributes:
        layout: ``"grouped"`` (default): rows grouped by node degree, each group a block
            ELL of its own width (:class:`jaxsync.fem.GroupedEll`; on an
            unstructured mesh the padded slots follow the mean degree, not the largest);
            ``"ell"``: one block ELL as wide as the largest degree
            (:class:`jaxsync.fem.BlockEll`), kept for comparison.
        blocks_dtype: ``"float64"`` (default) or ``"float32"``: the off-diagonal blocks
            stored in single precision (their bytes halved), the state, the sums and each
            row's diagonal block still float64, the diagonal being minus the sum of the
            row's rounded blocks (so rigid translations still cost no force). K is
            perturbed by about 6e-8 relative. Bound (docs/guides/performance.md, measured
            over 1e5 steps against float64): 1e-6 of the largest displacement for runs
            loaded from rest; where rough initial fields keep every mode ringing, the
            error grows about 1e-6 per 1 000 steps (use float64 there). Gradients flow
            but to float32 accuracy only: the blocks' cotangents are float32 and the time
            loop sums them in float32 (measured against float64: 2e-6 relative on the
            vessel, 7e-4 on the cantilever over 2 000 steps); differentiate with float64
            blocks (the default) where that matters. Only with the grouped layout. (Under
            a traced E with nu fixed, E's cotangent is a float64 sum, <K_1 y_bar, u> with
            the rounded K_1: no float32 accumulation.)
        product: the form of the product K u. ``"fused"``: an unrolled sum over (slot,
            column component) that XLA fuses with the gathers into one loop streaming
            the blocks once, the fastest step (:func:`jaxsync.fem._sparse._matvec`);
            ``"compact"``: one gather of all neighbours and one reduction, a program of a
            few operations whatever the row width, compiled 1.7-3x faster and stepping
            up to 1.7x slower on XLA:CPU (benchmarks/bench_product.py); ``"auto"`` (default): the runners
            (:func:`jaxsync.simulate` and the solvers built on it) choose ``"compact"``
            for runs shorter than :data:`COMPACT_SLOT_STEPS` slot-steps (about 2e5 steps
            of the coarse cantilever, 2e4 of a 2 000-dof beam), ``"fused"`` otherwise
            and wherever the run length is not known (:func:`jaxsync.fem.build_system`
            alone, the timing harnesses). Both give K u to round-off.
        scale_min_nodes: the fewest nodes (rows of the mesh, or of each part) at which a
            traced E with a concrete nu is carried as the operator's scale (above). On
            smaller meshes XLA:CPU fuses the per-step dot product <K_1 y_bar, u> badly (it
            materializes the gathered neighbour values of K_1 y_bar and computes the sum
            twice; from about 1 500 nodes it hands the reduction to a library kernel and
            does not). Measured (checkpointed gradient in E and the damping, the beams of
            benchmarks/bench_gradients.py, against the Lame blocks, best of 3-5
            alternated calls): 1.4x slower at 117 nodes (1e4 steps), 1.2x slower at 496
            (5 000 steps); 1.4x faster at 2 989 nodes (2 000 steps), 1.4x at 12 221
            (1 000 steps), 1.8x at 36 225 (500 steps). 0: always.

    ``mode=Preassembled(blocks_dtype="float32")`` selects it in every solver, as the
    force models are selected.
    """

    layout: str = "grouped"
    blocks_dtype: str = "float64"
    scale_min_nodes: int = 1500
    product: str = "auto"
    name: str = dataclasses.field(default="preassembled", init=False)

    def __post_init__(self):
        if self.layout not in LAYOUTS:
            raise ProblemError(f"Preassembled(layout={self.layout!r}): choose one of {', '.join(LAYOUTS)}")
        if self.product not in PRODUCTS:
            raise ProblemError(f"Preassembled(product={self.product!r}): choose one of {', '.join(PRODUCTS)}")
        if self.blocks_dtype not in BLOCK_DTYPES:
            raise ProblemError(f"Preassembled(blocks_dtype={self.blocks_dtype!r}): choose one of "
                               f"{', '.join(BLOCK_DTYPES)}")
        if self.blocks_dtype == "float32" and self.layout != "grouped":
            raise ProblemError("Preassembled(blocks_dtype='float32') needs layout='grouped' (its diagonal "
                               "blocks kept in float64 keep the rounding error relative to the strains): "
                               "drop layout='ell'")
        if isinstance(self.scale_min_nodes, bool) or not isinstance(self.scale_min_nodes, int) \
                or self.scale_min_nodes < 0:
            raise ProblemError(f"Preassembled(scale_min_nodes={self.scale_min_nodes!r}): give a non-negative "
                               "integer (0: always carry a traced E as the stiffness's scale)")

    def for_run(self, problem, n_steps: int) -> "Preassembled":
        """This model with its product chosen for a run of ``n_steps`` steps of ``problem``:
        ``product="auto"`` becomes ``"compact"`` when the run streams fewer than
        :data:`COMPACT_SLOT_STEPS` stored blocks (the mesh's slots times ``n_steps``),
        where the compilation it saves outweighs its slower steps, else ``"fused"``; a
        product given explicitly is kept. Finite-strain problems are returned unchanged
        (their operator has no block product)."""
        if self.product != "auto" or _finite_strain(problem, self) is not None:
            return self
        adjacency = problem.operators.block_ell[0]
        slots = int(np.prod(np.shape(adjacency)))
        short = slots * int(n_steps) < COMPACT_SLOT_STEPS
        return dataclasses.replace(self, product="compact" if short else "fused")

    def operator(self, problem):
        """The stiffness of the whole mesh: a :class:`~jaxsync.fem.GroupedEll` (or
        with ``layout="ell"`` a :class:`~jaxsync.fem.BlockEll`), u and K u in the
        mesh's node numbering. The grouped layout works in reverse Cuthill-McKee order
        inside (it gathers u into it and scatters its rows back) where that order brings
        the neighbours much closer (:func:`jaxsync.fem._sparse.bandwidth_order`)."""
        if (tl := _finite_strain(problem, self)) is not None:  # no K of a nonlinear law: module docstring
            return tl.operator(problem)
        return self._mesh_stiffness(problem, problem.material)

    def unit_operators(self, problem) -> tuple:
        """(K_lambda, K_mu): the operators of the unit stiffnesses (lambda = 1, mu = 0 and
        lambda = 0, mu = 1 [dyn/cm^2]) of ``problem``'s mesh, in the layout :meth:`operator`
        gives it (the same groups, rows and node order; no scale). An operator whose blocks
        are lambda K_lambda + mu K_mu, combined group by group (``jax.tree_util.tree_map``
        over ``blocks``), is then the stiffness of any isotropic linear material there: the
        members of an ensemble (:mod:`jaxsync.solve`) are built so, with
        no assembly per member.

        Raises:
            ProblemError: float32 blocks (their diagonal is not linear in lambda and mu)."""
        if self.blocks_dtype != "float64":
            raise ProblemError("the unit operators K_lambda and K_mu are combined linearly, which float32 blocks "
                               "(diagonal = minus the sum of the rounded blocks) are not: use blocks_dtype='float64'")
        return tuple(self._mesh_stiffness(problem, _Lame(lam, mu)) for lam, mu in ((1.0, 0.0), (0.0, 1.0)))

    def _mesh_stiffness(self, problem, material):
        """The operator of the whole mesh for ``material`` (anything with ``lam`` and ``mu``)."""
        from .._sparse import bandwidth_order, permuted_block_ell

        adjacency, K_lambda, K_mu, _ = problem.operators.block_ell
        if self.layout == "ell":
            return self._stiffness(material, adjacency, K_lambda, K_mu)
        order = bandwidth_order(adjacency)
        if order is None:
            return self._stiffness(material, adjacency, K_lambda, K_mu)
        return self._stiffness(material, *permuted_block_ell(order, adjacency, K_lambda, K_mu), order=order)

    def part_operators(self, problem, parts, n_local: int):
        """The parts' stiffnesses stacked on a leading part axis, padded to ``n_local``
        rows (padding rows get zero force) and, with ``layout="grouped"``, to the same
        groups and group sizes in every part. Each part's rows are in its local order
        (:class:`jaxsync.parallel.PartLayout` orders the local nodes by reverse
        Cuthill-McKee)."""
        if (tl := _finite_strain(problem, self)) is not None:
            return tl.part_operators(problem, parts, n_local)
        columns, K_lambda, K_mu = _part_unit_blocks(problem.space, parts, n_local)
        return self._stiffness(problem.material, columns, K_lambda, K_mu)

    def _stiffness(self, material, columns, K_lambda, K_mu, order=None):
        """The operator of host unit blocks on ``columns`` (numbered in ``order``, if given:
        its rows go back to the caller's numbering, u is gathered into it). Stacked parts'
        ``columns`` (P, n, width) give a scale of shape (P,), if any."""
        from .._sparse import BlockEll, GroupedEll, grouped_layout, split_diagonal

        scale, lam, mu = self._moduli(material, int(np.shape(columns)[-2]))
        if scale is not None and np.ndim(columns) == 3:  # one per part (vmap / shard_map over the part axis)
            scale = jnp.broadcast_to(scale, np.shape(columns)[:1])

        def combine(a, b):  # constant (numpy) blocks K_1 under a scale, else lambda K_lambda + mu K_mu
            return lam * a + mu * b if scale is not None else lam * jnp.asarray(a) + mu * jnp.asarray(b)

        compact = self.product == "compact"
        if self.layout == "ell":
            return BlockEll(jnp.asarray(columns), jnp.asarray(combine(K_lambda, K_mu)), symmetric=True, scale=scale,
                            compact=compact)
        rows, group_columns, (lambdas, mus) = grouped_layout(columns, K_lambda, K_mu)
        blocks = [combine(a, b) for a, b in zip(lambdas, mus)]
        diagonal = None
        if self.blocks_dtype == "float32":  # off-diagonal blocks rounded, rows still summing to zero
            blocks, diagonal = zip(*(split_diagonal(b, jnp.float32) for b in blocks))
        n_rows = int(np.shape(columns)[-2])
        if order is not None:  # rows back to the caller's numbering (padding rows stay past the end)
            rows = [np.arange(n_rows) if r is None else r for r in rows]
            rows = [np.where(r < n_rows, order[np.minimum(r, n_rows - 1)], r).astype(np.int32) for r in rows]
        return GroupedEll(columns=tuple(jnp.asarray(c) for c in group_columns),
                          blocks=tuple(jnp.asarray(b) for b in blocks), symmetric=True,
                          rows=tuple(None if r is None else jnp.asarray(r) for r in rows),
                          n_rows=n_rows, diagonal=None if diagonal is None else tuple(jnp.asarray(d) for d in diagonal),
                          perm=None if order is None else jnp.asarray(order, dtype=jnp.int32), scale=scale,
                          compact=compact)

    def _moduli(self, material, n_rows: int):
        """(scale, lambda, mu) of the stiffness blocks of ``n_rows`` rows: (E, lambda / E,
        mu / E), the last two Python floats, when E is a traced scalar, nu a concrete
        number and ``n_rows >= scale_min_nodes`` (K = E K(E=1, nu): constant blocks under
        a traced scale); else (None, lambda, mu)."""
        from ...pytree import concrete_scalar, is_traced

        E = getattr(material, "E", None)
        if (n_rows < self.scale_min_nodes or E is None or not is_traced(E) or jnp.ndim(E) != 0
                or not dataclasses.is_dataclass(material) or concrete_scalar(getattr(material, "nu", None)) is None):
            return None, material.lam, material.mu
        unit = dataclasses.replace(material, E=1.0)
        return E, float(unit.lam), float(unit.mu)

    def max_stable_dt(self, problem):
        """The exact bound 2 / omega_max of M^-1 K [s] (:func:`jaxsync.fem.max_stable_dt`)."""
        if (tl := _finite_strain(problem, self)) is not None:
            return tl.max_stable_dt(problem)
        return _max_stable_dt(problem)


@dataclasses.dataclass(frozen=True)
class ElementRecompute:
    """The paper's element-recompute mode (Remark 2): each step forms every element's
    geometry, strain and stress and sums the element forces at the nodes
    (:class:`jaxsync.fem.forces.ElementStiffness`); nothing but the mesh is stored."""

    name: str = dataclasses.field(default="recompute", init=False)

    def operator(self, problem):
        """:class:`~jaxsync.fem.forces.ElementStiffness` of the whole mesh."""
        from ._element_force import ElementStiffness

        if (tl := _finite_strain(problem, self)) is not None:
            return tl.operator(problem)
        _check_p1(problem)
        mesh, m = problem.mesh, problem.material
        return ElementStiffness(jnp.asarray(mesh.points), jnp.asarray(mesh.tets, dtype=jnp.int32),
                                jnp.ones(mesh.n_elements), m.lam, m.mu)

    def part_operators(self, problem, parts, n_local: int):
        """The parts' :class:`~jaxsync.fem.forces.ElementStiffness` stacked on a
        leading part axis; padding elements repeat the part's element 0 with weight 0."""
        from ._element_force import ElementStiffness

        if (tl := _finite_strain(problem, self)) is not None:
            return tl.part_operators(problem, parts, n_local)
        _check_p1(problem)
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
        if (tl := _finite_strain(problem, self)) is not None:
            return tl.max_stable_dt(problem)
        return _max_stable_dt(problem)


def _check_p1(problem) -> None:
    """The element-recompute kernel forms P1 element quantities (one-point strains)."""
    if problem.element != "P1":
        raise ProblemError(f"mode='recompute' forms the element quantities of linear (P1) tetrahedra; this "
                           f"problem uses {problem.element} elements: use mode='preassembled'")


def _total_lagrangian():
    from ._total_lagrangian import TotalLagrangian

    return TotalLagrangian()


_MODELS = {"preassembled": Preassembled, "recompute": ElementRecompute, "total-lagrangian": _total_lagrangian}


def run_force_model(mode, problem, n_steps: int):
    """``mode`` for a run of ``n_steps`` steps of ``problem``: a force model that chooses
    its form by the run's length (:meth:`Preassembled.for_run`) chosen now, any other
    mode (a name or a model) as it is."""
    model = force_model(mode)
    choose = getattr(model, "for_run", None)
    return mode if choose is None else choose(problem, n_steps)


def force_model(mode: Mode | ForceModel = "preassembled") -> ForceModel:
    """The force model of ``mode``: ``"preassembled"`` (:class:`Preassembled`),
    ``"recompute"`` (:class:`ElementRecompute`), ``"total-lagrangian"``
    (:class:`jaxsync.fem.forces.TotalLagrangian`), or a force model, returned as it is.

    Raises:
        ProblemError: any other value, naming the allowed ones.
    """
    if not isinstance(mode, str) and all(hasattr(mode, a) for a in ("operator", "part_operators", "max_stable_dt")):
        return mode
    return _MODELS[check_option("mode", mode, Mode, error=ProblemError)]()


def _part_unit_blocks(space, parts, n_local: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(columns (P, n_local, width) int32, K_lambda and K_mu blocks (P, n_local, 3, width, 3))
    of the parts' own elements (``local_tets``: each element's nodes of ``space``, in the
    part's numbering), material-independent (numpy)."""
    import scipy.sparse as sp

    from .._assembly import element_blocks
    from .._sparse import block_ell_values, node_adjacency, pad_block_ell

    k_lambda, k_mu = element_blocks(space)
    size = k_lambda.shape[1]  # 3 x the nodes of an element: 12 (P1) or 30 (P2)
    columns, lambdas, mus = [], [], []
    for part in parts:
        dofs = (3 * part.local_tets[:, :, None] + np.arange(3)).reshape(-1, size)
        rows, cols = np.repeat(dofs, size, axis=1).ravel(), np.tile(dofs, (1, size)).ravel()
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

