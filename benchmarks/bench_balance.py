"""Whether balancing an input's area measure undoes a Moebius read of it, up to a rotation.

A start that moves with the inputs' parametrizations would make a resolved distance
independent of a Moebius read of an input (docs/guides/registration_notes.md, "Open").
This measures the step it rests on, on the authors' surfaces. For a surface f on the grid,
mu_f is its area measure on the parameter sphere (each mesh triangle's area shared among
its three vertices, ``elastic_jax.io.grid_to_mesh``), and its balancing map is the
Moebius map phi_a whose push-forward of mu_f has its centre of mass at the origin:

    sum_k w_k phi_a(u_k) = 0,     w_k: vertex k's share of f's area, u_k its direction,

solved for a in the open unit ball by scipy's ``root`` (a = tanh(|b|) b / |b|). f o
phi_a^-1 is then balanced, and the balanced surface is unique up to a rotation of the
parameter sphere (the Douady-Earle barycentre). For f read through phi_c (a Moebius map
of boost c) and turned in space, f' = R (f o phi_c), the balancing maps obey
phi_a' = r o phi_a o phi_c for a rotation r, so the map

    psi = phi_a' o phi_c^-1 o phi_a^-1

between the two balanced parametrizations is a rotation. The record gives how far psi
is from its nearest rotation (Kabsch, on the 25 x 49 grid's points: the largest and
mean distance on the unit sphere), next to phi_c^-1 itself, and both balancing boosts.

Inputs: each surface read at 99 x 197 by its spline, as given and through the Moebius
map of ``bench_levels.py --moebius A`` (boost A along (0.36, -0.48, 0.8), turned in space
by ``shapes.random_rotation(7)``). float64, CPU.

Run: python benchmarks/bench_balance.py [--shapes cat1,cat2,horse0,hand4] [--moebius 0.3]
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from bench_levels import MOEBIUS_DIRECTION  # noqa: E402
from scipy.optimize import root  # noqa: E402

import elastic_jax as ej  # noqa: E402

from _common import emit, environment, moebius_read, shape  # noqa: E402

READ = (99, 197)
CHECK = (25, 49)


def vertex_weights(f) -> tuple[np.ndarray, np.ndarray]:
    """f's area shared among its grid mesh's vertices (weights summing to 1) and each
    vertex's direction on the parameter sphere (the same mesh of the sphere's points)."""
    mesh = ej.io.grid_to_mesh(np.asarray(f))
    areas = np.zeros(len(mesh.vertices))
    for corner in range(3):
        areas += np.bincount(mesh.faces[:, corner], mesh.area_faces, len(mesh.vertices))
    directions = ej.io.grid_to_mesh(ej.sphere_points(*np.shape(f)[-2:])).vertices
    return areas / areas.sum(), np.asarray(directions).T


def into_ball(b: np.ndarray) -> np.ndarray:
    r = float(np.linalg.norm(b))
    return b if r == 0.0 else np.tanh(r) * b / r


def balancing_boost(f) -> tuple[np.ndarray, float]:
    """The boost a of f's balancing map and the norm of the centre of mass it leaves."""
    weights, directions = vertex_weights(f)

    def centre(b: np.ndarray) -> np.ndarray:
        return np.asarray(ej.moebius(jnp.asarray(directions), jnp.asarray(into_ball(b)))) @ weights

    solution = root(centre, np.zeros(3), tol=1e-13)
    return into_ball(solution.x), float(np.linalg.norm(centre(solution.x)))


def from_rotation(points: np.ndarray, mapped: np.ndarray) -> tuple[float, float]:
    """The largest and mean distance of ``mapped`` (3, P) from the rotation of ``points``
    (3, P) that fits it best (Kabsch)."""
    u, _, vt = np.linalg.svd(mapped @ points.T)
    rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    gaps = np.linalg.norm(mapped - rotation @ points, axis=0)
    return float(gaps.max()), float(gaps.mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", default="cat1,cat2,horse0,hand4")
    parser.add_argument("--moebius", type=float, default=0.3)
    args = parser.parse_args()
    if not 0.0 < args.moebius < 1.0:
        parser.error(f"--moebius must lie in (0, 1); got {args.moebius}")
    unknown = sorted(set(args.shapes.split(",")) - set(ej.datasets.names()))
    if unknown:
        parser.error(
            f"--shapes: unknown {', '.join(unknown)}; the names are "
            f"{', '.join(ej.datasets.names())}"
        )
    boost = args.moebius * MOEBIUS_DIRECTION / np.linalg.norm(MOEBIUS_DIRECTION)
    points = np.asarray(ej.sphere_points(*CHECK)).reshape(3, -1)
    for name in args.shapes.split(","):
        f = shape(name)
        if f is None:
            continue
        given = moebius_read(jnp.asarray(f), np.zeros(3), np.eye(3), READ)
        read = moebius_read(jnp.asarray(f), boost, ej.shapes.random_rotation(7), READ)
        a, left = balancing_boost(given)
        a_read, left_read = balancing_boost(read)
        psi = ej.moebius(ej.moebius(ej.moebius(jnp.asarray(points), -a), -boost), a_read)
        unbalanced = ej.moebius(jnp.asarray(points), -boost)
        emit(
            {
                "benchmark": "balance",
                "shape": name,
                "moebius": args.moebius,
                "read": list(READ),
                "check_grid": list(CHECK),
                "boost_given": a.tolist(),
                "boost_read": a_read.tolist(),
                "centre_left": [left, left_read],
                "balanced_from_rotation": from_rotation(points, np.asarray(psi)),
                "read_from_rotation": from_rotation(points, np.asarray(unbalanced)),
                "environment": environment(),
            }
        )


if __name__ == "__main__":
    main()
