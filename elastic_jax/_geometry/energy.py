"""Discrete path energy and length under the split metric (math §4)."""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, ArrayLike, Float

from .._checks import check_choice, check_int
from .._errors import InputError
from .._options import SCHEMES
from .differential import interior_frame
from .grid import integrate_interior, interior_weights
from .metric import SplitMetric, split_bilinear
from .validation import as_surface


def _density(metric, b1, b2, v1, v2):
    return split_bilinear(metric, b1, b2, v1, v2, v1, v2)


@jax.custom_jvp
def speed_density(metric: SplitMetric, b1: Array, b2: Array, v1: Array, v2: Array) -> Array:
    """G_b(v, v) at each point, for columns ``b1, b2, v1, v2 (..., 3, p, q)``: ``(..., p, q)``.

    The path energy's integrand. Its derivative is taken from the partials with respect
    to its 12 inputs, computed once per point (the custom rule below), instead of by
    autodiff through split_bilinear's graph.
    """
    return _density(metric, b1, b2, v1, v2)


def _density_partials(metric, frames):
    value, pullback = jax.vjp(lambda *x: _density(metric, *x), *frames)
    return value, pullback(jnp.ones_like(value))


@functools.partial(speed_density.defjvp, symbolic_zeros=True)
def _speed_density_jvp(primals, tangents):
    # XLA:CPU fuses the pointwise graph into each of its consumers: the gradient's pads
    # and slices (one per time and coordinate neighbour) each recomputed it, about 65 %
    # of the time of a value and gradient. A conditional's results are buffers that no
    # consumer can fuse into, so behind one the partials are computed once per point:
    # 50 x 99, N 13, float64, the value and gradient 3.95 -> 2.95 ms (median, 2 cores)
    # and XLA's count 108 -> 53 MFLOP. Its predicate is a runtime value that always
    # holds (the other branch would give zeros of the right shapes). On GPU a
    # conditional synchronizes with the host, and under vmap a batched predicate turns
    # it into a select of both branches: plain autodiff's graph there.
    metric, *frames = primals
    d_metric, *d_frames = tangents
    if jax.default_backend() == "cpu":

        def nothing(frames):
            value = jnp.zeros(frames[0].shape[:-3] + frames[0].shape[-2:], frames[0].dtype)
            return value, tuple(jnp.zeros_like(x) for x in frames)

        holds = jnp.isfinite(frames[0].reshape(-1)[0])
        value, partials = jax.lax.cond(
            holds, functools.partial(_density_partials, metric), nothing, tuple(frames)
        )
    else:
        value, partials = _density_partials(metric, tuple(frames))
    tangent = jnp.zeros_like(value)
    for partial, d_x in zip(partials, d_frames, strict=True):
        if not isinstance(d_x, SymbolicZero):
            tangent = tangent + jnp.sum(partial * d_x, axis=-3)
    if any(not isinstance(t, SymbolicZero) for t in jax.tree_util.tree_leaves(d_metric)):
        # Linear in the coefficients: the derivative along d_metric is the density with
        # the coefficients replaced by their tangents (zeros where symbolic).
        coefficients = [
            jnp.zeros((), value.dtype) if isinstance(t, SymbolicZero) else t
            for t in jax.tree_util.tree_leaves(d_metric, is_leaf=_is_symbolic)
        ]
        tangent = tangent + _density(SplitMetric.tree_unflatten(None, coefficients), *frames)
    return value, tangent


def _is_symbolic(x) -> bool:
    return isinstance(x, SymbolicZero)


def frame_speeds2(metric: SplitMetric, a1: Array, a2: Array, scheme: str) -> tuple[Array, Array]:
    """Squared speeds and time-quadrature weights of a path given by its interior frames
    (:func:`pointwise_speeds2` integrated over the grid's interior points)."""
    density, weights = pointwise_speeds2(metric, a1, a2, scheme)
    return integrate_interior(density), weights


def step_frames(a1: Array, a2: Array, scheme: str) -> tuple[Array, Array, Array, Array, Array]:
    """Each time step's base frame and velocity under ``scheme`` and the time weights:
    (base1, base2, v1, v2) ``(..., T', 3, p, q)`` each and ``(T',)``, what
    :func:`pointwise_speeds2` evaluates the metric at (schemes as there)."""
    n_times = a1.shape[-4]
    t = n_times - 1
    if scheme in ("forward", "midpoint"):
        if scheme == "forward":
            base1, base2 = a1[..., :-1, :, :, :], a2[..., :-1, :, :, :]
        else:
            base1 = 0.5 * (a1[..., 1:, :, :, :] + a1[..., :-1, :, :, :])
            base2 = 0.5 * (a2[..., 1:, :, :, :] + a2[..., :-1, :, :, :])
        v1 = t * (a1[..., 1:, :, :, :] - a1[..., :-1, :, :, :])
        v2 = t * (a2[..., 1:, :, :, :] - a2[..., :-1, :, :, :])
        weights = jnp.full((t,), 1.0 / t, dtype=a1.dtype)
    else:

        def central(a):
            inner = 0.5 * (a[..., 2:, :, :, :] - a[..., :-2, :, :, :])
            first = a[..., 1:2, :, :, :] - a[..., :1, :, :, :]
            last = a[..., -1:, :, :, :] - a[..., -2:-1, :, :, :]
            return t * jnp.concatenate([first, inner, last], axis=-4)

        base1, base2, v1, v2 = a1, a2, central(a1), central(a2)
        weights = jnp.full((n_times,), 1.0 / t, dtype=a1.dtype)
        weights = weights.at[0].mul(0.5).at[-1].mul(0.5)
    return base1, base2, v1, v2, weights


def pointwise_speeds2(
    metric: SplitMetric, a1: Array, a2: Array, scheme: str
) -> tuple[Array, Array]:
    """G_b(v, v) of each step at each point, ``(..., T', p, q)``, and the time weights.

    ``a1, a2 (..., N, 3, m-2, n-1)`` are the columns of df_k (see ``interior_frame``);
    the differential is linear, so d(f_{k+1} - f_k) = df_{k+1} - df_k.
    forward: v_k = T (f_{k+1} - f_k) at f_k, k = 0..T-1, weights 1/T.
    central: v_k = T (f_{k+1} - f_{k-1}) / 2 at interior k, one-sided at the two ends,
    trapezoid weights (1/2, 1, ..., 1, 1/2) / T: symmetric under reversing the path.
    midpoint: v_k = T (f_{k+1} - f_k) at (f_k + f_{k+1}) / 2, weights 1/T: the midpoint
    rule for the energy of the piecewise-linear path through the frames.
    """
    base1, base2, v1, v2, weights = step_frames(a1, a2, scheme)
    return speed_density(metric, base1, base2, v1, v2), weights


def frame_energy(metric: SplitMetric, a1: Array, a2: Array, scheme: str) -> Array:
    """Path energy from interior frames ``(..., N, 3, m-2, n-1)`` (see :func:`path_energy`)."""
    speeds2, weights = frame_speeds2(metric, a1, a2, scheme)
    return jnp.einsum("...k,k->...", speeds2, weights)


@functools.partial(jax.jit, static_argnames=("scheme",))
def _path_energy(metric, path, *, scheme):
    return frame_energy(metric, *interior_frame(path), scheme)


@functools.partial(jax.jit, static_argnames=("scheme",))
def _path_length(metric, path, *, scheme):
    speeds2, weights = frame_speeds2(metric, *interior_frame(path), scheme)
    return jnp.einsum("...k,k->...", jnp.sqrt(speeds2), weights)


def as_path(path, name: str = "path") -> Array:
    """Check a path ``(..., N, 3, m, n)`` with N >= 2 (every frame a well-formed immersion)."""
    path = as_surface(path, name)
    if path.ndim < 4 or path.shape[-4] < 2:
        raise InputError(f"{name} must have shape (..., N, 3, m, n) with N >= 2; got {path.shape}")
    return path


def check_scheme(scheme: str) -> None:
    check_choice("scheme", scheme, SCHEMES)


def path_energy(
    metric: SplitMetric, path: Float[ArrayLike, "*batch N 3 m n"], scheme: str = "midpoint"
) -> Float[Array, "*batch"]:
    """Discrete energy of a path of surfaces (:ref:`math §4 <math-4>`; paper eq. (4.4)).

    midpoint (default): E = (1/T) sum_{k=0}^{T-1} G_{(f_k + f_{k+1})/2}(T (f_{k+1} - f_k)),
    T = N - 1: the midpoint rule for the energy of the piecewise-linear path through the
    frames; second order and symmetric under reversal. forward (:ref:`math §4 <math-4>`,
    the paper's): the metric at f_k instead; first order, and its minimizers exploit large
    steps (:doc:`/guides/settings`, "What the distance means"). central: velocities by
    central differences at
    interior times (one-sided at the ends) and the trapezoid rule in time; it cannot see
    an odd-even zigzag of the frames. The geodesic distance is sqrt(min E).

    Args:
        metric: the split metric coefficients.
        path: ``(..., N, 3, m, n)`` surfaces f_0 .. f_{N-1} at t_k = k / (N - 1), N >= 2.
        scheme: ``"midpoint"``, ``"forward"`` or ``"central"``.

    Returns:
        ``(...)`` energies.

    Example:
        >>> import elastic_jax as ej
        >>> from elastic_jax import shapes
        >>> f1 = shapes.sample(shapes.sphere, 25, 49)
        >>> path = ej.straight_path(f1, 2.0 * f1, 13)
        >>> e = ej.path_energy(ej.SplitMetric(1.0, 1.0, 0.1, 0.0), path)  # ~ 8 pi b (2 - 1)^2
    """
    check_scheme(scheme)
    return _path_energy(metric, as_path(path), scheme=scheme)


def path_length(
    metric: SplitMetric, path: Float[ArrayLike, "*batch N 3 m n"], scheme: str = "midpoint"
) -> Float[Array, "*batch"]:
    """Discrete length of a path of surfaces (:ref:`math §4 <math-4>`).

    L = (1/T) sum_{k=0}^{T-1} sqrt(G_{b_k}(T (f_{k+1} - f_k))) with b_k = (f_k + f_{k+1})/2
    (midpoint, default) or f_k (forward); central as in :func:`path_energy`.
    L^2 <= E with equality for constant speed.

    Args:
        metric: the split metric coefficients.
        path: ``(..., N, 3, m, n)``, N >= 2.
        scheme: ``"midpoint"``, ``"forward"`` or ``"central"``.

    Returns:
        ``(...)`` lengths.
    """
    check_scheme(scheme)
    return _path_length(metric, as_path(path), scheme=scheme)


class EnergyDensity(NamedTuple):
    """Where a path's energy lies: one ``(..., m, n)`` field per term of the split metric.

    Each field is the path's energy at each grid point: the term's density integrated
    over time (the scheme's time weights) times the point's quadrature weight, so that
    the five fields sum over the grid to energies, and ``shear + area + bending +
    rotation == total`` sums to :func:`path_energy` (same scheme). The pole rows carry no
    quadrature weight and are zero; column 0 and the seam column n - 1 (the same points)
    share their energy equally, as :func:`~elastic_jax.quadrature_weights` shares their
    weight, so that a field divided by those weights (where nonzero) is the energy per
    unit area of the parameter sphere.

    Attributes:
        shear: ``(..., m, n)`` the a-term: the change of shape at fixed area (math §3,
            xi_m).
        area: ``(..., m, n)`` the b-term: the change of area (xi_vol).
        bending: ``(..., m, n)`` the c-term: the motion normal to the surface (xi_perp).
        rotation: ``(..., m, n)`` the d-term: the rotation within the tangent plane (xi_0).
        total: ``(..., m, n)`` their sum.
    """

    shear: Float[Array, "*batch m n"]
    area: Float[Array, "*batch m n"]
    bending: Float[Array, "*batch m n"]
    rotation: Float[Array, "*batch m n"]
    total: Float[Array, "*batch m n"]

    def on_vertices(self, vertex_map) -> EnergyDensity:
        """The fields at the vertices of the mesh an input was read from, ``(..., V)``
        numpy arrays: each field's density read at the vertices' directions times their
        shares of the parameter sphere (``io.VertexMap.to_vertex_values``), so that
        they sum to about the grid's energy and can be written beside the input's own
        mesh (``vertex_map.to_mesh``). The grid's points must carry that input's
        parametrization: a geodesic between parametrized surfaces, or a shape geodesic
        with the map of f2 (its path ends at R f2 in f2's parametrization; its other end
        is f1 o gamma, whose points are not f1's vertices).

        Args:
            vertex_map: the :class:`~elastic_jax.io.VertexMap` of the input (from
                ``io.mesh_to_grid`` or ``io.load_surface`` with ``return_map=True``).
        """
        return EnergyDensity(*(vertex_map.to_vertex_values(field) for field in self))


@functools.partial(jax.jit, static_argnames=("scheme",))
def _energy_density(metric, path, *, scheme):
    a1, a2 = interior_frame(path)
    m, n = path.shape[-2:]
    weights = interior_weights(m, n, path.dtype)
    zero = jnp.zeros((), path.dtype)
    coefficients = jax.tree_util.tree_leaves(metric)
    fields = []
    for k in range(4):
        # The metric is linear in its coefficients: each term is the density under the
        # metric with that coefficient alone (built without __post_init__, which would
        # reject traced coefficients).
        alone = [c if j == k else zero for j, c in enumerate(coefficients)]
        term = SplitMetric.tree_unflatten(None, alone)
        density, time_weights = pointwise_speeds2(term, a1, a2, scheme)
        energy = jnp.einsum("...kij,k,ij->...ij", density, time_weights, weights)
        seam = 0.5 * energy[..., :1]
        energy = jnp.concatenate([seam, energy[..., 1:], seam], axis=-1)
        poles = jnp.zeros(energy.shape[:-2] + (1, n), path.dtype)
        fields.append(jnp.concatenate([poles, energy, poles], axis=-2))
    return EnergyDensity(*fields, sum(fields))


def energy_density(
    metric: SplitMetric, path: Float[ArrayLike, "*batch N 3 m n"], scheme: str = "midpoint"
) -> EnergyDensity:
    """The path energy of each grid point, split by the terms of the split metric.

    With the scheme's base frames b_k, velocities v_k and time weights w_k
    (:func:`path_energy`) and the grid's quadrature weights q_ij (:ref:`math §2
    <math-2>`), the field of the term X in {a: shear, b: area, c: bending, d: rotation}
    is ``E_X[i, j] = q_ij sum_k w_k X G^X_{b_k}(v_k, v_k)[i, j]`` with math §3's
    decomposition ``G = a |xi_m|^2 + b |xi_vol|^2 + c |xi_perp|^2 + d |xi_0|^2`` (paper
    eq. (3.4)). The fields partition the energy: sum_ij of ``total`` is
    ``path_energy(metric, path, scheme)`` (to rounding), and a term whose coefficient is
    zero is zero everywhere.

    Args:
        metric: the split metric coefficients.
        path: ``(..., N, 3, m, n)`` surfaces f_0 .. f_{N-1} at t_k = k / (N - 1), N >= 2
            (a geodesic's ``path``).
        scheme: ``"midpoint"``, ``"forward"`` or ``"central"``.

    Returns:
        :class:`EnergyDensity`, fields ``(..., m, n)``.

    Example:
        >>> import elastic_jax as ej
        >>> from elastic_jax import shapes
        >>> f = shapes.sample(shapes.sphere, 13, 25)
        >>> metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
        >>> fields = ej.energy_density(metric, ej.straight_path(f, 2 * f, 5))
        >>> bool(fields.shear.sum() < 1e-10 * fields.area.sum())  # a scaling only changes area
        True
    """
    check_scheme(scheme)
    return _energy_density(metric, as_path(path), scheme=scheme)


def straight_path(
    f1: Float[ArrayLike, "*batch1 3 m n"], f2: Float[ArrayLike, "*batch2 3 m n"], n_times: int
) -> Float[Array, "*batch N 3 m n"]:
    """The straight line f(t_k) = (1 - t_k) f1 + t_k f2, t_k = k / (n_times - 1) (paper eq. (4.1)).

    Args:
        f1, f2: ``(..., 3, m, n)`` end surfaces on the same grid.
        n_times: N >= 2, the number of time points (end points included).

    Returns:
        ``(..., N, 3, m, n)``; the end frames are f1 and f2 exactly.
    """
    f1 = as_surface(f1, "f1", check_immersion=False)
    f2 = as_surface(f2, "f2", check_immersion=False)
    if f1.shape[-3:] != f2.shape[-3:]:
        raise InputError(f"f1 and f2 must be on the same grid; got {f1.shape} and {f2.shape}")
    n_times = check_int("n_times", n_times, 2)
    f1, f2 = jnp.broadcast_arrays(f1, f2)
    batch_ones = (1,) * (f1.ndim - 3)
    t = jnp.linspace(0.0, 1.0, n_times, dtype=f1.dtype).reshape(batch_ones + (n_times, 1, 1, 1))
    # f1 + t (f2 - f1) is exactly constant when f1 = f2; it rounds at t = 1, so the end
    # points are set exactly.
    path = f1[..., None, :, :, :] + t * (f2 - f1)[..., None, :, :, :]
    return path.at[..., 0, :, :, :].set(f1).at[..., -1, :, :, :].set(f2)
