"""Sparse matrices of a triangle mesh's edges."""

from __future__ import annotations

import numpy as np
import scipy.sparse


def corner_weight_matrix(faces: np.ndarray, corner_weights: np.ndarray, size: int):
    """The symmetric ``(size, size)`` CSR matrix W with W_ij the sum, over the faces with
    edge ij, of the weight of the corner opposite it: ``corner_weights[f, k]`` belongs to
    corner k of face f, opposite its edge (k + 1, k + 2). With half cotangents as the
    weights, diag(W 1) - W is the cotangent Laplacian."""
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]
        rows += [i, j]
        cols += [j, i]
        vals += [corner_weights[:, k], corner_weights[:, k]]
    return scipy.sparse.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size)
    ).tocsr()
