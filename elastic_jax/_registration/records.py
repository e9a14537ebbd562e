"""What a registration returns: the result record, its refinement check, and the
path turned back onto the caller's second surface.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._checks import is_concrete
from .._errors import ConvergenceWarning, warn_user
from .._results import RESULTS, record_repr, status_record

MODULI = ("diff", "rigid")


class Refinement(NamedTuple):
    """The distance of a result re-evaluated at a finer discretization (:ref:`math §9 <math-9>`).

    Nothing is optimized again: the registered ends and the path are carried over, so a
    discretization the solve exploited shows as a jump here.

    Attributes:
        distance_time: ``()`` the same path with every time step halved (2N - 1 time
            points, frames linearly interpolated).
        distance_grid: ``()`` the same path by the nodes of the grid twice finer than
            the one its energy was integrated on: (2m - 1) x (2n - 1) for the working
            grid's nodes, (4m - 3) x (4n - 3) with ``ShapeOptions(quadrature=2)`` (a
            resolved distance's levels): gamma and f2 interpolated there, f1 o gamma
            read from f1's own grid, the path's spherical-harmonic perturbation
            evaluated on that grid. It reads what the solve's rule did not, where a
            registration may hide content between the points.
        relative_change: ``()`` max(abs(distance_time - d), abs(distance_grid - d)) / d.
    """

    distance_time: Float[Array, ""]
    distance_grid: Float[Array, ""]
    relative_change: Float[Array, ""]

    __repr__ = record_repr


class Levels(NamedTuple):
    """The working grids a resolved distance was solved on, coarse to fine
    (:ref:`math §10 <math-10>`).

    Attributes:
        grids: ``(L, 2)`` each level's working grid (m, n).
        distances: ``(L,)`` the distance of the last level's minimum on each level:
            each level's own where the levels continued one minimum, else the levels
            below solved again from the last one (its registration and path) when the
            last change missed rtol at a converged solve and either only two levels
            had run or the last three levels' changes turned back or stopped halving
            (an observed order below 1): the change of levels that ended in different
            minima is the minima's, not the grid's (NaN where the last gamma folds
            between a coarser grid's points).
        ascent: ``(L,)`` each level's distance as first solved, going up (equal to
            ``distances`` unless the levels below were solved again).
        refined: ``(L,)`` each level's registration and path as first solved, read by
            the nodes of the grid twice finer than the rule the level integrated by (its
            :class:`Refinement` ``distance_grid``; NaN without the refinement check):
            ``refined / ascent - 1`` is what each level's rule under-read, and its
            observed order across levels that of the discretization at fixed
            registrations, whichever minimum each level reached.
        seconds: ``(L,)`` each level's wall-clock time (its first call compiles; the
            levels below solved again count in the level that asked for them).
        estimate: ``()`` the relative change of ``distances`` between the last two
            levels, abs(d_L - d_{L-1}) / max(d_L, 0.05 p_L) with p_L the last level's
            parametrized distance (near-equal shapes, whose distance is near zero, are
            resolved to that absolute size), or the last level's own
            ``refinement.relative_change`` in the same scale where that is larger (two
            levels can agree in a minimum that hides content between both grids'
            points): the stated resolution of the answer (NaN with one level).
        rtol: ``()`` the tolerance asked for.
        candidates: ``(C,)`` the final distance of each candidate carried through the
            levels (``ShapeOptions.level_candidates``; one entry, the distance, for
            one candidate), in the order of the start search's ranking, then, with
            ``ShapeOptions.both_orders``, the other order's starts in theirs, then,
            with ``ShapeOptions.search_smoothing``, the graduated candidate; the
            result is the lowest (NaN for a candidate that ended non-finite).
        spread: ``()`` (max - min) / max(min, 0.05 p_L) of the finite ``candidates``
            (0 for one; p_L as in ``estimate``): how far apart the minima the
            candidates reached are; the result is converged only when it is within
            rtol.
    """

    grids: Int[Array, "L 2"]
    distances: Float[Array, " L"]
    ascent: Float[Array, " L"]
    refined: Float[Array, " L"]
    seconds: Float[Array, " L"]
    estimate: Float[Array, ""]
    rtol: Float[Array, ""]
    candidates: Float[Array, " C"]
    spread: Float[Array, ""]

    __repr__ = record_repr


@status_record
class ShapeGeodesicResult(NamedTuple):
    """A geodesic between shapes; a pytree, batched by ``jax.vmap``.

    Attributes:
        path: ``(N, 3, m, n)`` from f1 o gamma to R f2 (centered surfaces when modulo="rigid").
        distance: ``()`` sqrt(energy), the shape distance.
        energy: ``()`` the energy of ``path`` (the options' scheme).
        parametrized_distance: ``()`` the geodesic distance without registration (same scheme).
        f1_registered: ``(3, m, n)`` f1 o gamma (= path[0]).
        gamma: ``(3, m, n)`` the reparametrization, a point of S^2 per grid point; its
            Jacobian determinant is positive at every grid point.
        rotation: ``(3, 3)`` R applied to f2 (the identity for modulo="diff").
        coefficients: ``(N - 2, L)`` the path's perturbation (as in :class:`GeodesicResult`).
        parametrized_coefficients: ``(N - 2, L)`` the parametrized geodesic's perturbation
            (f1 -> f2 as given): a finer level starts its parametrized geodesic there.
        energy_history: ``(outer_steps + 2,)`` the parametrized geodesic's energy, the
            straight line's after the initialization, then the energy after each
            registration round (NaN for rounds not taken).
        rounds: ``()`` registration rounds taken.
        num_steps: ``()`` solver steps, all solves together.
        converged: ``()`` the final geodesic solve converged (a minimum, not a saddle, when
            saddle_checks >= 1) and the last round changed the
            energy by at most the rounds' stop (``ShapeOptions.round_stop``: rounds_tol,
            else outer_tol; times E + that tolerance E_0), or its change and the one before,
            continued geometrically, leave at most that (always true when outer_steps=0
            asks for no rounds) or was refused, and that round's step did not have to shrink
            to stay resolved.
        result: an ``elastic_jax.RESULTS`` code: the final solve's failure if it failed, else
            ``resolution_limited`` when the last round's step had to shrink until the grid
            resolved it (J > 0, area floor) and then lowered the energy little or not at
            all, else ``nonlinear_max_steps_reached`` when the rounds ran out, else successful;
            ``nonfinite`` over all of these when the energy is not finite (the distance is
            then NaN, never 0; levels stop at such a level), ``below_area_bound`` when
            the distance came out under 0.9 times math §9's area bound for the path's
            ends (lost precision; the distance is then NaN too).
        grad_norm: ``()`` 2-norm of the gradient of the joint objective (path in whitened
            coefficients and the next Diff step, energy / its scale) at the result.
        min_curvature: ``()`` the final geodesic solve's estimate of the smallest Hessian
            eigenvalue of its scaled objective (:class:`GeodesicResult`): positive at a
            minimum of the path for this registration.
        refinement: :class:`Refinement` (NaN when the options turn it off).
        levels: :class:`Levels` when the options' ``rtol`` asked for a resolved distance
            (the working grid refined until two levels agree), else None.
    """

    path: Float[Array, "N 3 m n"]
    distance: Float[Array, ""]
    energy: Float[Array, ""]
    parametrized_distance: Float[Array, ""]
    f1_registered: Float[Array, "3 m n"]
    gamma: Float[Array, "3 m n"]
    rotation: Float[Array, "3 3"]
    coefficients: Float[Array, "K L"]
    parametrized_coefficients: Float[Array, "K L"]
    energy_history: Float[Array, " H"]
    rounds: Int[Array, ""]
    grad_norm: Float[Array, ""]
    min_curvature: Float[Array, ""]
    refinement: Refinement
    levels: Levels | None
    converged: Bool[Array, ""]
    result: RESULTS
    num_steps: Int[Array, ""]

    @property
    def spread(self) -> Array:
        """``()`` the candidates' spread of a resolved distance (:class:`Levels`
        ``spread``; ``ShapeOptions.level_candidates``, ``both_orders``,
        ``search_smoothing``), 0 on one
        working grid."""
        if self.levels is None:
            return jnp.zeros((), self.distance.dtype)
        return self.levels.spread

    def _explain(self, words: str) -> str:
        # A converged result whose last round was refused (its full step, resolved by the
        # grid, raised the energy: the composed reparametrization's interpolation cost
        # more than the step gained) says so.
        if RESULTS.name(self.result) == "saddle_point":  # no eager == (a program of its own)
            words += f" (smallest Hessian eigenvalue {float(self.min_curvature):.3g})"
        history, k = np.asarray(self.energy_history), int(self.rounds)
        # After at least one accepted round: a first round refused at once is a match at
        # interpolation noise (identical inputs), not a registration held back.
        if not words and k >= 2 and history[k + 1] == history[k] > 0:
            change = 100.0 * (history[k - 1] - history[k]) / history[k]
            words = (
                "the rounds ended where the next round's Diff step raised the energy (the "
                f"last accepted round lowered it by {change:.2g} %); refinement shows how a "
                "finer grid sees the result"
            )
        return words


def turned_back(res, end):
    """A shape geodesic's path (from f1 o gamma to R f2) turned by R^T and moved so that it
    ends at ``end`` (its f2) as parametrized and placed (modulo "rigid" centres both)."""
    back = jnp.einsum("ji,tj...->ti...", res.rotation, res.path)
    return back + (end - back[-1]).mean(axis=(-2, -1), keepdims=True)[None]


def warn_unless_converged(result: ShapeGeodesicResult) -> None:
    """ConvergenceWarning for a concrete result that did not converge."""
    if is_concrete(result.converged, result.energy_history, result.rounds) and not bool(
        result.converged
    ):
        history = np.asarray(result.energy_history)
        # Every other ending's words (stalled, saddle, resolution-limited) say what to
        # change; running out of steps is the one that does not.
        ran_out = RESULTS.name(result.result) == "nonlinear_max_steps_reached"
        advice = "; raise outer_steps or max_steps" if ran_out else ""
        if result.levels is not None:
            steps = ", ".join(
                f"{m} x {n}: {d:.6g}"
                for (m, n), d in zip(
                    np.asarray(result.levels.grids).tolist(),
                    np.asarray(result.levels.distances).tolist(),
                    strict=True,
                )
            )
            advice += f"; levels {steps} (estimate {float(result.levels.estimate):.3g})"
        warn_user(
            f"shape_geodesic: not converged after {int(result.rounds)} registration rounds "
            f"({result.message}; energies {history[np.isfinite(history)].round(6).tolist()})"
            f"{advice}",
            ConvergenceWarning,
        )
