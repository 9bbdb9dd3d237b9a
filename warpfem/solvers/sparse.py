"""Block-sparse (3x3 blocks) matrices with a pattern built per mesh, which can grow.

The pattern holds a block for every pair of vertices that share an element (and every diagonal
block), plus any extra vertex pairs (``extra_pairs``: blocks that a form such as contact between
vertices of different elements adds). It is stored in a ``warp.sparse`` BSR matrix;
``block_index`` maps (element, local a, local b) to the block's position so assembly kernels add
element blocks in place with atomics and no triplet sort per Newton iteration, and
``pair_index(pairs)`` gives the positions of extra blocks.

:class:`HessianSystem` owns the current pattern, the block-value arrays that live in it (the
Hessian, the mass matrix, ...) and the linear solver: ``ensure_blocks(pairs)`` grows the pattern
when pairs are missing, moves every value array to the new pattern and makes the solver analyse
it again (a direct solver's symbolic analysis then happens once more; nothing happens when the
pattern already has the blocks).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import warp as wp
import warp.sparse as wsp
from warpfem.transfer import read, to_device


class BlockPattern:
    """The sparsity pattern of a mesh's 3x3-block matrices, on a device.

    Attributes:
        num_rows: number of block rows (vertices).
        nnz: number of stored blocks.
        offsets, columns: device int32 arrays (CSR layout of the blocks).
        block_index: device int32 array, (m * k * k,) position of block (e, a, b).
        block_indices: per element group, its part of ``block_index`` (several groups: the bodies of
            a multi-body model, ``elements_flat`` and ``nodes_per_element`` given as lists).
        diag_index: numpy int array (n,), position of each diagonal block.
    """

    def __init__(self, elements_flat: np.ndarray, nodes_per_element: int, num_vertices: int, *, device, block_type,
                 extra_pairs=None):
        n = int(num_vertices)
        # several element groups (bodies of different element types): elements_flat and
        # nodes_per_element are then lists, one entry per group; block_index holds the groups' element
        # blocks one after the other and block_indices[g] is group g's part (a view)
        multi = isinstance(nodes_per_element, (list, tuple))
        groups = (list(zip(elements_flat, nodes_per_element)) if multi else [(elements_flat, nodes_per_element)])
        self._groups = [(np.asarray(e), int(k)) for e, k in groups]
        self._elements_flat, self._k = (([e for e, _ in self._groups], [k for _, k in self._groups]) if multi
                                        else self._groups[0])
        row_parts, col_parts = [], []
        for e, k in self._groups:
            E = np.asarray(e, dtype=np.int64).reshape(-1, k)
            row_parts.append(np.repeat(E, k, axis=1).ravel())
            col_parts.append(np.tile(E, (1, k)).ravel())
        rows, cols = np.concatenate(row_parts), np.concatenate(col_parts)
        diag = np.arange(n, dtype=np.int64)
        extra = np.zeros((0, 2), dtype=np.int64) if extra_pairs is None else np.asarray(extra_pairs, dtype=np.int64).reshape(-1, 2)
        if extra.size and (extra.min() < 0 or extra.max() >= n):
            raise IndexError(f"extra block pair out of range [0, {n}): {extra[(extra < 0).any(1) | (extra >= n).any(1)][0]}")
        ek = np.unique(np.concatenate([extra[:, 0] * n + extra[:, 1], extra[:, 1] * n + extra[:, 0]]))  # symmetric
        extra = np.stack([ek // n, ek % n], axis=1)  # (unique by int64 keys: np.unique(axis=0) is ~20x slower)
        self.extra_pairs = extra
        keys = np.concatenate([rows * n + cols, diag * n + diag, extra[:, 0] * n + extra[:, 1]])
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
            to_device(r, wp.int32, device),
            to_device(c, wp.int32, device),
            wp.zeros(len(uniq), dtype=block_type, device=device),
            prune_numerical_zeros=False,
        )
        offsets = read(self.matrix.offsets, n + 1)
        columns = read(self.matrix.columns, self.nnz)
        if offsets[-1] != self.nnz or not np.array_equal(columns, c):
            raise RuntimeError("warp.sparse reordered the block pattern unexpectedly")
        self.offsets = self.matrix.offsets
        self.columns = self.matrix.columns
        self.rows_np = r
        self.cols_np = c
        self.block_index = to_device(inverse[: len(rows)].astype(np.int32), wp.int32, device)
        self.block_indices = [self.block_index]  # per element group (one group: the array itself)
        if multi:
            sizes = np.cumsum([0] + [len(r) for r in row_parts])
            self.block_indices = [self.block_index[int(a):int(b)] for a, b in zip(sizes[:-1], sizes[1:])]
        self.diag_index = inverse[len(rows):len(rows) + n]
        self._keys = uniq
        self.version = 0  # how many times the pattern grew (0: the mesh's own)

    def pair_index(self, pairs) -> np.ndarray:
        """Positions of the blocks (i, j) of ``pairs`` ((k, 2) ints); -1 where the pattern has none."""
        p = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        keys = p[:, 0] * self.num_rows + p[:, 1]
        pos = np.searchsorted(self._keys, keys)
        pos = np.minimum(pos, len(self._keys) - 1)
        return np.where(self._keys[pos] == keys, pos, -1)

    def contains(self, pairs) -> bool:
        """Whether every block (i, j) and (j, i) of ``pairs`` is in the pattern."""
        p = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        return bool(np.all(self.pair_index(p) >= 0) and np.all(self.pair_index(p[:, ::-1]) >= 0))

    def grown(self, pairs) -> "BlockPattern":
        """A new pattern: this one plus the blocks (i, j), (j, i) of ``pairs``."""
        extra = np.concatenate([self.extra_pairs, np.asarray(pairs, dtype=np.int64).reshape(-1, 2)])
        new = BlockPattern(self._elements_flat, self._k, self.num_rows, device=self.device, block_type=self.block_type,
                           extra_pairs=extra)
        new.version = self.version + 1
        return new

    def transfer(self, values, old: "BlockPattern"):
        """Block values of the pattern ``old`` moved into this (larger) pattern, zeros elsewhere."""
        pos = self.pair_index(np.stack([old.rows_np, old.cols_np], axis=1))
        if np.any(pos < 0):
            raise ValueError("the new pattern does not contain the old one")
        v = read(values)
        out = np.zeros((self.nnz, 3, 3), dtype=v.dtype)
        out[pos] = v
        return to_device(out, self.block_type, self.device)

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
        return to_device(blocks, self.block_type, self.device)

    def to_scipy(self, values) -> scipy.sparse.csr_matrix:
        """The (3n x 3n) matrix with these block values, as scipy CSR (float64)."""
        v = read(values).astype(np.float64) if hasattr(values, "numpy") else np.asarray(values)
        offsets = read(self.offsets, self.num_rows + 1)
        bsr = scipy.sparse.bsr_matrix((v, self.cols_np, offsets), shape=(3 * self.num_rows, 3 * self.num_rows))
        return bsr.tocsr()


class HessianSystem:
    """The pattern of a simulator's Newton matrices, the block values kept in it (``values[name]``:
    "hessian", "mass", ...) and the linear solver bound to it; the pattern grows on demand."""

    def __init__(self, pattern: BlockPattern, solver=None):
        self.pattern = pattern
        self.solver = solver
        self.values = {}
        self.listeners = []  # callables run after the pattern grew (e.g. contact's diagonal positions)
        self.growths = 0

    def new_values(self, name=None):
        v = self.pattern.new_values()
        if name is not None:
            self.values[name] = v
        return v

    @property
    def hessian_values(self):
        return self.values["hessian"]

    def ensure_blocks(self, pairs) -> bool:
        """Grow the pattern to hold the blocks of ``pairs`` ((k, 2) vertex pairs); True if it grew."""
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        if not len(pairs) or self.pattern.contains(pairs):
            return False
        old, new = self.pattern, self.pattern.grown(pairs)
        for name, v in list(self.values.items()):
            self.values[name] = new.transfer(v, old)
        self.pattern = new
        self.growths += 1
        if self.solver is not None:
            self.solver.analyse(new)
        for f in self.listeners:
            f(new)
        return True


class PatternView:
    """Stands for the current pattern of a :class:`HessianSystem` (attribute access is forwarded),
    so a form that keeps it follows the pattern when it grows."""

    def __init__(self, system: HessianSystem):
        self._system = system

    def __getattr__(self, name):
        return getattr(self._system.pattern, name)
