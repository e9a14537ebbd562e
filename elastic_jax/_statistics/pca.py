"""Tangent principal component analysis at a Karcher mean, under the split metric.

The shapes' initial velocities v_i at the mean mu (:class:`KarcherResult`'s velocities,
the logs of the shapes at mu) live in one tangent space, whose inner product is the
metric G_mu (math §3), not the Euclidean one of the grid's coordinates: a coordinate
PCA would weigh a bending mode against a stretching mode by how far the grid points move,
not by their elastic cost. With K shapes the modes lie in the span of the centred
velocities w_i = v_i - mean(v), so PCA is the eigen-decomposition of the K x K Gram matrix
W_ij = G_mu(w_i, w_j) / K (the dual, "snapshot" form): W a_k = lambda_k a_k gives the
variance lambda_k and the mode e_k = sum_i a_ik w_i / sqrt(K lambda_k), G_mu-orthonormal;
the scores s_ik = sqrt(K lambda_k) a_ik satisfy w_i = sum_k s_ik e_k.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._checks import check_int, check_positive, real_array
from .._errors import InputError
from .._geodesics.shooting import shoot
from .._geometry.metric import SplitMetric, metric_inner
from .._geometry.validation import as_surface
from .._results import record_repr


class TangentPCA(NamedTuple):
    """Principal modes of a collection's velocities at its mean; a pytree.

    Attributes:
        mean: ``(3, m, n)`` the base point mu.
        modes: ``(k, 3, m, n)`` G_mu-orthonormal directions, by decreasing variance.
        variances: ``(k,)`` lambda_k, the variance along each mode (G_mu units: distance^2).
        explained: ``(k,)`` lambda_k / sum of all variances.
        scores: ``(K, k)`` each shape's coordinates, G_mu(w_i, e_k).
        mean_velocity: ``(3, m, n)`` mean(v) (small at a converged Karcher mean).
    """

    mean: Float[Array, "3 m n"]
    modes: Float[Array, "k 3 m n"]
    variances: Float[Array, " k"]
    explained: Float[Array, " k"]
    scores: Float[Array, "K k"]
    mean_velocity: Float[Array, "3 m n"]

    __repr__ = record_repr


def _mean_and_velocities(karcher) -> tuple[Array, Array]:
    if hasattr(karcher, "mean") and hasattr(karcher, "velocities"):
        mean, velocities = karcher.mean, karcher.velocities
    elif isinstance(karcher, tuple) and len(karcher) == 2:
        mean, velocities = karcher
    else:
        raise InputError(
            "karcher must be a KarcherResult or a pair (mean (3, m, n), velocities "
            f"(K, 3, m, n)); got {type(karcher).__name__}"
        )
    mean = as_surface(mean, "mean")
    velocities = real_array(velocities, "velocities").astype(mean.dtype)
    if mean.ndim != 3 or velocities.ndim != 4 or velocities.shape[1:] != mean.shape:
        raise InputError(
            f"velocities must have shape (K, *mean.shape) = (K, {mean.shape}); got "
            f"{velocities.shape} for a mean of shape {mean.shape}"
        )
    if velocities.shape[0] < 2:
        raise InputError(f"PCA needs at least 2 velocities; got {velocities.shape[0]}")
    return mean, velocities


@jax.jit
def _pca(metric, mean, velocities):
    k = velocities.shape[0]
    centred = velocities - velocities.mean(axis=0, keepdims=True)
    gram = jax.vmap(lambda u: jax.vmap(lambda w: metric_inner(metric, mean, u, w))(centred))(
        centred
    )
    gram = 0.5 * (gram + gram.T) / k
    lam, vec = jnp.linalg.eigh(gram)
    lam, vec = lam[::-1], vec[:, ::-1]
    return centred, lam, vec


def tangent_pca(
    karcher,
    metric: SplitMetric,
    *,
    n_modes: int | None = None,
    rtol: float = 1e-10,
) -> TangentPCA:
    """Metric PCA of the velocities at a Karcher mean (module docstring; paper's statistics
    framework, with G_mu as the inner product).

    Args:
        karcher: a :class:`KarcherResult` (its ``mean`` and ``velocities``) or a pair
            ``(mean (3, m, n), velocities (K, 3, m, n))``.
        metric: the split metric the mean was computed with.
        n_modes: modes to keep (default: every mode whose variance exceeds ``rtol`` times
            the total, at most K - 1, the centred velocities' rank).
        rtol: that relative floor; never below K times the dtype's epsilon, where the
            rank's missing direction lies in float32.

    Returns:
        :class:`TangentPCA`.
    """
    mean, velocities = _mean_and_velocities(karcher)
    rtol = check_positive("rtol", rtol)
    centred, lam, vec = _pca(metric, mean, velocities)
    total = jnp.sum(jnp.clip(lam, 0.0))
    k = velocities.shape[0]
    if n_modes is None:
        # The centring leaves one eigenvalue at rounding level: 3e-8 of the total in
        # float32 (three random fields), above a floor of 1e-10, which then asked for K
        # modes and was refused.
        floor = max(rtol, k * float(jnp.finfo(lam.dtype).eps))
        n_modes = min(max(1, int(jnp.sum(lam > floor * total))), max(1, k - 1))
    n_modes = check_int("n_modes", n_modes, 1)
    if n_modes > velocities.shape[0] - 1:
        raise InputError(
            f"n_modes={n_modes} is above K - 1 = {velocities.shape[0] - 1}, the rank of the "
            "centred velocities"
        )
    lam, vec = lam[:n_modes], vec[:, :n_modes]
    if not bool(jnp.all(lam > 0)):
        raise InputError(f"mode {int(jnp.argmin(lam > 0))} has zero variance: ask for fewer modes")
    norms = jnp.sqrt(k * lam)
    modes = jnp.einsum("ik,i...->k...", vec / norms[None, :], centred)
    return TangentPCA(
        mean=mean,
        modes=modes,
        variances=lam,
        explained=lam / total,
        scores=vec * norms[None, :],
        mean_velocity=velocities.mean(axis=0),
    )


def mode_path(
    pca: TangentPCA,
    mode: int,
    metric: SplitMetric,
    *,
    sigmas: float = 2.0,
    n_times: int = 7,
    degree: int = 7,
    scheme: str = "midpoint",
) -> Float[Array, "P 3 m n"]:
    """The geodesic through the mean along a mode, from -sigmas to +sigmas standard
    deviations: two shots (:func:`shoot`) from the mean with velocities
    +-sigmas sqrt(lambda_k) e_k.

    Returns:
        ``(2 n_times - 1, 3, m, n)``: exp(-s sigma e) ... mean ... exp(+s sigma e). A
        shot whose Newton solve fails warns (ConvergenceWarning) and leaves NaN nodes at
        that end of the path (see :func:`shoot`); a finite path converged.
    """
    mode = check_int("mode", mode, 0)
    if mode >= pca.modes.shape[0]:
        raise InputError(f"mode={mode} is out of range: the PCA has {pca.modes.shape[0]} modes")
    sigmas = check_positive("sigmas", sigmas)
    v = sigmas * jnp.sqrt(pca.variances[mode]) * pca.modes[mode]
    options = {"n_times": n_times, "degree": degree, "scheme": scheme}
    ahead = shoot(pca.mean, v, metric, **options).path
    behind = shoot(pca.mean, -v, metric, **options).path
    return jnp.concatenate([behind[::-1], ahead[1:]])


def sigmas_reached(path, sigmas: float) -> list[float]:
    """How far a :func:`mode_path` got on each side: ``[low, high]`` in standard
    deviations (``-sigmas`` and ``+sigmas`` when both shots converged).

    Each half of the ``(2 T + 1, 3, m, n)`` path is a shot from the mean (the centre):
    a failed step leaves the nodes beyond it NaN, so the solved nodes are a run around
    the centre, T nodes of sigmas / T each way.

    Args:
        path: ``(2 T + 1, 3, m, n)``, a :func:`mode_path` (T >= 1).
        sigmas: the ``sigmas`` the path was shot to.

    Returns:
        ``[low, high]``: the signed standard deviations of the last solved node on each
        side.

    Example:
        >>> import numpy as np
        >>> path = np.zeros((5, 3, 5, 9))  # T = 2 nodes each way, shot to 2 sigmas
        >>> path[0] = np.nan  # the last step down failed
        >>> sigmas_reached(path, 2.0)
        [-1.0, 2.0]
    """
    import numpy as np

    path = np.asarray(path)
    if path.ndim != 4 or path.shape[1] != 3 or path.shape[0] < 3 or path.shape[0] % 2 == 0:
        raise InputError(
            f"path must have shape (2 T + 1, 3, m, n) with T >= 1 (a mode_path); got {path.shape}"
        )
    solved = np.isfinite(path).all(axis=(1, 2, 3))
    c = (len(solved) - 1) // 2
    down = int(np.argmin([*solved[c::-1], False]))  # solved nodes from the centre down
    up = int(np.argmin([*solved[c:], False]))
    return [sigmas * (1 - down) / c, sigmas * (up - 1) / c]
