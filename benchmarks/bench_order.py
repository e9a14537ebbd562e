"""Where the levels' error lives: each level's registration and path re-evaluated finer.

For each pair, modulo rigid motion, metric (1, 1, 0.1, 0), float64: the levels of a
resolved distance (the package's own continuation, each level from the one below), and
for every level

- ``quadrature``: the same registration and path (gamma read through its interpolant, R
  and the path's coefficients held) integrated on the working grid cut 2x and 4x
  (``--factors``), with the energy split by region: points whose gamma(x) lies within
  8 degrees of f1's poles, points within 8 degrees of the working grid's poles, and the
  rest by gamma's Jacobian determinant J (bins 0-0.5, 0.5-2, 2-4, 4-8, above 8: J > 1
  where gamma compresses a region of f1 onto the working grid);
- ``path_only`` (``--path-only``): only the path re-solved on the 2x grid, gamma and R
  held, so that the level change splits into quadrature, path and registration;
- ``correspondence``: on the 2x grid, the area element of f1 o gamma over R f2's at each
  point (10 %, 50 %, 90 % quantiles; 1 everywhere for an isometric correspondence) and
  the pointwise area bound of the path through that correspondence,
  sqrt(2 b int (sqrt(rho_1) - sqrt(rho_2))^2): the volume term alone costs at least that
  much (Cauchy-Schwarz in time on <xi_vol, xi_vol> = 2 (d_t sqrt(rho))^2), however the
  path bends;
- ``density``: the inputs' own parametrizations, their area element |f_theta x f_phi| /
  sin(phi) over its mean (1 %, 50 %, 99 % quantiles), which is what a registration
  between them must transfer (J ~ rho2 / rho1 o gamma for nearly isometric pairs).

``--balanced``: each input first put through the package's own spherical
parametrization of its grid's mesh (``io.grid_to_mesh``, ``io.mesh_to_grid`` with
``method="spherical"``, ``frame="input"``) at 99 x 197: the same shape up to the mesh's
chords, with a parametrization whose area element varies far less (cat1: 1-99 %
quantiles 0.18-4.4 of its mean on the data, 0.51-2.1 balanced).

``--turn DEGREES``: both inputs read through one rotation of their parameter sphere
(that many degrees about (1, 2, 3) / sqrt(14)) by the spline at 99 x 197, so that the
data's poles land away from the working grid's.

``--fourier``: each input replaced by its trigonometric interpolant (``fourier_read``:
the data's samples interpolated by a Fourier series on the sphere doubled in phi,
sampled 4 times finer, then read by the spline): an interpolant that is smooth between
the samples where the spline's third derivatives jump at every grid line.

``--stretch FRACTION``: solve with ``ShapeOptions(stretch_quadrature=FRACTION)`` (that
fraction of the quadrature grid's cells, where gamma stretches most, integrated
``--subdivision`` times finer in each direction, 4 by default, on top of the finer nodes
where the levels integrate at them; the package's default when absent, 0.03 on the
levels; ``--stretch 0`` for the nodes alone).

``--quadrature Q``: solve with ``ShapeOptions(quadrature=Q)`` (every energy of a level
integrated at the nodes of the grid Q times finer; the package's default when absent,
2 on the levels; ``--quadrature 1`` for the node rule); the ``quadrature`` records still
integrate the result by the nodes of the working grid cut by each factor.

``--down``: after the levels, each coarser level solved again from the finest level's
registration and path (``continued_geodesic``): the coarser grids' values in the finest
level's basin, with their 2x-grid evaluations. The levels' own changes mix the
discretization's error with changes of basin (each level continues the one below and
may leave its basin); the values in one basin show the discretization's order alone.

One JSON record per level and per pair, then a summary per pair (the level changes and
the observed orders log2(change_(L-1) / change_L)). ``--interpolation`` is passed to
ShapeOptions, and ``--floor`` changes the registration's resolution floor (the module
constant ``RESOLUTION_FACTOR``, 5) for a diagnostic run. ``--path-only`` re-solves the
path on the levels up to ``--path-only-up-to`` (default 49 x 97: on 193 x 385 one path
solve takes minutes).

Pairs: cat1 -> cat2, cat1 -> horse0 (``horse-cat``: the other order), horse0 -> hand4
(the authors' surfaces from elastic_jax.datasets: $ELASTIC_JAX_DATA or a download;
skipped when they cannot be had) and, when nilearn is installed, FreeSurfer's
fsaverage5 pial hemispheres (``pial``: left against right, each put on the 50 x 99 grid
by the package's spherical parametrization, area 4 pi).

Run: python benchmarks/bench_order.py [--pairs cats,cat-horse,horse-hand,pial]
     [--levels 13x25,25x49,49x97,97x193] [--factors 1,2,4] [--path-only]
     [--path-only-up-to 49x97] [--interpolation spline] [--floor 5] [--balanced]
     [--turn 0] [--fourier] [--stretch F] [--subdivision 4] [--down]
     [--quadrature Q]
"""

from __future__ import annotations

import argparse
import importlib.util
import pathlib
import time
import warnings
from typing import NamedTuple

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import elastic_jax as ej  # noqa: E402
from elastic_jax._geometry import bases as _bases  # noqa: E402
from elastic_jax._geometry.bases import make_bases  # noqa: E402
from elastic_jax._geometry.composition import compose  # noqa: E402
from elastic_jax._geometry.differential import area_element, interior_frame  # noqa: E402
from elastic_jax._geometry.energy import speed_density  # noqa: E402
from elastic_jax._geometry.grid import interior_weights_np, sphere_points  # noqa: E402
from elastic_jax._geometry.numerics import default_tol  # noqa: E402
from elastic_jax._geometry.reparam import jacobian_determinant_unchecked  # noqa: E402
from elastic_jax._registration import levels as _levels  # noqa: E402
from elastic_jax._registration import one_grid as _one_grid  # noqa: E402
from elastic_jax._registration import problem as _problem  # noqa: E402

from _common import emit, environment, shape  # noqa: E402

METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
PAIRS = {
    "cats": ("cat1", "cat2"),
    "cat-horse": ("cat1", "horse0"),
    "horse-cat": ("horse0", "cat1"),
    "horse-hand": ("horse0", "hand4"),
    "pial": ("pial_left", "pial_right"),
}
# Regions: within this angle of a pole; gamma's Jacobian determinant bins.
POLE_DEGREES = 8.0
J_EDGES = (0.0, 0.5, 2.0, 4.0, 8.0, np.inf)


def load(name: str):
    """One of the authors' shapes on its 50 x 99 grid, or an fsaverage5 pial hemisphere on
    50 x 99; None when its source is absent."""
    if name.startswith("pial_"):
        if importlib.util.find_spec("nilearn") is None:
            return None
        from elastic_jax import io

        folder = pathlib.Path(importlib.util.find_spec("nilearn").origin).parent
        path = folder / "datasets" / "data" / "fsaverage5" / f"{name}.gii.gz"
        return np.asarray(io.load_surface(path, 50, 99, normalize="area"))
    return shape(name)


def balanced(f, m: int = 99, n: int = 197):
    """f through the package's spherical parametrization of its grid's mesh, on m x n."""
    from elastic_jax import io

    mesh = io.grid_to_mesh(f)
    return np.asarray(io.mesh_to_grid(mesh, m, n, method="spherical", frame="input"))


def turned(f, degrees: float, m: int = 99, n: int = 197):
    """f o Q on m x n, Q the rotation by ``degrees`` about (1, 2, 3) / sqrt(14), read by
    f's spline (pole rows and seam made exact)."""
    axis = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    q = np.asarray(ej.so3_exp(jnp.asarray(np.radians(degrees) * axis)))
    points = np.einsum("ij,jmn->imn", q, np.asarray(sphere_points(m, n, jnp.float64)))
    g = np.array(ej.reparametrize(jnp.asarray(f), jnp.asarray(points), method="spline"))
    g[:, 0], g[:, -1] = g[:, 0, :1], g[:, -1, :1]
    g[:, :, -1] = g[:, :, 0]
    return g


def fourier_read(f, factor: int = 4):
    """f's trigonometric interpolant on the sphere doubled in phi (the rows continued past
    the south pole by f(2 pi - phi, theta + pi), a periodic (2 (m - 1), n - 1) array),
    sampled ``factor`` times finer in each direction: ``(3, factor (m - 1) + 1,
    factor (n - 1) + 1)``, equal to f at f's own points (to rounding) and smooth between
    them. n - 1 must be even (the half turn in theta is a whole number of columns)."""
    from scipy.signal import resample

    f = np.asarray(f)
    m, n = f.shape[-2:]
    columns = n - 1
    if columns % 2:
        raise ValueError(f"fourier_read needs an even n - 1 (a half turn in columns); got n = {n}")
    g = f[:, :, :columns]
    beyond = np.roll(g[:, m - 2 : 0 : -1, :], columns // 2, axis=2)
    doubled = np.concatenate([g, beyond], axis=1)
    doubled = resample(doubled, factor * doubled.shape[1], axis=1)
    doubled = resample(doubled, factor * columns, axis=2)
    out = doubled[:, : factor * (m - 1) + 1]
    out = np.concatenate([out, out[:, :, :1]], axis=2)
    out[:, 0], out[:, -1] = out[:, 0, :1], out[:, -1, :1]
    return out


def density_quantiles(f) -> list[float]:
    """The area element of f's parametrization over its mean: 1 %, 50 %, 99 % quantiles."""
    m, n = f.shape[-2:]
    rho = area_element(*interior_frame(np.asarray(f)))
    w = interior_weights_np(m, n)
    rho = rho / ((rho * w).sum() / (4.0 * np.pi))
    return np.quantile(rho, [0.01, 0.5, 0.99]).tolist()


def levels_of(f1, f2, options: ej.ShapeOptions):
    """Each level's result, every level solved (no early stop), as shape_geodesic runs them."""
    results, result = [], None
    for grid in options.levels:
        begin = time.perf_counter()
        result = _levels.level_solve(f1, f2, METRIC, "rigid", options, grid, result)
        results.append((grid, result, time.perf_counter() - begin))
    return results


class Evaluation(NamedTuple):
    """A level's registration on another grid: the problem there and gamma read at its
    points through gamma's interpolant."""

    prob: _problem.Problem
    options: ej.ShapeOptions
    gamma: jax.Array


def evaluation(f1, f2, result, grid, options) -> Evaluation:
    opts = options.replace(
        grid=grid,
        rtol=None,
        refinement=False,
        tol=default_tol(f1.dtype),
        quadrature=1,
        stretch_quadrature=0.0,
    )
    bases = make_bases(*grid, opts, f1.dtype)
    prob = _problem.make_problem(
        METRIC, jnp.asarray(f1), jnp.asarray(f2), bases, True, opts.interpolation
    )
    gamma = jnp.asarray(result.gamma)
    if gamma.shape[-2:] != tuple(grid):
        gamma = compose(gamma, sphere_points(*grid, gamma.dtype), opts.interpolation)
    return Evaluation(prob, opts, gamma)


def quadrature_record(at: Evaluation, result) -> dict:
    """The level's gamma, R and path integrated on ``at``'s grid, split by region."""
    prob, opts, gamma = at
    grid = opts.grid
    a1, a2 = _problem.path_frames_at(prob, opts, gamma, result.rotation, result.coefficients)
    t = a1.shape[0] - 1
    speed = speed_density(
        METRIC,
        0.5 * (a1[1:] + a1[:-1]),
        0.5 * (a2[1:] + a2[:-1]),
        t * (a1[1:] - a1[:-1]),
        t * (a2[1:] - a2[:-1]),
    )
    w = interior_weights_np(*grid)
    terms = np.asarray(jnp.sum(speed, axis=0) / t) * w
    g = np.asarray(gamma)[:, 1:-1, :-1]
    jac = np.asarray(jacobian_determinant_unchecked(gamma))[1:-1, :-1]
    f1_pole = np.abs(g[2]) > np.cos(np.radians(POLE_DEGREES))
    phi = np.linspace(0.0, np.pi, grid[0])[1:-1, None] * np.ones((1, grid[1] - 1))
    near = np.radians(POLE_DEGREES)
    grid_pole = ((phi < near) | (phi > np.pi - near)) & ~f1_pole
    rest = ~f1_pole & ~grid_pole
    regions = {"f1_pole": f1_pole, "grid_pole": grid_pole}
    for low, high in zip(J_EDGES[:-1], J_EDGES[1:], strict=True):
        regions[f"J {low:g}-{high:g}"] = rest & (jac >= low) & (jac < high)
    return {
        "grid": list(grid),
        "distance": float(np.sqrt(terms.sum())),
        "energy": float(terms.sum()),
        "max_jacobian": float(jac.max()),
        "energy_by_region": {k: float(terms[v].sum()) for k, v in regions.items()},
        "area_by_region": {k: float(w[v].sum()) for k, v in regions.items()},
    }


def correspondence_record(at: Evaluation, result) -> dict:
    """How far the registration is from matching areas point for point, on ``at``'s grid."""
    prob, opts, gamma = at
    grid = opts.grid
    rho1 = np.asarray(area_element(*_problem.registered_frame(prob, opts, gamma)))
    rho2 = np.asarray(area_element(*_problem.rotated_end_frame(prob, opts, result.rotation)))
    w = interior_weights_np(*grid)
    bound = np.sqrt(2.0 * METRIC.b * np.sum(w * (np.sqrt(rho1) - np.sqrt(rho2)) ** 2))
    return {
        "grid": list(grid),
        "area_ratio_quantiles": np.quantile(rho1 / rho2, [0.1, 0.5, 0.9]).tolist(),
        "pointwise_area_bound": float(bound),
    }


def path_only(at: Evaluation, result) -> dict:
    """Only the path re-solved on ``at``'s grid, gamma and R held."""
    prob, opts, gamma = at
    grid = opts.grid
    begin = time.perf_counter()
    held = _problem.path_energy_at(prob, opts, gamma, result.rotation, result.coefficients)
    res = _problem.geodesic_at(prob, opts, gamma, result.rotation, result.coefficients)
    return {
        "grid": list(grid),
        "held": float(np.sqrt(held)),
        "resolved": float(np.sqrt(res.energy)),
        "steps": int(res.num_steps),
        "seconds": time.perf_counter() - begin,
    }


def observed_orders(distances) -> list[float]:
    """log2(change_(L-1) / change_L) of successive levels' distances."""
    changes = np.abs(np.diff(distances))
    return [
        float(np.log2(a / b)) if b > 0 else float("inf")
        for a, b in zip(changes[:-1], changes[1:], strict=False)
    ]


def basin_record(f1, f2, solved, options) -> dict:
    """The coarser levels solved again from the finest level's registration and path:
    distances (coarse to fine, the finest level's own last), their 2x-grid evaluations,
    the observed orders of those distances, and seconds."""
    (*coarser, (grid, finest, _)) = solved
    distances, on_2x, seconds = [], [], []
    for (m, n), _, _ in coarser:
        begin = time.perf_counter()
        if _levels.registration_at(finest, (m, n), finest.gamma.dtype, "rigid") is None:
            # The finest gamma folds between this grid's points: no start there.
            distances.append(float("nan"))
            on_2x.append(float("nan"))
            seconds.append(0.0)
            continue
        again = _one_grid.continued_geodesic(
            f1,
            f2,
            METRIC,
            "rigid",
            options.on_level((m, n)),
            finest.gamma,
            finest.rotation,
            finest.coefficients,
        )
        distances.append(float(again.distance))
        on_2x.append(float(again.refinement.distance_grid))
        seconds.append(time.perf_counter() - begin)
    distances.append(float(finest.distance))
    on_2x.append(float(finest.refinement.distance_grid))
    return {
        "grids": [list(g) for g, _, _ in solved],
        "distances": distances,
        "distances_2x_grid": on_2x,
        "observed_orders": observed_orders(distances),
        "observed_orders_2x_grid": observed_orders(on_2x),
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default="cats,cat-horse,horse-hand,pial")
    parser.add_argument("--levels", default="13x25,25x49,49x97,97x193")
    parser.add_argument("--factors", default="1,2,4")
    parser.add_argument("--path-only", action="store_true")
    parser.add_argument("--path-only-up-to", default="49x97")
    parser.add_argument("--interpolation", default="spline")
    parser.add_argument("--floor", type=float, default=None)
    parser.add_argument("--balanced", action="store_true")
    parser.add_argument("--turn", type=float, default=0.0)
    parser.add_argument("--fourier", action="store_true")
    parser.add_argument("--stretch", type=float, default=None)
    parser.add_argument("--subdivision", type=int, default=4)
    parser.add_argument("--down", action="store_true")
    parser.add_argument("--quadrature", type=int, default=None)
    args = parser.parse_args()
    if args.floor is not None:
        _bases.RESOLUTION_FACTOR = args.floor
    levels = tuple(tuple(int(v) for v in g.split("x")) for g in args.levels.split(","))
    factors = [int(k) for k in args.factors.split(",")]
    try:
        options = ej.ShapeOptions(
            levels=levels,
            interpolation=args.interpolation,
            stretch_quadrature=args.stretch,
            stretch_subdivision=args.subdivision,
            quadrature=args.quadrature,
        )
    except ej.InputError as error:
        parser.error(str(error))
    path_only_up_to = tuple(int(v) for v in args.path_only_up_to.split("x"))
    settings = {
        "metric": [1.0, 1.0, 0.1, 0.0],
        "modulo": "rigid",
        "dtype": "float64",
        "levels": [list(g) for g in levels],
        "interpolation": args.interpolation,
        "balanced": args.balanced,
        "turn_degrees": args.turn,
        "fourier": args.fourier,
        "floor": args.floor if args.floor is not None else _bases.RESOLUTION_FACTOR,
        "stretch_quadrature": options.level_stretch,  # what the levels integrated by
        "stretch_subdivision": args.subdivision,
        "quadrature": options.level_quadrature,  # what the levels integrated by
    }
    for pair in args.pairs.split(","):
        names = PAIRS[pair]
        f1, f2 = (load(name) for name in names)
        if f1 is None or f2 is None:
            emit({"benchmark": "order", "pair": pair, "skipped": "data absent"})
            continue
        if args.balanced:
            f1, f2 = (balanced(f) for f in (f1, f2))
        if args.turn:
            f1, f2 = (turned(f, args.turn) for f in (f1, f2))
        if args.fourier:
            f1, f2 = (fourier_read(f) for f in (f1, f2))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ej.ConvergenceWarning)
            solved = levels_of(f1, f2, options)
            distances = []
            for (m, n), result, seconds in solved:
                distances.append(float(result.distance))
                record = {
                    "benchmark": "order",
                    "pair": pair,
                    "level": [m, n],
                    "distance": distances[-1],
                    "converged": bool(result.converged),
                    "result": ej.RESULTS.name(result.result),
                    "seconds": seconds,
                }
                at = {}  # one problem and one read of gamma per grid
                for k in sorted({*factors, 2}):
                    grid = (k * (m - 1) + 1, k * (n - 1) + 1)
                    at[k] = evaluation(f1, f2, result, grid, options)
                record["quadrature"] = [quadrature_record(at[k], result) for k in factors]
                record["correspondence"] = correspondence_record(at[2], result)
                if args.path_only and m * n <= path_only_up_to[0] * path_only_up_to[1]:
                    record["path_only"] = path_only(at[2], result)
                emit(record)
            basin = basin_record(f1, f2, solved, options) if args.down else None
        changes = np.abs(np.diff(distances))
        emit(
            {
                "benchmark": "order_summary",
                "pair": pair,
                "distances": distances,
                "changes": changes.tolist(),
                "observed_orders": observed_orders(distances),
                "basin": basin,
                "density_quantiles": {
                    name: density_quantiles(f) for name, f in zip(names, (f1, f2), strict=True)
                },
                "settings": settings,
                "environment": environment(),
            }
        )


if __name__ == "__main__":
    main()
