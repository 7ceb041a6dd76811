"""Node-blocked ELL sparse layouts for the stiffness mat-vec in JAX.

Row i of the block matrix holds the 3x3 blocks K[i, j] for the (padded) list of nodes j
adjacent to node i. The mat-vec reads the three components of ``u[j]`` (24 contiguous
bytes, one cache line) for each block; padding slots point at the row's own node with a
zero block.

The blocks are stored as (n_rows, 3, width, 3) -- row component, slot, column component --
and the product is an unrolled sum over (slot, column component), which XLA:CPU fuses
with the gathers into a single loop (see :meth:`BlockEll.matvec` for the form of the
gather that makes this fusion happen). Chosen by measurement (benchmarks/bench_stepper.py):
a reduction over a gathered (n, width, 3) array materializes the gather (1.4x slower at
250k dofs), the (n, width, 3, 3) order with an einsum is lowered to a batched dot (3x
slower), BCOO is 3-4x slower.

Three details of that loop were measured to matter (:func:`_matvec`, on this machine's
XLA:CPU, jax 0.10.2; benchmarks/bench_stepper.py): the sum runs in 8 independent partial
sums (one serial chain of 3 width fused multiply-adds per output was latency-bound:
1.3-1.4x slower); the arrays pass through an ``optimization_barrier`` so that XLA does
not hoist the index broadcasts (or a float32 -> float64 conversion of the blocks) out of
the time loop into width separate materialized arrays (5-15 %); and the column indices
are unsigned, which drops the negative-index clamp from every gather (7-18 %).

:class:`BlockEll` pads every row to the largest node degree. That is nearly free on a
structured mesh (the beams: mean degree 13.3-14.2, largest 15) but not on an
unstructured one: the generated coronary tree (:func:`jaxsync.coronary_mesh`) has mean
degree 11.8-12.7 and largest 25-26 (surface nodes of a thin wall have about 10
neighbours, interior ones 15-20), so 2.1x the real blocks are streamed.
:class:`GroupedEll` therefore splits the rows by degree into a few groups, each its own
block ELL of its own width, whose results are scattered into the output rows
(:func:`degree_widths` picks the widths: 3-4 groups on the vessel, 1.10-1.16x the real
blocks; 1 group on the beams). Alternatives measured on the 91k-dof vessel (CPU time of
the full step, the same round): concatenating the groups and gathering the output rows
back (XLA then fuses the groups' products into that gather and computes them in output
order: 1.1-1.4x slower than the scatter); a base ELL over all rows
plus overflow ELLs for the high-degree rows added through gather maps (as fast on the
vessel, 1.7x slower on the beams, where most rows overflow); sliced ELL slices
bucketed by width (that is this layout with many groups; more than 4 groups gained
nothing). The product per group is :func:`_matvec`, so every group keeps the fused form.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from ..pytree import pytree_dataclass, static_field

__all__ = ["BlockEll", "GroupedEll", "node_adjacency", "block_ell_values", "pad_block_ell",
           "degree_widths", "grouped_layout", "row_degrees", "split_diagonal", "bandwidth_order",
           "permuted_block_ell", "in_compact_form", "PARTIAL_SUMS"]


@pytree_dataclass
class BlockEll:
    """Square block-sparse matrix in node-blocked ELL format.

    Attributes:
        columns: (n_rows, width) int32 column node of each slot.
        blocks: (n_rows, 3, width, 3) values, ``blocks[r, i, s, j] = K[3 r + i,
            3 columns[r, s] + j]``; zero in padding slots.
        symmetric: K = K^T (stiffness and mass matrices assembled from symmetric element
            matrices). Then reverse mode uses K itself for the transpose product (a
            gather, like the forward product) instead of the scatter-adds autodiff would
            write, and keeps only u per product: see :func:`_symmetric_matvec`.
        scale: None (the matrix is ``blocks``), or a scalar s (one per part when stacked)
            multiplying them: the matrix is s K_1 with ``blocks`` holding K_1, applied as
            s (K_1 u). The stiffness of a material whose Young's modulus E is traced and
            whose Poisson ratio is fixed is E K(E=1): its blocks are then constants and E
            the one traced value, so that reverse mode through a time loop sums a scalar
            cotangent per product, s_bar += <y_bar, K_1 u> (= <K_1 y_bar, u> for a
            symmetric K, the transpose product it forms anyway), instead of carrying the
            blocks' cotangent, an array as large as K, across every step.
    """

    columns: jnp.ndarray
    blocks: jnp.ndarray
    symmetric: bool = static_field(default=False)
    scale: jnp.ndarray | None = None
    compact: bool = static_field(default=False)

    def matvec(self, u):
        """y = K u for u of shape (n_cols, 3); returns (n_rows, 3).

        Written as an unrolled sum over (slot, column component) of gathered values times
        block columns. Each gather has the output's own shape (n_rows, 3) -- the column
        index broadcast over the row component -- so that XLA fuses every gather, product
        and sum into one loop that streams the blocks once. Gathering a (n_rows, 3) row
        and broadcasting its columns instead makes XLA materialize each of the ``width``
        gathers (its fusion heuristics refuse to duplicate a broadcast gather): 1.6x
        slower at 250k dofs (benchmarks/bench_stepper.py)."""
        if self.symmetric:
            return _symmetric_matvec(self.columns, self.blocks, jnp.asarray(u), self.scale, self.compact)
        return _matvec(self.columns, self.blocks, jnp.asarray(u), scale=self.scale, compact=self.compact)

    def damped_matvec(self, u, velocity, beta):
        """K u + beta K v = K (u + beta v) for u, v = ``velocity`` (n_cols, 3) and the
        stiffness-proportional damping beta [s]: one product (a linear operator's tangent is
        itself; :mod:`jaxsync.fem`)."""
        return self.matvec(u + beta * velocity)

    @property
    def shape(self) -> tuple[int, int]:
        return self.columns.shape


PARTIAL_SUMS = 8
"""Independent partial sums per output entry in :func:`_matvec` (the terms are dealt to
them in turn and added pairwise at the end). One serial chain of 3 width fused
multiply-adds per output was latency-bound; 4 and 8 partial sums were measured alike
(1.3-1.4x faster than 1 on the 51k-dof beam, 1.2-1.4x on the vessel)."""


def _matvec(columns, blocks, u, diagonal=None, scale=None, compact=False):
    """y = K u (:meth:`BlockEll.matvec`): u (n_cols, 3) -> y (n_rows, 3), in ``u``'s dtype
    (float32 blocks are widened term by term: the sums are float64 for float64 u).

    ``diagonal``: (n_rows, 3, 3) blocks of slot 0 kept apart (in u's dtype), ``blocks``
    then holding slots 1.. only (the split storage of :class:`GroupedEll`). ``scale``: a
    scalar multiplying the sum (:attr:`BlockEll.scale`), or None. ``compact``: the
    product as one gather and one reduction (:func:`_compact_matvec`) instead of the
    unrolled sum."""
    if compact:
        y = _compact_matvec(columns, blocks, u, diagonal)
        return y if scale is None else _scaled(y, scale)
    # Kept together behind a barrier: inside a time loop XLA would otherwise hoist the
    # loop-invariant index broadcasts (and a blocks dtype conversion) out of the loop as
    # width separate (n_rows, 3) arrays, which the loop then streams instead of columns.
    columns, blocks, diagonal, u = jax.lax.optimization_barrier((columns, blocks, diagonal, u))
    # Unsigned indices: a gather clamps its index into range, and an unsigned one needs no
    # lower clamp. Padding slots point at the row's own node, so every index is in bounds.
    columns = columns.astype(jnp.uint32)
    n_rows = columns.shape[0]
    first = 0 if diagonal is None else 1
    partial = [None] * PARTIAL_SUMS
    k = 0
    for s in range(columns.shape[1]):
        index = jnp.broadcast_to(columns[:, s, None], (n_rows, 3))
        for j in range(3):
            gathered = u[:, j].at[index].get(mode="promise_in_bounds")
            block = diagonal[:, :, j] if s < first else blocks[:, :, s - first, j]
            term = block.astype(u.dtype) * gathered
            a = k % PARTIAL_SUMS
            partial[a] = term if partial[a] is None else partial[a] + term
            k += 1
    partial = [p for p in partial if p is not None]
    while len(partial) > 1:
        partial = [partial[i] + partial[i + 1] if i + 1 < len(partial) else partial[i]
                   for i in range(0, len(partial), 2)]
    return partial[0] if scale is None else _scaled(partial[0], scale)


def _compact_matvec(columns, blocks, u, diagonal=None):
    """y = K u (as :func:`_matvec`, without its scale) as one gather of every slot's
    neighbour, (n_rows, width, 3), and one reduction over (slot, column component).

    The program is a few operations whatever the width, where the unrolled sum is 3 width
    gathers and products: XLA:CPU compiles a run's programs 1.7-3x faster, and steps up
    to 1.7x slower on one device (the gathered array is materialized; alike within 5 % in
    partitioned runs, whose step the exchange dominates: benchmarks/bench_product.py).
    The same sums in another order: equal to round-off."""
    columns = columns.astype(jnp.uint32)
    first = 0 if diagonal is None else 1
    neighbours = u.at[columns[:, first:]].get(mode="promise_in_bounds")  # (n_rows, width - first, 3)
    y = jnp.sum(blocks.astype(u.dtype) * neighbours[:, None], axis=(2, 3))
    if diagonal is not None:
        own = u.at[columns[:, 0]].get(mode="promise_in_bounds")
        y = y + jnp.sum(diagonal.astype(u.dtype) * own[:, None, :], axis=2)
    return y


def _scaled(y, scale):
    """``scale * y`` in y's dtype (a scalar scale)."""
    return y * jnp.asarray(scale).astype(y.dtype)


@functools.partial(jax.custom_vjp, nondiff_argnums=(4,))
def _symmetric_matvec(columns, blocks, u, scale, compact=False):
    """y = K u for a symmetric K, with a reverse pass written for it: the cotangent of u is
    K^T y_bar = K y_bar (the forward gather form again, no scatter-add), and that of the
    blocks the outer product y_bar[r, i] u[columns[r, s], j] (a gather). Autodiff of
    :func:`_matvec` would instead scatter-add 3 width times per product and keep every
    gathered neighbour value (3 width (n, 3) fields) for the reverse pass; here only u is
    kept. Measured on a 1e4-step gradient of the coarse cantilever: 5x faster, 5x less
    memory.

    With a ``scale`` s (K = s K_1, ``blocks`` holding K_1: :attr:`BlockEll.scale`), the
    reverse pass forms w = K_1 y_bar once: u's cotangent is s w and s's the dot product
    <w, u> (= <y_bar, K_1 u>, K_1 being symmetric), and the blocks' s y_bar u^T.
    ``compact``: the form of the products (:func:`_matvec`), both passes."""
    return _matvec(columns, blocks, u, scale=scale, compact=compact)


def _symmetric_matvec_fwd(columns, blocks, u, scale, compact=False):
    return _matvec(columns, blocks, u, scale=scale, compact=compact), (columns, blocks, u, scale)


def _symmetric_matvec_bwd(compact, residuals, y_bar):
    columns, blocks, u, scale = residuals
    w = _matvec(columns, blocks, y_bar, compact=compact)  # K_1^T y_bar = K_1 y_bar
    u_bar, scale_bar, y_bar = _unscaled_cotangents(w, u, y_bar, scale)
    blocks_bar = y_bar[:, :, None, None] * u[columns][:, None, :, :]  # (n_rows, 3, width, 3)
    return None, blocks_bar.astype(blocks.dtype), u_bar, scale_bar


def _unscaled_cotangents(w, u, y_bar, scale):
    """(u_bar, scale_bar, the blocks' y_bar) of y = scale K_1 u given w = K_1 y_bar."""
    if scale is None:
        return w, None, y_bar
    scale = jnp.asarray(scale)
    return _scaled(w, scale), jnp.sum(w * u).astype(scale.dtype), _scaled(y_bar, scale)


_symmetric_matvec.defvjp(_symmetric_matvec_fwd, _symmetric_matvec_bwd)


@pytree_dataclass
class GroupedEll(BlockEll):
    """Square block-sparse matrix with its rows grouped by degree, each group a node-blocked
    ELL of its own width (why and the alternatives measured: the module docstring). A
    :class:`BlockEll` generalized (one group of all rows is a BlockEll), with the same
    symmetric reverse pass; build it from a BlockEll's host arrays with
    :func:`grouped_layout` (fields by keyword).

    Group g holds the rows ``rows[g]`` with (at most) ``widths[g]`` slots each; its
    product is the :class:`BlockEll` product of ``columns[g]``, ``blocks[g]``, scattered
    into those rows of the output. Rows of no group (padding nodes of a part) get 0.

    Attributes:
        columns: per group, (n_g, w_g) int32 column node of each slot (padding slots and
            rows point at an existing node with a zero block).
        blocks: per group, (n_g, 3, w_g, 3) values as in :class:`BlockEll`.
        symmetric: K = K^T: reverse mode uses K itself for the transpose product (the same
            gathers and scatters as the forward one) and keeps only u per product, as
            :class:`BlockEll` does.
        rows: per group, (n_g,) int32 output row of each group row; past ``n_rows`` (all
            different) on padding rows, whose products are dropped; or None for a single
            group of all rows in order (then no scatter is written).
        n_rows: rows of the matrix (a static int).
        diagonal: per group, (n_g, 3, 3) the diagonal blocks (slot 0) kept apart in the
            state's dtype, ``blocks[g]`` then holding slots 1..w_g - 1 only, and equal to
            minus the sum of them (the symmetric reverse pass differentiates it as that
            sum, folding its cotangent into theirs); or None. The
            float32 option stores the off-diagonal blocks in float32 (widened term by
            term, the sums carried in u's dtype) and the diagonal as minus the float64 sum
            of the row's rounded blocks (:func:`split_diagonal`): a stiffness's block rows
            sum to zero (it annihilates rigid translations), and so do the rounded ones,
            so that the rounding errs relative to the neighbour differences (the
            strains), not to the displacements: 27x smaller on the vessel (measured:
            docs/guides/performance.md).
        perm: (n_cols,) int32 or None: the columns number the nodes in this order (node
            ``perm[k]`` is column k; u is gathered into it first), while ``rows`` stay in
            the caller's numbering: a bandwidth-reducing order applied inside the
            operator (:func:`bandwidth_order`), results in the caller's numbering.
        scale: None, or a scalar multiplying the whole matrix (:attr:`BlockEll.scale`;
            one per part when stacked).

    All arrays may carry one leading part axis (the parts of a partition, stacked and
    padded alike: the same groups and shapes in every part) for ``vmap``/``shard_map``.
    """

    rows: tuple = ()
    n_rows: int = static_field(default=0)
    diagonal: tuple | None = None
    perm: jnp.ndarray | None = None

    def matvec(self, u):
        """y = K u for u of shape (n_cols, 3); returns (n_rows, 3)."""
        u = jnp.asarray(u)
        diagonal = (None,) * len(self.columns) if self.diagonal is None else self.diagonal
        args = (self.rows, self.columns, self.blocks, diagonal, self.perm, u, self.scale, self.n_rows,
                self.compact)
        return _grouped_symmetric(*args) if self.symmetric else _grouped_matvec(*args)

    @property
    def shape(self) -> tuple[int, int]:
        """(n_rows, n_rows)."""
        return (self.n_rows, self.n_rows)

    @property
    def widths(self) -> tuple[int, ...]:
        """Slots per row of each group."""
        return tuple(int(np.shape(c)[-1]) for c in self.columns)

    @property
    def slots(self) -> int:
        """Stored slots (padding included) of all groups (and parts)."""
        return int(sum(np.prod(np.shape(c)) for c in self.columns))


def _grouped_matvec(rows, columns, blocks, diagonal, perm, u, scale, n_rows, compact=False):
    """y = K u (:meth:`GroupedEll.matvec`). A scatter, not a gather, puts each group's
    rows in place: XLA fuses each group's product into its scatter and walks the group's
    own rows in order (measured: see the module docstring). ``scale``: None or a scalar
    multiplying each group's product (:attr:`BlockEll.scale`)."""
    if perm is not None:  # the layout's own node order (the columns number it)
        u = u.at[perm].get(mode="promise_in_bounds")
    y = None
    for r, c, b, d in zip(rows, columns, blocks, diagonal):
        part = _matvec(c, b, u, d, scale, compact)
        if r is None:
            y = part if y is None else y + part
            continue
        if y is None:
            y = jnp.zeros((n_rows, 3), part.dtype)
        y = y.at[r].set(part, mode="drop", unique_indices=True)
    return y


@functools.partial(jax.custom_vjp, nondiff_argnums=(7, 8))
def _grouped_symmetric(rows, columns, blocks, diagonal, perm, u, scale, n_rows, compact=False):
    """:func:`_grouped_matvec` for a symmetric K with its own reverse pass (as
    :func:`_symmetric_matvec`): u's cotangent is K y_bar, each group's blocks' (and
    diagonal blocks') the outer product of y_bar at its rows and the gathered u; with a
    ``scale`` s (K = s K_1), w = K_1 y_bar is formed once, u's cotangent is s w and s's
    <w, u>. Only u (in the caller's numbering: the state itself) is kept per product."""
    return _grouped_matvec(rows, columns, blocks, diagonal, perm, u, scale, n_rows, compact)


def _grouped_symmetric_fwd(rows, columns, blocks, diagonal, perm, u, scale, n_rows, compact=False):
    out = _grouped_matvec(rows, columns, blocks, diagonal, perm, u, scale, n_rows, compact)
    return out, (rows, columns, blocks, diagonal, perm, u, scale)


def _grouped_symmetric_bwd(n_rows, compact, residuals, y_bar):
    rows, columns, blocks, diagonal, perm, u, scale = residuals
    w = _grouped_matvec(rows, columns, blocks, diagonal, perm, y_bar, None, n_rows, compact)  # K_1^T y_bar = K_1 y_bar
    u_bar, scale_bar, y_bar = _unscaled_cotangents(w, u, y_bar, scale)
    # under a scale the blocks are constants: their cotangents below are unused, and the
    # compiled program drops them (no loop carries them: tests/solve/test_gradient_cotangent.py)
    if perm is not None:
        u = u[perm]
    blocks_bar, diagonal_bar = [], []
    for r, c, b, d in zip(rows, columns, blocks, diagonal):
        y_rows = y_bar if r is None else y_bar.at[r].get(mode="fill", fill_value=0.0)
        outer = y_rows[:, :, None, None] * u[c][:, None, :, :]  # (n_g, 3, w_g, 3)
        if d is None:
            blocks_bar.append(outer.astype(b.dtype))
            diagonal_bar.append(None)
        else:
            # the diagonal is minus the sum of the row's blocks: its cotangent folds into
            # theirs, y_bar_r (u_s - u_r), before the (float32) rounding, which then errs
            # relative to these differences; rounding y_bar_r u_s and y_bar_r u_r apart
            # and subtracting was measured 13 % off on the cantilever's gradient
            blocks_bar.append((outer[:, :, 1:] - outer[:, :, :1]).astype(b.dtype))
            diagonal_bar.append(jnp.zeros_like(d))
    return None, None, tuple(blocks_bar), tuple(diagonal_bar), None, u_bar, scale_bar


_grouped_symmetric.defvjp(_grouped_symmetric_fwd, _grouped_symmetric_bwd)


def in_compact_form(operator):
    """``operator`` with its product in the compact form (one gather of every slot and one
    reduction, :attr:`BlockEll.compact`) when it is a :class:`BlockEll` or
    :class:`GroupedEll`, else ``operator`` itself (element-by-element forces have no
    stored blocks). For programs that apply an operator a few times, where compiling is
    the cost: the start's conjugate gradients (:func:`jaxsync.fem.start_levels`)."""
    if isinstance(operator, BlockEll) and not operator.compact:
        return dataclasses.replace(operator, compact=True)
    return operator


def split_diagonal(blocks, dtype):
    """(off-diagonal blocks (..., n, 3, w - 1, 3) in ``dtype``, diagonal blocks (..., n, 3,
    3) in ``blocks``' dtype) of a stiffness's block-ELL ``blocks`` (..., n, 3, w, 3), slot
    0 the diagonal: the diagonal is minus the sum of the row's rounded off-diagonal blocks,
    so that the rounded rows sum to zero as K's do (JAX; traced values flow through:
    :class:`GroupedEll`'s symmetric reverse pass differentiates the diagonal as that sum,
    folded into the off-diagonal blocks' cotangents, and gives it none of its own)."""
    off = blocks[..., 1:, :].astype(dtype)
    return off, -off.astype(blocks.dtype).sum(axis=-2)


def bandwidth_order(columns: np.ndarray, *, gain: float = 16.0) -> np.ndarray | None:
    """Reverse Cuthill-McKee order (``scipy.sparse.csgraph.reverse_cuthill_mckee``) of
    the node graph of host block-ELL ``columns`` (n, width), or None when it would not
    bring a row's neighbours ``gain`` times closer on average (mean |i - j| over the
    stored blocks): the mesh's own order is then kept, with no permutation to pay.

    Measured (CPU time of the full step, benchmarks/bench_stepper.py's harness): on the
    generated coronary tree (gmsh order; RCM brings the neighbours 38-43x closer) the
    single-device step is 6 % faster at 91k and 270k dofs with the operator gathering u
    into RCM order (:attr:`GroupedEll.perm`) than in gmsh order, and 2 % faster with only
    the rows in RCM order; on the structured beams (6-10x closer: their order is regular
    already) the permutation gained nothing (-3 to +5 %), hence the threshold."""
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    columns = np.asarray(columns)
    n, width = columns.shape
    rows = np.repeat(np.arange(n), width)
    graph = sp.csr_matrix((np.ones(n * width, dtype=np.int8), (rows, columns.ravel())), shape=(n, n))
    order = reverse_cuthill_mckee(graph, symmetric_mode=True).astype(np.int64)
    position = np.empty(n, dtype=np.int64)
    position[order] = np.arange(n)
    before = np.abs(rows - columns.ravel()).mean()
    after = np.abs(position[rows] - position[columns.ravel()]).mean()
    return order if after * gain < before else None


def permuted_block_ell(order, columns: np.ndarray, *blocks: np.ndarray):
    """Host block-ELL arrays (the :func:`node_adjacency` layout) renumbered by ``order``
    (node ``order[k]`` becomes node k): (columns, *blocks) with rows and columns permuted."""
    position = np.empty(len(order), dtype=np.int64)
    position[order] = np.arange(len(order))
    return (position[np.asarray(columns)[order]].astype(np.int32), *(np.asarray(b)[order] for b in blocks))


def row_degrees(columns: np.ndarray) -> np.ndarray:
    """Stored blocks per row of host block-ELL ``columns`` (..., n_rows, width) in the
    layout of :func:`node_adjacency`: the diagonal slot plus every slot that does not
    repeat the row's own node (padding)."""
    columns = np.asarray(columns)
    own = np.arange(columns.shape[-2])[:, None]
    return 1 + (columns[..., 1:] != own).sum(axis=-1)


def degree_widths(degrees, *, max_groups: int = 4, row_cost: float = 3.0,
                  group_cost: float = 500.0) -> tuple[int, ...]:
    """Group widths (increasing; the last is the largest degree) for rows of the given
    degrees: the grouping that minimizes the stored slots, plus, once there are two groups
    or more, ``row_cost`` slots per row (every row is then scattered into place) and
    ``group_cost`` slots per group after the first (its own loop).

    The costs are measured (benchmarks/bench_stepper.py, full step): a second group
    cost 2 us a step on the 312-dof cantilever; on the beams, whose two degree groups
    (11 and 15) would save 7-11 % of the slots, grouping was 25 % slower at 15k and 51k
    dofs on an idle machine (two threads ran the ELL loop, apparently one the scatter) and 7 %
    faster at 93k, so they keep one group; the vessel's 3-4 groups save 45 % of the slots
    and were 1.8-1.9x faster than one ELL (3, 4 and 6 groups measured alike: at most
    ``max_groups``)."""
    values, counts = np.unique(np.asarray(degrees).ravel(), return_counts=True)
    n, k = int(counts.sum()), len(values)
    before = np.concatenate([[0], np.cumsum(counts)])
    best = np.full((max_groups + 1, k + 1), np.inf)
    best[0, 0] = 0.0
    cut = np.zeros((max_groups + 1, k + 1), dtype=int)
    for g in range(1, max_groups + 1):
        for j in range(1, k + 1):
            costs = best[g - 1, :j] + (before[j] - before[:j]) * values[j - 1]
            i = int(np.argmin(costs))
            best[g, j], cut[g, j] = costs[i], i
    totals = [best[g, k] + (row_cost * n if g > 1 else 0.0) + group_cost * (g - 1)
              for g in range(1, max_groups + 1)]
    g = 1 + int(np.argmin(totals))
    widths, j = [], k
    while j > 0:
        widths.append(int(values[j - 1]))
        j = cut[g, j]
        g -= 1
    return tuple(sorted(widths))


def grouped_layout(columns: np.ndarray, *blocks: np.ndarray, widths=None):
    """Host arrays of a :class:`GroupedEll` from those of a block ELL in the layout of
    :func:`node_adjacency` / :func:`block_ell_values` (slots of a row: the diagonal, its
    neighbours, then padding).

    Args:
        columns: (n_rows, width) or, stacked parts, (P, n_rows, width) int.
        blocks: any number of (..., n_rows, 3, width, 3) block arrays on ``columns`` (the
            unit stiffnesses K_lambda and K_mu, say): each is regrouped alike.
        widths: the groups' widths (default :func:`degree_widths` of all rows).

    Returns:
        ``(rows, columns, blocks)``: tuples over the groups (``blocks`` a tuple, per input
        array, of tuples over the groups), numpy; ``rows`` is ``(None,)`` for one group.
        Stacked parts share the groups: group g holds the rows of degree in
        (widths[g-1], widths[g]] of every part, padded to the largest count.
    """
    stacked = np.ndim(columns) == 3
    cols = np.asarray(columns) if stacked else np.asarray(columns)[None]
    blks = [np.asarray(b) if stacked else np.asarray(b)[None] for b in blocks]
    n_parts, n_rows, _ = cols.shape
    degree = row_degrees(cols)
    widths = degree_widths(degree) if widths is None else tuple(int(w) for w in widths)
    if widths[-1] < degree.max():
        raise ValueError(f"group widths {widths} below the largest row degree {int(degree.max())}")

    def unstack(x):
        return x if stacked else x[0]

    if len(widths) == 1:
        w = widths[0]
        return ((None,), (unstack(np.ascontiguousarray(cols[..., :w]).astype(np.int32)),),
                tuple((unstack(np.ascontiguousarray(b[..., :w, :])),) for b in blks))
    out_rows, out_cols, out_blocks = [], [], [[] for _ in blks]
    low = 0
    for w in widths:
        member = (degree > low) & (degree <= w)  # (P, n_rows)
        n_g = max(int(member.sum(axis=1).max()), 1)
        # padding rows: distinct indices past the end (dropped, and the scatter's indices stay unique)
        rows = np.broadcast_to(n_rows + np.arange(n_g, dtype=np.int32), (n_parts, n_g)).copy()
        group_cols = np.zeros((n_parts, n_g, w), dtype=np.int32)
        group_blocks = [np.zeros((n_parts, n_g, 3, w, 3), dtype=b.dtype) for b in blks]
        for p in range(n_parts):
            r = np.flatnonzero(member[p])
            rows[p, :len(r)] = r
            group_cols[p, :len(r)] = cols[p, r, :w]
            for src, dst in zip(blks, group_blocks):
                dst[p, :len(r)] = src[p, r, :, :w]
        out_rows.append(unstack(rows))
        out_cols.append(unstack(group_cols))
        for k, b in enumerate(group_blocks):
            out_blocks[k].append(unstack(b))
        low = w
    return tuple(out_rows), tuple(out_cols), tuple(tuple(b) for b in out_blocks)


def node_adjacency(tets: np.ndarray, n_nodes: int) -> np.ndarray:
    """(n_nodes, width) int32 padded adjacency (node itself first, then neighbours in
    increasing order, padded with the node itself) of the mesh graph of ``tets``
    (n_elements, k): two nodes are neighbours when an element holds both (k = 4 for P1
    tetrahedra, 10 for P2)."""
    tets = np.asarray(tets)
    k = tets.shape[1]
    rows = np.repeat(tets, k, axis=1).ravel()
    cols = np.tile(tets, (1, k)).ravel()
    graph = sp.coo_matrix((np.ones_like(rows, dtype=np.int8), (rows, cols)),
                          shape=(n_nodes, n_nodes)).tocsr()
    graph.sum_duplicates()
    degree = np.diff(graph.indptr)
    width = int(degree.max())
    adjacency = np.repeat(np.arange(n_nodes)[:, None], width, axis=1)
    # Vectorised fill: slot position of each entry within its row.
    row_of = np.repeat(np.arange(n_nodes), degree)
    slot = np.arange(graph.nnz) - np.repeat(graph.indptr[:-1], degree)
    neighbours = graph.indices
    # Put the diagonal first so that padding slots repeat it.
    is_diag = neighbours == row_of
    order = np.lexsort((neighbours, ~is_diag, row_of))
    adjacency[row_of, slot] = neighbours[order]
    return adjacency.astype(np.int32)


def block_ell_values(matrix: sp.spmatrix, adjacency: np.ndarray) -> np.ndarray:
    """(n_nodes, 3, width, 3) blocks (the :class:`BlockEll` layout) of the node-interleaved
    ``matrix`` on ``adjacency``; padding slots (repeats of the diagonal after the first)
    get zero blocks."""
    bsr = sp.csr_matrix(matrix).tobsr(blocksize=(3, 3))
    bsr.sort_indices()
    n_nodes, width = adjacency.shape
    # Look up block (i, adjacency[i, s]) in the BSR structure.
    indptr, indices = bsr.indptr, bsr.indices
    row_of = np.repeat(np.arange(n_nodes), np.diff(indptr))
    key_bsr = row_of.astype(np.int64) * n_nodes + indices
    key_ell = np.arange(n_nodes)[:, None].astype(np.int64) * n_nodes + adjacency
    pos = np.searchsorted(key_bsr, key_ell)
    pos = np.minimum(pos, len(key_bsr) - 1)
    present = key_bsr[pos] == key_ell
    out = np.where(present[..., None, None], bsr.data[pos], 0.0)
    padding = np.zeros_like(present)
    padding[:, 1:] = adjacency[:, 1:] == np.arange(n_nodes)[:, None]
    out[padding] = 0.0
    return np.ascontiguousarray(out.transpose(0, 2, 1, 3))


def pad_block_ell(columns: np.ndarray, blocks: np.ndarray, n_rows: int, width: int):
    """Pad a host block-ELL matrix to ``n_rows`` rows and ``width`` slots: new slots and
    rows point at the row's own node with zero blocks (new rows are padding nodes)."""
    rows, w = columns.shape
    own = np.arange(n_rows)[:, None]
    out_cols = np.repeat(own, width, axis=1).astype(columns.dtype)
    out_cols[:rows, :w] = columns
    out_blocks = np.zeros((n_rows, 3, width, 3), dtype=blocks.dtype)
    out_blocks[:rows, :, :w] = blocks
    return out_cols, out_blocks
