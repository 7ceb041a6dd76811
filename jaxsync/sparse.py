"""Node-blocked ELL sparse layout for the stiffness mat-vec in JAX.

Row i of the block matrix holds the 3x3 blocks K[i, j] for the (padded) list of nodes j
adjacent to node i. The mat-vec gathers whole 3-vectors ``u[j]`` (24 contiguous bytes)
instead of scalars, which is what makes XLA:CPU gathers affordable; padding slots point at
the row's own node with a zero block. Chosen by measurement (benchmarks/bench_stepper.py):
on this kind of machine it beats scalar ELL, BCOO and element-by-element products.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from .pytree import pytree_dataclass

__all__ = ["BlockEll", "node_adjacency", "block_ell_values"]


@pytree_dataclass
class BlockEll:
    """Square block-sparse matrix in node-blocked ELL format.

    Attributes:
        columns: (n_rows, width) int32 column node of each slot.
        blocks: (n_rows, width, 3, 3) values; zero in padding slots.
    """

    columns: jnp.ndarray
    blocks: jnp.ndarray

    def matvec(self, u):
        """y = K u for u of shape (n_cols, 3); returns (n_rows, 3)."""
        gathered = u[self.columns]  # (n_rows, width, 3)
        return jnp.einsum("rwij,rwj->ri", self.blocks, gathered)

    @property
    def shape(self) -> tuple[int, int]:
        return self.columns.shape


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
    """(n_nodes, width, 3, 3) blocks of the node-interleaved ``matrix`` on ``adjacency``;
    padding slots (repeats of the diagonal after the first) get zero blocks."""
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
    return out
