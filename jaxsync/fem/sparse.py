"""Node-blocked ELL sparse layout for the stiffness mat-vec in JAX.

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
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from ..pytree import pytree_dataclass, static_field

__all__ = ["BlockEll", "node_adjacency", "block_ell_values", "pad_block_ell"]


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
    """

    columns: jnp.ndarray
    blocks: jnp.ndarray
    symmetric: bool = static_field(default=False)

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
            return _symmetric_matvec(self.columns, self.blocks, jnp.asarray(u))
        return _matvec(self.columns, self.blocks, jnp.asarray(u))

    @property
    def shape(self) -> tuple[int, int]:
        return self.columns.shape


def _matvec(columns, blocks, u):
    """y = K u (:meth:`BlockEll.matvec`): u (n_cols, 3) -> y (n_rows, 3)."""
    n_rows = columns.shape[0]
    y = None
    for s in range(columns.shape[1]):
        index = jnp.broadcast_to(columns[:, s, None], (n_rows, 3))
        for j in range(3):
            # Padding slots point at the row's own node, so every index is in bounds.
            gathered = u[:, j].at[index].get(mode="promise_in_bounds")
            term = blocks[:, :, s, j] * gathered
            y = term if y is None else y + term
    return y


@jax.custom_vjp
def _symmetric_matvec(columns, blocks, u):
    """y = K u for a symmetric K, with a reverse pass written for it: the cotangent of u is
    K^T y_bar = K y_bar (the forward gather form again, no scatter-add), and that of the
    blocks the outer product y_bar[r, i] u[columns[r, s], j] (a gather). Autodiff of
    :func:`_matvec` would instead scatter-add 3 width times per product and keep every
    gathered neighbour value (3 width (n, 3) fields) for the reverse pass; here only u is
    kept. Measured on a 1e4-step gradient of the coarse cantilever: 5x faster, 5x less
    memory (issue 15)."""
    return _matvec(columns, blocks, u)


def _symmetric_matvec_fwd(columns, blocks, u):
    return _matvec(columns, blocks, u), (columns, blocks, u)


def _symmetric_matvec_bwd(residuals, y_bar):
    columns, blocks, u = residuals
    u_bar = _matvec(columns, blocks, y_bar)  # K^T y_bar = K y_bar
    blocks_bar = y_bar[:, :, None, None] * u[columns][:, None, :, :]  # (n_rows, 3, width, 3)
    return None, blocks_bar, u_bar


_symmetric_matvec.defvjp(_symmetric_matvec_fwd, _symmetric_matvec_bwd)


def node_adjacency(tets: np.ndarray, n_nodes: int) -> np.ndarray:
    """(n_nodes, width) int32 padded adjacency (node itself first, then neighbours in
    increasing order, padded with the node itself) of the mesh graph of ``tets``."""
    tets = np.asarray(tets)
    rows = np.repeat(tets, 4, axis=1).ravel()
    cols = np.tile(tets, (1, 4)).ravel()
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
