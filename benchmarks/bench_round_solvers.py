"""The registration rounds' solver: the package's BFGS against Levenberg-Marquardt with
conjugate gradients on the energy's residuals, on the first round of a level.

The rounds minimize the path energy over the path's whitened coefficients and a Diff
step (and a rotation) together. That energy is a sum of squares with weights >= 0
(math §3; metric.split_residuals at every node and sub-point of the level's rule, the
stretched cells' correction folded into the nodes' weights), so a Gauss-Newton method
could use its structure where BFGS learns a Hessian from gradients. This measures both
on the same problem: for each pair, the levels below ``--level`` are solved once (kept
in ``--keep``, shared with ``bench_finest.py``), their registration and path are read on
``--level``'s grid, and the first round's objective is minimized from there:

- ``bfgs``: the package's solver (optimistix BFGS stopped by the gradient norm), cut
  after each of ``--bfgs-steps`` steps (one compiled solve, a traced cap);
- ``lm``: optimistix's Levenberg-Marquardt over the residuals, its damped step solved by
  lineax's CG on the normal equations, at most ``--cg-steps`` iterations a step (a
  truncated step is taken as it is), cut after each of ``--lm-steps`` steps.

One JSON record per run: the solver, its settings, the objective reached (energy over the
round's scale, as the solver sees it), the steps and the warm seconds (the program is
compiled before it is timed). A ``residuals`` record first states how far
the residuals' sum of squares is from the package's objective at the start.

Run: python benchmarks/bench_round_solvers.py [--pairs cats] [--level 49x97] [--keep DIR]
     [--bfgs-steps 50,100,200,400,800] [--lm-steps 3,10] [--cg-steps 20,80]
"""

from __future__ import annotations

import argparse
import pathlib
import tempfile
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import lineax as lx  # noqa: E402
import optimistix as optx  # noqa: E402
from bench_finest import METRIC, below_level  # noqa: E402
from bench_order import PAIRS, load  # noqa: E402

import elastic_jax as ej  # noqa: E402
from elastic_jax._geodesics.solvers import minimize  # noqa: E402
from elastic_jax._geometry.energy import step_frames  # noqa: E402
from elastic_jax._geometry.grid import interior_weights  # noqa: E402
from elastic_jax._geometry.metric import split_residuals  # noqa: E402
from elastic_jax._registration import problem as P  # noqa: E402
from elastic_jax._registration.one_grid import grid_setup  # noqa: E402
from elastic_jax._registration.starts import given_start  # noqa: E402
from elastic_jax._registration.stretch import cell_corners, cell_frames  # noqa: E402

from _common import emit, environment  # noqa: E402


def joint_residuals(prob, options, rigid, gamma, rotation, scaling):
    """Residuals r(z, y) with sum(r^2) = problem.joint_objective (the midpoint scheme)."""
    frames_of = P.joint_frames(prob, options, rigid, gamma, rotation, scaling)
    cells = P.stretched_cells_of(prob, options, gamma)
    read = P.source_method(options.interpolation)
    at_nodes = P.quadrature_gamma(prob, options, gamma)
    m, n = at_nodes.shape[-2:]
    weights = interior_weights(m, n, gamma.dtype)
    if cells is not None:
        # The corrected rule's node weights: each node's weight less its trapezoid shares
        # over the chosen cells around it (>= 0).
        flat, shares = cell_corners(cells, m, n, gamma.dtype)
        weights = weights.reshape(-1).at[flat.reshape(-1)].add(-shares.reshape(-1))
        weights = jnp.maximum(weights.reshape(m - 2, n - 1), 0.0)

    def pieces(frames, point_weights):
        b1, b2, v1, v2, dt = step_frames(*frames, "midpoint")
        root = jnp.sqrt(point_weights * dt[:, None, None] / scaling.energy_scale)
        return [(r * root).reshape(-1) for r in split_residuals(prob.metric, b1, b2, v1, v2)]

    def residuals(variables):
        frames, stepped, turned = frames_of(variables)
        out = pieces(frames, weights)
        if cells is not None:
            sub, sub_weights, *_ = cell_frames(
                prob.source1,
                read,
                options.interpolation,
                stepped,
                turned,
                frames,
                cells,
                options.stretch_subdivision,
            )
            out += pieces(sub, sub_weights)
        return jnp.concatenate(out)

    return residuals


class _TruncatedCG(lx.CG):
    """CG whose step limit ends the solve with what it has (an inexact Newton step),
    not with an error."""

    def compute(self, state, vector, options):
        solution, result, stats = super().compute(state, vector, options)
        cut = result == lx.RESULTS.max_steps_reached
        return solution, lx.RESULTS.where(cut, lx.RESULTS.successful, result), stats


def first_round(name: str, f1, f2, below, grid: tuple):
    """The first round's objective and residuals on ``grid``, continuing ``below``."""
    options = ej.ShapeOptions().on_level(grid)
    options, units, g1, g2, args = grid_setup(f1, f2, METRIC, options)
    bases = args[-1]
    gammas, rotations, _ = given_start((below.gamma, below.rotation), *grid, f1.dtype, True)
    coefficients = jnp.asarray(below.coefficients) / units.scale
    prob = P.make_problem(args[0], g1, g2, bases, True, options.interpolation)
    gamma, rotation = gammas[0], rotations[0]
    scaling = P.scaling_at(prob, options, gamma, rotation)
    objective = P.joint_objective(prob, options, True, gamma, rotation, scaling)
    residuals = joint_residuals(prob, options, True, gamma, rotation, scaling)
    start = (scaling.whitened(coefficients), P.zero_registration(prob, True, f1.dtype))
    value = float(jax.jit(objective)(start))
    squares = float(jnp.sum(jax.jit(residuals)(start) ** 2))
    emit(
        {
            "benchmark": "round_solvers_residuals",
            "pair": name,
            "grid": list(grid),
            "objective": value,
            "sum_of_squares": squares,
            "relative_difference": abs(squares / value - 1.0),
            "residuals": int(jax.eval_shape(residuals, start).shape[0]),
            "variables": int(sum(x.size for x in start)),
        }
    )
    return options, objective, residuals, start


def _timed(run, *args):
    """``run(*args)`` and its seconds, compiled first (not timed)."""
    compiled = run.lower(*args).compile()
    begin = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    return out, time.perf_counter() - begin


def solver_runs(name: str, grid: tuple, options, objective, residuals, start, steps: dict):
    """Each solver from ``start`` under each of its step limits: one record a run."""

    @jax.jit
    def bfgs(cap):
        found = minimize(
            objective, start, solver="bfgs", max_steps=None, tol=options.tol, step_cap=cap
        )
        return found.value, found.num_steps, found.grad_norm

    for cap in steps["bfgs_steps"]:
        (value, taken, grad), seconds = _timed(bfgs, jnp.int32(cap))
        emit(
            {
                "benchmark": "round_solvers",
                "pair": name,
                "grid": list(grid),
                "solver": "bfgs",
                "steps": int(taken),
                "objective": float(value),
                "grad_norm": float(grad),
                "seconds": seconds,
            }
        )
    for cg_steps in steps["cg_steps"]:
        for cap in steps["lm_steps"]:

            @jax.jit
            def lm(cap=cap, cg_steps=cg_steps):
                cg = _TruncatedCG(rtol=1e-2, atol=0.0, max_steps=cg_steps)
                solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8, linear_solver=lx.Normal(cg))
                sol = optx.least_squares(
                    lambda v, _: residuals(v), solver, start, max_steps=cap, throw=False
                )
                return objective(sol.value), sol.stats["num_steps"]

            (value, taken), seconds = _timed(lm)
            emit(
                {
                    "benchmark": "round_solvers",
                    "pair": name,
                    "grid": list(grid),
                    "solver": "lm",
                    "cg_steps": cg_steps,
                    "steps": int(taken),
                    "objective": float(value),
                    "seconds": seconds,
                }
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default="cats")
    parser.add_argument("--level", default="49x97")
    parser.add_argument("--keep", default=None, help="folder for the levels below")
    parser.add_argument("--bfgs-steps", default="50,100,200,400,800")
    parser.add_argument("--lm-steps", default="3,10")
    parser.add_argument("--cg-steps", default="20,80")
    args = parser.parse_args()
    grid = tuple(int(k) for k in args.level.split("x"))
    if grid not in ej.ShapeOptions().levels[1:]:
        parser.error(f"--level must be one of the default levels above the first; got {args.level}")
    steps = {}
    for flag in ("bfgs_steps", "lm_steps", "cg_steps"):
        try:
            steps[flag] = [int(k) for k in getattr(args, flag).split(",")]
        except ValueError:
            parser.error(f"--{flag.replace('_', '-')} must be integers separated by commas")
        if min(steps[flag]) < 1:
            parser.error(f"--{flag.replace('_', '-')} must be positive integers")
    keep = pathlib.Path(args.keep or tempfile.mkdtemp(prefix="bench-round-solvers-"))
    keep.mkdir(parents=True, exist_ok=True)
    emit({"benchmark": "environment", "environment": environment(), "keep": str(keep)})
    for name in args.pairs.split(","):
        f1, f2 = (load(k) for k in PAIRS[name])
        if f1 is None or f2 is None:
            emit({"benchmark": "round_solvers", "pair": name, "skipped": "data absent"})
            continue
        f1, f2 = jnp.asarray(f1), jnp.asarray(f2)
        below = below_level(name, f1, f2, keep, grid)
        options, objective, residuals, start = first_round(name, f1, f2, below, grid)

        solver_runs(name, grid, options, objective, residuals, start, steps)


if __name__ == "__main__":
    main()
