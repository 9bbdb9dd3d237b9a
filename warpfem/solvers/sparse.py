"""Block-sparse (3x3 blocks) matrices with a pattern built once per mesh.

The pattern holds a block for every pair of vertices that share an element (and every diagonal
block). It is stored in a ``warp.sparse`` BSR matrix; ``block_index`` maps (element, local a,
local b) to the block's position so assembly kernels add element blocks in place with atomics and
no triplet sort per Newton iteration.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import warp as wp
import warp.sparse as wsp


class BlockPattern:
    """The sparsity pattern of a mesh's 3x3-block matrices, on a device.

    Attributes:
        num_rows: number of block rows (vertices).
        nnz: number of stored blocks.
        offsets, columns: device int32 arrays (CSR layout of the blocks).
        block_index: device int32 array, (m * k * k,) position of block (e, a, b).
        diag_index: numpy int array (n,), position of each diagonal block.
    """

    def __init__(self, elements_flat: np.ndarray, nodes_per_element: int, num_vertices: int, *, device, block_type):
        k = int(nodes_per_element)
        n = int(num_vertices)
        E = np.asarray(elements_flat, dtype=np.int64).reshape(-1, k)
        rows = np.repeat(E, k, axis=1).ravel()
        cols = np.tile(E, (1, k)).ravel()
        diag = np.arange(n, dtype=np.int64)
        keys = np.concatenate([rows * n + cols, diag * n + diag])
        uniq, inverse = np.unique(keys, return_inverse=True)
        r = (uniq // n).astype(np.int32)
        c = (uniq % n).astype(np.int32)
        self.num_rows = n
        self.nnz = len(uniq)
        self.device = device
        self.block_type = block_type
        self.matrix = wsp.bsr_zeros(n, n, block_type=block_type, device=device)
        wsp.bsr_set_from_triplets(
            self.matrix,
            wp.array(r, dtype=wp.int32, device=device),
            wp.array(c, dtype=wp.int32, device=device),
            wp.zeros(len(uniq), dtype=block_type, device=device),
            prune_numerical_zeros=False,
        )
        offsets = self.matrix.offsets.numpy()[: n + 1]
        columns = self.matrix.columns.numpy()[: self.nnz]
        if offsets[-1] != self.nnz or not np.array_equal(columns, c):
            raise RuntimeError("warp.sparse reordered the block pattern unexpectedly")
        self.offsets = self.matrix.offsets
        self.columns = self.matrix.columns
        self.rows_np = r
        self.cols_np = c
        self.block_index = wp.array(inverse[: len(rows)].astype(np.int32), dtype=wp.int32, device=device)
        self.diag_index = inverse[len(rows):]

    def new_values(self):
        """A zeroed device array of blocks for this pattern."""
        return wp.zeros(self.nnz, dtype=self.block_type, device=self.device)

    def values_from_scalar_matrix(self, A: scipy.sparse.spmatrix):
        """Blocks a_ij I3 for a scalar (n x n) matrix whose pattern is inside this one (mass)."""
        A = scipy.sparse.csr_matrix(A)
        vals = np.asarray(A[self.rows_np, self.cols_np]).ravel()
        if not np.isclose(vals.sum(), A.sum(), rtol=1e-12, atol=0.0):
            raise ValueError("scalar matrix has entries outside the block pattern")
        blocks = vals[:, None, None] * np.eye(3)[None]
        return wp.array(blocks, dtype=self.block_type, device=self.device)

    def to_scipy(self, values) -> scipy.sparse.csr_matrix:
        """The (3n x 3n) matrix with these block values, as scipy CSR (float64)."""
        v = values.numpy().astype(np.float64) if hasattr(values, "numpy") else np.asarray(values)
        offsets = self.offsets.numpy()[: self.num_rows + 1]
        bsr = scipy.sparse.bsr_matrix((v, self.cols_np, offsets), shape=(3 * self.num_rows, 3 * self.num_rows))
        return bsr.tocsr()
