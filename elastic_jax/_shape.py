"""Geodesics between shapes: registration modulo reparametrization and rigid motion.

Paper sections 4.2-4.3 (Algorithms 2 and 3, Remark 4), MATH.md 6-7. f1 is reparametrized
by gamma (f1 o gamma), f2 is rotated in R^3 by R for modulo="rigid"; translations cost
nothing (the metric sees only df), so both surfaces are centered for modulo="rigid".
"""

from __future__ import annotations

import functools
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._differential import area_element, interior_frame
from ._energy import frame_energy
from ._geodesic import (
    ConvergenceWarning,
    _basis_np,
    _check_pair,
    _check_solve_options,
    _frames_between,
    _perturbed_frames,
    _scaling,
    _solve,
)
from ._grid import interior_weights, sphere_points
from ._harmonics import _harmonics_np, _vector_fields_np, check_degree
from ._metric import SplitMetric
from ._reparam import _jacobian_determinant, _reparametrize
from ._so3 import _icosahedral_np, _so3_exp
from ._solvers import minimize
from ._srnf import _center

MODULI = ("diff", "rigid")
ALGORITHMS = ("coordinate", "joint")
INITS = ("icosahedral", "none")
# Shrink factors tried for a reparametrization step, largest first; 0 keeps gamma.
_STEP_SCALES = (1.0, 0.5, 0.25, 0.125, 0.0625, 0.0)
# BFGS steps spent on each of the 60 icosahedral starting rotations before ranking them.
_SEARCH_STEPS = 12


class ShapeGeodesicResult(NamedTuple):
    """A geodesic between shapes; a pytree, batched by ``jax.vmap``.

    Attributes:
        path: ``(N, 3, m, n)`` from f1 o gamma to R f2 (centered surfaces when modulo="rigid").
        distance: ``()`` sqrt(energy), the shape distance.
        energy: ``()`` the energy of ``path``.
        parametrized_distance: ``()`` the geodesic distance without registration.
        f1_registered: ``(3, m, n)`` f1 o gamma (= path[0]).
        gamma: ``(3, m, n)`` the reparametrization, a point of S^2 per grid point; its
            Jacobian determinant is positive at every grid point.
        rotation: ``(3, 3)`` R applied to f2 (the identity for modulo="diff").
        energy_history: ``(outer_steps + 2,)`` the parametrized geodesic energy, then the
            energy after the initialization and after each outer step.
        num_steps: ``()`` solver steps, all solves together.
        converged: ``()`` the last geodesic solve converged and the last outer step changed
            the energy by less than ``outer_tol`` times the parametrized energy.
    """

    path: Float[Array, "N 3 m n"]
    distance: Float[Array, ""]
    energy: Float[Array, ""]
    parametrized_distance: Float[Array, ""]
    f1_registered: Float[Array, "3 m n"]
    gamma: Float[Array, "3 m n"]
    rotation: Float[Array, "3 3"]
    energy_history: Float[Array, " H"]
    num_steps: Array
    converged: Array


@functools.cache
def _field_scale_np(m: int, n: int, degree: int) -> np.ndarray:
    """1 / sqrt(l(l+1)) per vector field: differentials grow like l; this evens the Hessian."""
    ls = _harmonics_np(m, n, degree)[4][1:]
    return np.repeat(1.0 / np.sqrt(ls * (ls + 1.0)), 2)


class _Config(NamedTuple):
    rigid: bool
    joint: bool
    n_times: int
    outer_steps: int
    icosahedral: bool
    solver: str
    max_steps: int
    tol: float
    outer_tol: float
    scheme: str
    interpolation: str


def _compose(gamma, step, interpolation):
    """gamma o step: read gamma's coordinates at the points of step, back onto the sphere."""
    g = _reparametrize(gamma, step, method=interpolation)
    return g / jnp.linalg.norm(g, axis=-3, keepdims=True)


def _step_field(y, fields, scale, e1):
    w = e1 + jnp.einsum("k,kimn->imn", y * scale, fields)
    return w / jnp.linalg.norm(w, axis=-3, keepdims=True)


def _rotate(r, f):
    return jnp.einsum("ij,j...->i...", r, f)


def _kabsch(source, target):
    """The rotation R minimizing the area-weighted sum |R source - target|^2 (centered)."""
    m, n = target.shape[-2:]
    weights = area_element(*interior_frame(target)) * interior_weights(m, n, target.dtype)
    x, y = source[:, 1:-1, :-1], target[:, 1:-1, :-1]
    total = jnp.sum(weights)
    x = x - jnp.sum(x * weights[None], axis=(1, 2), keepdims=True) / total
    y = y - jnp.sum(y * weights[None], axis=(1, 2), keepdims=True) / total
    h = jnp.einsum("imn,jmn,mn->ij", x, y, weights)
    u, _, vt = jnp.linalg.svd(h)
    d = jnp.sign(jnp.linalg.det(vt.T @ u.T))
    return vt.T @ jnp.diag(jnp.asarray([1.0, 1.0, 1.0], h.dtype).at[2].set(d)) @ u.T


def _safe_update(gamma, y, fields, scale, e1, interpolation):
    """The largest shrink of the step whose composition with gamma has J > 0 everywhere."""
    candidates = jnp.stack(
        [
            _compose(gamma, _step_field(s * y, fields, scale, e1), interpolation)
            for s in _STEP_SCALES
        ]
    )
    ok = jnp.min(_jacobian_determinant(candidates), axis=(-2, -1)) > 0
    # The last candidate (scale 0) is gamma itself, which is valid.
    first = jnp.argmax(ok.at[-1].set(True))
    return candidates[first]


def _shape_solve(metric, f1, f2, values, dframe, fields, field_scale, fields0, scale0, ico, cfg):
    m, n = f1.shape[-2:]
    dtype = f1.dtype
    e1 = sphere_points(m, n, dtype)
    eye = jnp.eye(3, dtype=dtype)
    if cfg.rigid:
        f1, f2 = _center(f1), _center(f2)
    geodesic_options = {
        "n_times": cfg.n_times,
        "solver": cfg.solver,
        "max_steps": cfg.max_steps,
        "tol": cfg.tol,
        "scheme": cfg.scheme,
    }
    zero_coefficients = jnp.zeros((cfg.n_times - 2, dframe.shape[0] * 3), dtype)
    parametrized = _solve(metric, f1, f2, zero_coefficients, values, dframe, **geodesic_options)
    steps = parametrized.num_steps

    def registered(gamma):
        return _reparametrize(f1, gamma, method=cfg.interpolation)

    def stepped(gamma, x, basis, scale):
        """f1 o gamma o Proj(Id + sum x_k v_k): f1 registered after one more Diff step."""
        return registered(_compose(gamma, _step_field(x, basis, scale, e1), cfg.interpolation))

    def straight_energy(f_start, f_end):
        # Ranking and refining straight lines needs no time resolution: 3 time points
        # (4.5x cheaper than N = 10) order the candidates the same way.
        frames = _frames_between(interior_frame(f_start), interior_frame(f_end), 3)
        return frame_energy(metric, *frames, cfg.scheme)

    gamma, rotation = e1, eye
    if cfg.icosahedral:
        # Remark 4: the 60 icosahedral rotations as reparametrizations, each refined by a
        # short BFGS over rotations of the parameter sphere, the best by straight-line
        # energy kept. When rigid, R^3's rotation is the Procrustes optimum for the
        # current correspondence (variable projection); ranking unrefined candidates
        # picks wrong basins once a true rotation is ~30 degrees from every candidate.
        def aligned(q, v):
            start = registered(_rotate(q @ _so3_exp(v), e1))
            r = _kabsch(f2, start) if cfg.rigid else eye
            return start, r

        reference = straight_energy(f1, f2)
        reference = jnp.where(reference > 0, reference, 1.0)

        def refine(q, v0, max_steps):
            def objective(v):
                start, r = aligned(q, v)
                return straight_energy(start, _rotate(r, f2)) / reference

            found = minimize(objective, v0, solver=cfg.solver, max_steps=max_steps, tol=cfg.tol)
            return objective(found.x), found.x, found.num_steps

        zero = jnp.zeros(3, dtype)
        energies, tangents, search_steps = jax.lax.map(
            lambda q: refine(q, zero, _SEARCH_STEPS), ico
        )
        best = jnp.argmin(energies)
        q = ico[best]
        # Then the winner, refined to the tolerance.
        _, v, final_steps = refine(q, tangents[best], cfg.max_steps)
        steps = steps + jnp.sum(search_steps).astype(steps.dtype) + final_steps
        gamma = _rotate(q @ _so3_exp(v), e1)
        rotation = aligned(q, v)[1]

        # Then a low-degree Diff step on the straight-line energy.
        def diff_objective(y):
            start = stepped(gamma, y, fields0, scale0)
            return straight_energy(start, _rotate(rotation, f2)) / reference

        y0 = jnp.zeros(fields0.shape[0], dtype)
        found = minimize(
            diff_objective, y0, solver=cfg.solver, max_steps=cfg.max_steps, tol=cfg.tol
        )
        steps = steps + found.num_steps
        gamma = _safe_update(gamma, found.x, fields0, scale0, e1, cfg.interpolation)

    def geodesic_at(gamma, rotation, init):
        return _solve(
            metric,
            registered(gamma),
            _rotate(rotation, f2),
            init,
            values,
            dframe,
            **geodesic_options,
        )

    first = geodesic_at(gamma, rotation, zero_coefficients)
    steps = steps + first.num_steps
    n_fields = fields.shape[0]

    def registration_variables(y):
        x = y[:n_fields]
        r_step = _so3_exp(y[n_fields:]) if cfg.rigid else eye
        return x, r_step

    def coordinate_step(carry, _):
        gamma, rotation, coefficients, path, energy, steps = carry
        interior = interior_frame(path[1:-1])
        scale_e = jnp.maximum(energy, jnp.finfo(dtype).tiny)

        # Algorithm 3: with the interior of the path fixed, move the end points
        # (f1 o gamma o gamma_x, and R f2) to lower the energy of the end segments.
        def objective(y):
            x, r_step = registration_variables(y)
            start = interior_frame(stepped(gamma, x, fields, field_scale))
            end = interior_frame(_rotate(r_step @ rotation, f2))
            frames = [
                jnp.concatenate([s[None], i, e[None]])
                for s, i, e in zip(start, interior, end, strict=True)
            ]
            return frame_energy(metric, *frames, cfg.scheme) / scale_e

        y0 = jnp.zeros(n_fields + (3 if cfg.rigid else 0), dtype)
        found = minimize(objective, y0, solver=cfg.solver, max_steps=cfg.max_steps, tol=cfg.tol)
        x, r_step = registration_variables(found.x)
        gamma = _safe_update(gamma, x, fields, field_scale, e1, cfg.interpolation)
        rotation = r_step @ rotation
        res = geodesic_at(gamma, rotation, coefficients)
        steps = steps + found.num_steps + res.num_steps
        carry = (gamma, rotation, res.coefficients, res.path, res.energy, steps)
        return carry, (res.energy, res.converged)

    def joint_step(carry, _):
        gamma, rotation, coefficients, path, energy, steps = carry
        f_start, f_end = registered(gamma), _rotate(rotation, f2)
        scaling = _scaling(metric, f_start, f_end, dframe, cfg.n_times, cfg.scheme)

        # Algorithm 2: the path coefficients and the registration together.
        def objective(variables):
            z, y = variables
            x, r_step = registration_variables(y)
            start = interior_frame(stepped(gamma, x, fields, field_scale))
            end = [_rotate(r_step, a) for a in interior_frame(f_end)]
            straight = _frames_between(start, end, cfg.n_times)
            frames = _perturbed_frames(straight, scaling.coefficients(z), dframe)
            return frame_energy(metric, *frames, cfg.scheme) / scaling.energy_scale

        y0 = jnp.zeros(n_fields + (3 if cfg.rigid else 0), dtype)
        found = minimize(
            objective,
            (scaling.whitened(coefficients), y0),
            solver=cfg.solver,
            max_steps=cfg.max_steps,
            tol=cfg.tol,
        )
        z, y = found.x
        x, r_step = registration_variables(y)
        gamma = _safe_update(gamma, x, fields, field_scale, e1, cfg.interpolation)
        rotation = r_step @ rotation
        # Polish the path for the registration actually taken (the step may have shrunk).
        res = geodesic_at(gamma, rotation, scaling.coefficients(z))
        steps = steps + found.num_steps + res.num_steps
        carry = (gamma, rotation, res.coefficients, res.path, res.energy, steps)
        return carry, (res.energy, res.converged)

    carry = (gamma, rotation, first.coefficients, first.path, first.energy, steps)
    step = joint_step if cfg.joint else coordinate_step
    carry, (energies, converged) = jax.lax.scan(step, carry, None, length=cfg.outer_steps)
    gamma, rotation, _, path, energy, steps = carry
    history = jnp.concatenate([parametrized.energy[None], first.energy[None], energies])
    # Progress is measured against the unregistered energy: near a perfect match the
    # energy itself is interpolation noise and its relative changes mean nothing.
    change = jnp.abs(history[-1] - history[-2]) / jnp.maximum(history[0], jnp.finfo(dtype).tiny)
    last_converged = converged[-1] if cfg.outer_steps else first.converged
    return ShapeGeodesicResult(
        path=path,
        distance=jnp.sqrt(energy),
        energy=energy,
        parametrized_distance=parametrized.distance,
        f1_registered=path[0],
        gamma=gamma,
        rotation=rotation,
        energy_history=history,
        num_steps=steps,
        converged=last_converged & (change <= cfg.outer_tol),
    )


_shape_geodesic = jax.jit(_shape_solve, static_argnames=("cfg",))


def shape_geodesic(
    f1: Float[ArrayLike, "3 m n"],
    f2: Float[ArrayLike, "3 m n"],
    metric: SplitMetric,
    *,
    modulo: str = "diff",
    method: str = "coordinate",
    degree: int = 7,
    vf_degree: int = 7,
    n_times: int = 13,
    outer_steps: int = 5,
    init: str = "icosahedral",
    init_degree: int = 2,
    solver: str = "bfgs",
    max_steps: int = 500,
    tol: float | None = None,
    outer_tol: float = 1e-3,
    scheme: str = "forward",
    interpolation: str = "bilinear",
) -> ShapeGeodesicResult:
    """Geodesic between the shapes of f1 and f2, modulo reparametrization (and rigid motion).

    Minimizes the path energy (MATH.md 4) over paths from f1 o gamma to R f2 and over
    gamma in Diff+(S^2) (and R in SO(3) for modulo="rigid"); paper sections 4.2-4.3.

    - method="coordinate" (Algorithm 3): alternate a parametrized geodesic (whitened
      BFGS, as :func:`geodesic`) with a registration step that, with the path's interior
      fixed, minimizes the energy over gamma_x = Proj(Id + sum x_k v_k) (degree vf_degree)
      composed onto gamma (and over R).
    - method="joint" (Algorithm 2): minimize over the path coefficients and x together,
      then compose, outer_steps times.
    - init="icosahedral" (Remark 4): the best of the 60 icosahedral rotations as
      reparametrizations by straight-line energy (each with the Procrustes rotation of f2
      when rigid), then BFGS over rotations, then a Diff step of degree init_degree.

    Large reparametrizations are compositions of small steps; each step is shrunk (by
    halves, down to no step) until the composed gamma has a positive Jacobian at every
    grid point, so every returned gamma is a diffeomorphism on the grid. The whole
    computation is one jitted call, vmappable over f2.

    Args:
        f1, f2: ``(3, m, n)`` immersions on the same grid.
        metric: split metric coefficients.
        modulo: ``"diff"`` (reparametrizations) or ``"rigid"`` (also rotations; centers both).
        method: ``"coordinate"`` or ``"joint"``.
        degree: of the path perturbations; vf_degree: of the vector fields of a Diff step.
        n_times: N >= 3; outer_steps: registration rounds after the initialization.
        init: ``"icosahedral"`` or ``"none"``; init_degree: of the initial Diff step.
        solver, max_steps, tol, scheme: as in :func:`geodesic`, for every inner solve.
        outer_tol: energy change of the last round, relative to the parametrized energy,
            that counts as converged.
        interpolation: ``"bilinear"`` (the paper's) or ``"bicubic"`` for f1 o gamma.

    Returns:
        :class:`ShapeGeodesicResult`.
    """
    checks = {"modulo": (modulo, MODULI), "method": (method, ALGORITHMS), "init": (init, INITS)}
    for name, (value, allowed) in checks.items():
        if value not in allowed:
            raise ValueError(f"{name} must be one of {allowed}; got {value!r}")
    if interpolation not in ("bilinear", "bicubic"):
        raise ValueError(f"interpolation must be 'bilinear' or 'bicubic'; got {interpolation!r}")
    f1, f2 = _check_pair(f1, f2)
    m, n = f1.shape[-2:]
    check_degree(degree, m, n)
    check_degree(vf_degree, m, n, "vf_degree")
    check_degree(init_degree, m, n, "init_degree")
    tol = _check_solve_options(n_times, solver, max_steps, tol, scheme, f1.dtype)
    if not isinstance(outer_steps, int) or outer_steps < 0:
        raise ValueError(f"outer_steps must be an integer >= 0; got {outer_steps!r}")
    cfg = _Config(
        rigid=modulo == "rigid",
        joint=method == "joint",
        n_times=n_times,
        outer_steps=outer_steps,
        icosahedral=init == "icosahedral",
        solver=solver,
        max_steps=max_steps,
        tol=float(tol),
        outer_tol=float(outer_tol),
        scheme=scheme,
        interpolation=interpolation,
    )
    dtype = f1.dtype
    values, dframe = (jnp.asarray(a, dtype) for a in _basis_np(m, n, degree))
    fields = jnp.asarray(_vector_fields_np(m, n, vf_degree), dtype)
    field_scale = jnp.asarray(_field_scale_np(m, n, vf_degree), dtype)
    fields0 = jnp.asarray(_vector_fields_np(m, n, init_degree), dtype)
    scale0 = jnp.asarray(_field_scale_np(m, n, init_degree), dtype)
    ico = jnp.asarray(_icosahedral_np(), dtype)
    result = _shape_geodesic(
        metric, f1, f2, values, dframe, fields, field_scale, fields0, scale0, ico, cfg
    )
    if not isinstance(result.converged, jax.core.Tracer) and not bool(result.converged):
        warnings.warn(
            f"shape_geodesic: not converged after {outer_steps} outer steps (energy history "
            f"{np.asarray(result.energy_history).round(6).tolist()}); raise outer_steps or "
            "max_steps",
            ConvergenceWarning,
            stacklevel=2,
        )
    return result
