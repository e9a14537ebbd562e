"""The frame a mesh carries with it: centroid, size and principal axes of its surface.

mesh_to_grid resamples a mesh in this frame so that its result follows rigid motions
and uniform scalings of the mesh (a moved mesh gives the moved grid): the grid's axes
are the mesh's principal axes, not the file's coordinate axes. Working in the frame
also puts every mesh at the same scale, which trimesh's absolute tolerances (ray hits
1e-6 behind the origin, closest points) assume.

The moments are exact integrals over the piecewise-linear surface: for a triangle T of
area A with corner values l_a, l_b, l_c of a linear function l,
int_T l^2 dA = A (l_a^2 + l_b^2 + l_c^2 + l_a l_b + l_b l_c + l_c l_a) / 6 and
int_T l^3 dA = A h3(l_a, l_b, l_c) / 10, h3 the sum of all ten cubic monomials, from
int_T lam_a^i lam_b^j lam_c^k dA = 2 A i! j! k! / (i + j + k + 2)!.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .._results import record_repr

# The frame counts as determined when the second-moment eigenvalues differ by more than
# this fraction of the largest and the two largest third moments (skewnesses) exceed it:
# below it, rounding or a mesh's symmetry decides the axes.
FRAME_TOL = 1e-6


class MeshFrame(NamedTuple):
    """Where a mesh sits: ``x = center + scale * axes @ y`` for y in the frame.

    Attributes:
        center: ``(3,)`` the area centroid of the surface.
        scale: the root-mean-square distance of the surface from its centroid.
        axes: ``(3, 3)`` rotation whose columns are the principal axes, largest second
            moment first, each signed so that its third moment is positive (the axis with
            the smallest third moment completes a right-handed frame).
        moments: ``(3,)`` second moments along the axes over scale^2 (they sum to 1).
        skewness: ``(3,)`` third moments along the axes over their second moment^(3/2).
        undetermined: empty when the axes are fixed by the surface; otherwise why not
            (equal second moments, or third moments that vanish: a symmetry).
    """

    __repr__ = record_repr

    center: np.ndarray
    scale: float
    axes: np.ndarray
    moments: np.ndarray
    skewness: np.ndarray
    undetermined: str

    def to_frame(self, x: np.ndarray) -> np.ndarray:
        """Points ``(..., 3)`` in the frame's coordinates y."""
        return ((x - self.center) / self.scale) @ self.axes

    def from_frame(self, y: np.ndarray) -> np.ndarray:
        """Points ``(..., 3)`` back from frame coordinates to the mesh's."""
        return self.center + self.scale * (y @ self.axes.T)


def principal_frame(vertices: np.ndarray, faces: np.ndarray) -> MeshFrame:
    """The area centroid, RMS size and signed principal axes of a triangle surface.

    Args:
        vertices: ``(V, 3)`` float64.
        faces: ``(F, 3)`` vertex indices.

    Returns:
        :class:`MeshFrame`; ``axes`` follows rigid motions of the mesh exactly (up to
        rounding) when ``undetermined`` is empty.
    """
    t = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    total = area.sum()
    center = area @ t.mean(axis=1) / total
    d = t - center
    s = d.sum(axis=1)
    # int_T x x^T dA = A (sum_k x_k x_k^T + (sum_k x_k)(sum_k x_k)^T) / 12
    second = np.einsum("f,fki,fkj->ij", area, d, d) + np.einsum("f,fi,fj->ij", area, s, s)
    second /= 12 * total
    eigenvalues, vectors = np.linalg.eigh(second)
    eigenvalues, vectors = eigenvalues[::-1], vectors[:, ::-1]
    scale = float(np.sqrt(eigenvalues.sum()))
    moments = eigenvalues / eigenvalues.sum()
    corner = d @ vectors  # (F, 3 corners, 3 axes)
    a, b, c = corner[:, 0], corner[:, 1], corner[:, 2]
    h3 = (
        a**3 + b**3 + c**3
        + a * a * (b + c) + b * b * (a + c) + c * c * (a + b)
        + a * b * c
    )  # fmt: skip
    skewness = (area @ h3) / (10 * total) / np.maximum(eigenvalues, 1e-300) ** 1.5
    reasons = []
    gaps = -np.diff(moments) / moments[0]
    for k, gap in enumerate(gaps):
        if gap <= FRAME_TOL:
            reasons.append(f"second moments {k + 1} and {k + 2} equal (gap {gap:.1e})")
    order = np.argsort(-np.abs(skewness))
    if abs(skewness[order[1]]) <= FRAME_TOL:
        small = ", ".join(f"{abs(skewness[k]):.1e}" for k in sorted(order[1:]))
        reasons.append(f"third moments vanish along two axes ({small}): a mirror or point symmetry")
    signs = np.sign(skewness)
    signs[signs == 0] = 1.0
    signs[order[2]] = 1.0
    axes = vectors * signs
    if np.linalg.det(axes) < 0:
        axes[:, order[2]] *= -1
    skewness = skewness * np.sign(np.einsum("ij,ij->j", axes, vectors))
    return MeshFrame(center, scale, axes, moments, skewness, "; ".join(reasons))
