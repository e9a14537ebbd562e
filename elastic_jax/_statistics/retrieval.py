"""Retrieval scores of a distance matrix against class labels: how well the nearest shapes
of each shape share its class (the shape-retrieval literature's nearest neighbour, first
tier and second tier; Shilane et al., "The Princeton Shape Benchmark", SMI 2004).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from jaxtyping import ArrayLike

from .._errors import InputError
from .._results import record_repr


class RetrievalScores(NamedTuple):
    """Leave-one-out retrieval scores, each in [0, 1] (1: every query perfect).

    Attributes:
        nearest_neighbour: the fraction of shapes whose nearest other shape has their label
            (leave-one-out 1-nearest-neighbour classification accuracy).
        first_tier: the mean over shapes of the fraction of their C - 1 classmates found
            among their C - 1 nearest other shapes (C: the size of the shape's class).
        second_tier: the same among the 2 (C - 1) nearest other shapes.
    """

    nearest_neighbour: float
    first_tier: float
    second_tier: float

    __repr__ = record_repr


def check_labels(labels, k: int, name: str = "labels") -> np.ndarray:
    """``labels`` as a ``(k,)`` array of class ids (integers, strings or finite floats),
    with at least two classes and at least two shapes in every class."""
    array = np.asarray(labels)
    if array.ndim != 1 or array.shape[0] != k:
        raise InputError(f"{name} must have shape ({k},), one per shape; got {array.shape}")
    if array.dtype.kind in "fc" and not np.all(np.isfinite(array)):
        raise InputError(f"{name} contains NaN or inf; give every shape a class")
    if array.dtype.kind not in "biufUSO":
        raise InputError(f"{name} must hold class ids (integers or strings); got {array.dtype}")
    classes, counts = np.unique(array, return_counts=True)
    if classes.size < 2:
        raise InputError(f"{name} has one class only ({classes[0]!r}); give at least two")
    if counts.min() < 2:
        lonely = classes[counts < 2].tolist()
        raise InputError(
            f"{name}: every class needs at least two shapes (a shape's classmates are what "
            f"is retrieved); classes with one: {lonely}"
        )
    return array


def check_distances(distances, name: str = "distances") -> np.ndarray:
    """A ``(K, K)`` finite, non-negative, symmetric matrix (to 1e-9 of its largest entry)."""
    d = np.asarray(distances, dtype=np.float64)
    if d.ndim != 2 or d.shape[0] != d.shape[1] or d.shape[0] < 2:
        raise InputError(f"{name} must be a square (K, K) matrix with K >= 2; got {d.shape}")
    if not np.all(np.isfinite(d)):
        raise InputError(f"{name} contains NaN or inf")
    if np.any(d < 0):
        raise InputError(f"{name} has negative entries; dissimilarities are >= 0")
    scale = float(np.max(d)) if d.size else 0.0
    asymmetry = float(np.max(np.abs(d - d.T)))
    if asymmetry > 1e-9 * max(scale, 1e-300):
        raise InputError(f"{name} is not symmetric (largest |D - D^T| = {asymmetry:.3g})")
    return d


def retrieval_scores(
    distances: ArrayLike,
    labels: ArrayLike,
) -> RetrievalScores:
    """Nearest neighbour, first tier and second tier of a distance matrix (leave one out).

    Each shape is a query; the other shapes are ranked by their distance to it (ties
    broken by index, smallest first). With C the size of the query's class, the nearest
    neighbour score counts a query whose first-ranked shape is a classmate, the first tier
    is the fraction of its C - 1 classmates among the first C - 1 ranked shapes, and the
    second tier that fraction among the first 2 (C - 1). Each is the mean over queries.

    Args:
        distances: ``(K, K)`` symmetric, non-negative (e.g. ``distance_matrix(...).distances``).
        labels: ``(K,)`` class ids; at least two classes, each with at least two shapes.

    Returns:
        :class:`RetrievalScores` (Python floats).

    Example:
        >>> import numpy as np
        >>> d = np.array([[0, 1, 4, 5], [1, 0, 3, 6], [4, 3, 0, 1], [5, 6, 1, 0]], float)
        >>> retrieval_scores(d, [0, 0, 1, 1]).nearest_neighbour
        1.0
    """
    d = check_distances(distances)
    labels = check_labels(labels, d.shape[0])
    k = d.shape[0]
    nearest, first, second = [], [], []
    for i in range(k):
        others = np.delete(np.arange(k), i)
        ranked = others[np.argsort(d[i, others], kind="stable")]
        hits = labels[ranked] == labels[i]
        c = int(np.sum(labels == labels[i]))
        nearest.append(float(hits[0]))
        first.append(float(np.sum(hits[: c - 1])) / (c - 1))
        second.append(float(np.sum(hits[: 2 * (c - 1)])) / (c - 1))
    return RetrievalScores(float(np.mean(nearest)), float(np.mean(first)), float(np.mean(second)))
