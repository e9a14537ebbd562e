"""The discrete log map: the initial velocity of the geodesic from f1 to f2, modulo
nothing, reparametrizations or rigid motions (the inverse of :func:`exp`).

It sits above registration because the shape-space log runs :func:`shape_geodesic`.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._checks import check_choice
from .._errors import InputError
from .._geodesics.geodesic import GeodesicResult, geodesic
from .._geodesics.shooting import check_scheme
from .._geometry.bases import make_bases
from .._geometry.composition import on_grid, rotate_surface
from .._geometry.differential import interior_frame
from .._geometry.grid import sphere_points
from .._geometry.metric import SplitMetric
from .._geometry.numerics import default_tol
from .._geometry.validation import check_pair
from .._options import ShapeOptions, options_with
from .._registration.problem import (
    geodesic_at,
    make_problem,
    path_frames_at,
)
from .._registration.records import Levels, turned_back
from .._registration.shape import shape_geodesic
from .._results import RESULTS, status_record


@status_record
class LogResult(NamedTuple):
    """The initial velocity of the geodesic from f1 to (the registered) f2.

    Every surface of the record is on the solve's working grid (m, n): f1's own grid
    on one grid, the finest level's grid when the registration was resolved by levels.

    Attributes:
        velocity: ``(3, m, n)`` T (f_1 - f_0) of the geodesic's path: shooting it from
            ``base`` with the same degree, N and scheme gives that path back.
        target: ``(3, m, n)`` the surface the velocity reaches: f2 for modulo="none",
            R^T (f2 o gamma) otherwise: f2 reparametrized and turned onto f1.
        distance: ``()`` the geodesic distance (the resolved one when levels ran).
        path: ``(N, 3, m, n)`` the geodesic from ``base`` to ``target``, integrated by
            the working grid's nodes as :func:`shoot` steps: where the solve integrated
            finer (the levels' quadrature and stretched cells), the path is solved again
            by the nodes at the solve's registration, so its length can differ from
            ``distance`` by what the finer rule reads beyond the nodes.
        converged: ``()`` the geodesic solve's own convergence.
        result: that solve's result code (``elastic_jax.RESULTS``).
        num_steps: ``()`` that solve's steps.
        frames: ``(2, 2, 3, m - 2, n - 1)`` the differentials of f1 and of ``velocity``
            on the interior points as the solve took them (``frames[i, j]`` the j-th
            column of the i-th): their central differences, except under
            ``differential="chain"`` modulo "diff" / "rigid", whose ends' differentials
            come from the chain rule (math §2). ``shoot(f1, velocity, frames=frames)``
            reproduces ``path``.
        path_frames: ``(N, 2, 3, m - 2, n - 1)`` every node's differentials on the
            interior points as the solve took them (``path_frames[0]`` is
            ``frames[0]``): the path as the solve saw it, for
            :func:`parallel_transport`'s ``path_frames``.
        base: ``(3, m, n)`` the point the velocity is tangent at: f1 itself on f1's
            grid, else f1's interpolant read at the working grid's points (math §10).
        levels: the registration's :class:`Levels` when it was resolved by levels
            (modulo "diff" / "rigid" with ``rtol``), else None.
    """

    velocity: Float[Array, "3 m n"]
    target: Float[Array, "3 m n"]
    distance: Float[Array, ""]
    path: Float[Array, "N 3 m n"]
    frames: Float[Array, "2 2 3 m-2 n-1"]
    path_frames: Float[Array, "N 2 3 m-2 n-1"]
    base: Float[Array, "3 m n"]
    levels: Levels | None
    converged: Bool[Array, ""]
    result: RESULTS
    num_steps: Int[Array, ""]


def log(
    f1: Float[ArrayLike, "3 m n"],
    f2: Float[ArrayLike, "3 m n"],
    metric: SplitMetric,
    *,
    modulo: str = "none",
    options: ShapeOptions | None = None,
    **changes,
) -> LogResult:
    """The initial velocity at f1 of the geodesic to f2 (the discrete log map).

    modulo="none": :func:`geodesic` f1 -> f2 and v = T (f_1 - f_0) of its path, so that
    ``shoot(f1, v, ...)`` with the same degree, N and scheme reproduces the path.
    modulo="diff" / "rigid": :func:`shape_geodesic` from f2 to f1 (it reparametrizes its
    first surface and turns its second), the path reversed and turned back by R^T so that
    it starts at f1 as given: v is a tangent vector at f1 itself (as for a Karcher mean's
    tangent space) and ``target`` the registered f2. With ``options.rtol`` (the default)
    the registration is resolved by levels of working grids, as :func:`shape_geodesic`
    resolves it (math §10), and the log lives on the finest level's grid: at ``base``,
    f1 read at that grid (``levels`` records the levels). The levels integrate finer than
    the working grid's nodes, and :func:`shoot` steps by the nodes, so the path is then
    solved again by the nodes at the resolved registration (gamma and R held): the
    geodesic that shooting ``velocity`` follows. ``grid=(m, n)`` or
    ``rtol=None`` (the inputs' grid, the finer of two) solve on one grid; logs that are to
    share a grid (a transfer, a tangent space's statistics) are asked for on one. The
    midpoint energy is symmetric under reversal, so the reversed path is again a discrete
    geodesic. Under
    ``differential="chain"`` the solve's path is given by its nodes' differentials, of
    which the ends' are not the grid differences of the ends: shoot with
    ``frames=result.frames`` to follow it.

    Args:
        f1, f2: ``(3, m, n)`` immersions on one grid; modulo "diff" / "rigid" each on a
            grid of its own, as in :func:`shape_geodesic`.
        metric: the split metric coefficients.
        modulo: ``"none"``, ``"diff"`` or ``"rigid"``.
        options: :class:`ShapeOptions` (degree, n_times, scheme, ... and the registration;
            its defaults when None): resolved by its ``rtol`` and ``levels`` modulo
            "diff" / "rigid", on one grid with ``grid`` or ``rtol=None``.
        **changes: fields of ShapeOptions as keywords (``degree=5``): without
            ``options`` each sets that field of the default record; beside ``options``
            each must equal the record's field (an equal one is accepted, another is an
            InputError: change the record with ``options.replace(...)``).

    Returns:
        :class:`LogResult`.
    """

    check_choice("modulo", modulo, ("none", "diff", "rigid"))
    options = options_with("log", options, changes)
    check_scheme(options.scheme)
    # A registered log reads each input through its interpolant: any two grids.
    f1, f2 = check_pair(f1, f2, same_grid=modulo == "none")
    solve_frames, base, levels = None, f1, None
    if modulo == "none":
        res: GeodesicResult = geodesic(f1, f2, metric, **options.geodesic_kwargs())
        path = res.path
    else:
        if options.scheme != "midpoint":
            raise InputError(
                f'log modulo "{modulo}" needs scheme="midpoint": the registered geodesic runs '
                "from f2 to f1 and is reversed, and only the midpoint energy is symmetric"
            )
        res = shape_geodesic(f2, f1, metric, modulo=modulo, options=options)
        levels = res.levels
        m, n = res.path.shape[-2:]
        node_rule = options.replace(
            refinement=False,
            rtol=None,
            grid=None,
            quadrature=1,
            stretch_quadrature=0.0,
            tol=default_tol(f1.dtype) if options.tol is None else options.tol,
        )
        solved = options.on_level((m, n))  # the options of the grid the path is on
        if solved.quadrature_factor != 1 or solved.stretch_fraction > 0.0:
            # The levels integrate finer than the nodes, and shoot steps by the nodes: a
            # geodesic of the finer rule is not one that shoot follows (concentric
            # spheres shot back 2.5e-6 off its last node, 1.4e-7 off this one's).
            path_res = _node_rule_path(
                f2, f1, metric, res.gamma, res.rotation, res.coefficients, node_rule, modulo
            )
            res = res._replace(
                path=path_res.path,
                coefficients=path_res.coefficients,
                converged=res.converged & path_res.converged,
                result=RESULTS.where(path_res.converged, res.result, path_res.result),
                num_steps=res.num_steps + path_res.num_steps,
            )
        base = on_grid(f1, sphere_points(m, n, f1.dtype), options.interpolation)
        # The solve's last node is R (f1 read at the working grid, centred modulo
        # "rigid"): turned back and moved onto ``base`` it is ``base`` but for rounding.
        path = turned_back(res, base)[::-1].at[0].set(base)
        if options.differential == "chain":
            # The frames at the working grid's nodes, as shoot takes them.
            solve_frames = _solve_frames(
                f2, f1, metric, res.gamma, res.rotation, res.coefficients, node_rule, modulo
            )
    t = options.n_times - 1
    velocity = t * (path[1] - path[0])
    if solve_frames is None:  # every node's differential is its grid differences
        solve_frames = jnp.stack(interior_frame(path), axis=1)
    return LogResult(
        velocity=velocity,
        target=path[-1],
        distance=res.distance,
        path=path,
        converged=res.converged,
        result=res.result,
        num_steps=res.num_steps,
        frames=jnp.stack([solve_frames[0], t * (solve_frames[1] - solve_frames[0])]),
        path_frames=solve_frames,
        base=base,
        levels=levels,
    )


@functools.partial(jax.jit, static_argnames=("options", "modulo"))
def _node_rule_path(f2, f1, metric, gamma, rotation, coefficients, options, modulo):
    """The geodesic from f2 o gamma to R f1 integrated by the working grid's nodes
    (``options``: the node rule), gamma and R held, warm-started at ``coefficients``."""
    m, n = gamma.shape[-2:]
    bases = make_bases(m, n, options, f1.dtype)
    prob = make_problem(metric, f2, f1, bases, modulo == "rigid", options.interpolation)
    return geodesic_at(prob, options, gamma, rotation, coefficients)


@functools.partial(jax.jit, static_argnames=("options", "modulo"))
def _solve_frames(f2, f1, metric, gamma, rotation, coefficients, options, modulo):
    """The differentials of the log's nodes as the registered solve took them,
    ``(N, 2, 3, m - 2, n - 1)``: its nodes' (the straight line between the chain-rule
    frames of f2 o gamma and R f1, plus the path's perturbation) in reverse order,
    turned back by R^T."""
    m, n = gamma.shape[-2:]
    bases = make_bases(m, n, options, f1.dtype)
    prob = make_problem(metric, f2, f1, bases, modulo == "rigid", options.interpolation)
    a1, a2 = path_frames_at(prob, options, gamma, rotation, coefficients)
    back = jax.vmap(lambda a: rotate_surface(rotation.T, a))
    return jnp.stack([back(a1), back(a2)], axis=1)[::-1]
