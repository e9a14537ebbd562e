"""The varifold-relaxed end condition, measured (docs/guides/registration_notes.md, "Tried and
not adopted").

The route of H2_SurfaceMatch and BaRe-ESA, put on the package's grid: the path starts at
f1 (fixed, on its own grid) and ends at a free surface f_end = f1 + sum_k c_k Y_k (real
spherical harmonics of degree <= L); the end is matched to R f2 by the varifold distance
between their triangulations (Gaussian kernel of width sigma in space, Binet kernel
(n . n')^2 / (|n| |n'|) on the normals), so f2 is never read through a reparametrization.
Objective, per stage of a schedule coarse to fine in sigma:

    E(path) + lambda * |S(f_end) - S(R f2)|_sigma^2 / |S(R f2)|_sigma^2,

minimized over the end, the path's interior (the geodesic basis of degree ``--degree``) and
R, by optimistix's BFGS. Coefficients are scaled by 1 / (1 + degree) (a diagonal
preconditioner). Each stage prints one JSON record: sqrt(E), the relative varifold
residual, the steps taken and whether BFGS met its tolerance.

``--floor`` prints instead how far the target's own triangulations are apart in the same
norm (cat2 bilinear at 25 x 49 and at 49 x 97 against its 50 x 99 data; cat1 for scale):
below the grid's spacing the varifold cannot tell a coarse sampling from another shape.

Run: python benchmarks/bench_varifold_end.py [--pair cat1,cat2] [--target g25|data]
     [--L 16] [--steps 2000] [--schedule 0.4:100,0.2:300,0.1:1000,0.05:3000] [--floor]
"""

from __future__ import annotations

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)  # a script, not the library

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402

import elastic_jax as ej  # noqa: E402
from elastic_jax._geometry.bases import basis_np, path_from_coefficients  # noqa: E402
from elastic_jax._geometry.energy import _path_energy  # noqa: E402
from elastic_jax._geometry.grid import distinct_points  # noqa: E402
from elastic_jax._geometry.grid import grid_faces as _grid_faces  # noqa: E402
from elastic_jax._geometry.harmonics import harmonics_np  # noqa: E402
from elastic_jax._geometry.so3 import so3_exp_unchecked  # noqa: E402
from elastic_jax._geometry.srnf import center_unchecked  # noqa: E402

from _common import emit, environment, shape  # noqa: E402

METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)


def _triangles(f):
    """Centres and area-weighted normals ``(T, 3)`` of the grid mesh of f ``(3, m, n)``."""
    faces = _grid_faces(*f.shape[-2:])
    v = distinct_points(f)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return (a + b + c) / 3.0, 0.5 * jnp.cross(b - a, c - a)


def _inner(s, t, sigma, block=512):
    """<S, T>_sigma = sum_ij exp(-|x_i - y_j|^2 / sigma^2) (n_i . m_j)^2 / (|n_i| |m_j|)."""
    (c1, n1), (c2, n2) = s, t
    norm2 = jnp.sqrt(jnp.sum(n2**2, -1))
    pad = (-c1.shape[0]) % block  # padded normals are 0 and add nothing

    # Recomputed in the backward pass: the kernel matrix is never stored whole.
    @jax.checkpoint
    def rows(args):
        c, n = args
        norm1 = jnp.sqrt(jnp.sum(n**2, -1) + 1e-300)
        d2 = jnp.sum(c**2, -1)[:, None] + jnp.sum(c2**2, -1)[None] - 2.0 * c @ c2.T
        return jnp.sum(jnp.exp(-d2 / sigma**2) * (n @ n2.T) ** 2 / (norm1[:, None] * norm2[None]))

    blocks = [jnp.pad(x, ((0, pad), (0, 0))).reshape(-1, block, 3) for x in (c1, n1)]
    return jnp.sum(jax.lax.map(rows, tuple(blocks)))


def _relaxed(f1, f2, *, L, degree, n_times, schedule, steps):
    m, n = f1.shape[-2:]
    target = _triangles(f2)
    harmonics = harmonics_np(m, n, L)
    y_end = jnp.asarray(harmonics.values.reshape(-1, m * n) / (1.0 + harmonics.degrees[:, None]))
    path_degrees = np.asarray(harmonics_np(m, n, degree).degrees[1:], float)
    values = jnp.asarray(basis_np(m, n, degree)[0] / (1.0 + path_degrees[:, None]))
    k = values.shape[0]

    def pieces(v, sigma):
        r = so3_exp_unchecked(v["w"])
        end = f1 + (v["c"] @ y_end).reshape(3, m, n)
        energy = _path_energy(
            METRIC, path_from_coefficients(f1, end, v["p"], values, n_times), scheme="midpoint"
        )
        s = _triangles(end)
        t = (target[0] @ r.T, target[1] @ r.T)
        # <T, T> is rotation-invariant: a constant of the objective.
        return energy, _inner(s, s, sigma) - 2.0 * _inner(s, t, sigma)

    @jax.jit
    def stage(v, sigma, lam, norm):
        def objective(v, _):
            energy, d2 = pieces(v, sigma)
            return energy + lam * (d2 + norm) / norm

        sol = optx.minimise(
            objective, optx.BFGS(rtol=1e-7, atol=1e-9), v, max_steps=steps, throw=False
        )
        energy, d2 = pieces(sol.value, sigma)
        return sol.value, energy, d2, sol.stats["num_steps"], sol.result

    v = {
        "w": jnp.zeros(3),
        "c": jnp.zeros((3, y_end.shape[0])),
        "p": jnp.zeros((n_times - 2) * 3 * k),
    }
    for sigma, lam in schedule:
        start = time.perf_counter()
        norm = _inner(target, target, sigma)
        v, energy, d2, num, result = stage(v, sigma, lam, norm)
        yield {
            "sigma": sigma,
            "lambda": lam,
            "distance": float(jnp.sqrt(energy)),
            "varifold_residual": float(jnp.sqrt(jnp.maximum(d2 + norm, 0.0) / norm)),
            "steps": int(num),
            "bfgs_converged": bool(result == optx.RESULTS.successful),
            "seconds": time.perf_counter() - start,
        }


def _load(name):
    f = shape(name)
    return None if f is None else jnp.asarray(f)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pair", default="cat1,cat2")
    parser.add_argument("--target", choices=("g25", "data"), default="g25")
    parser.add_argument("--L", type=int, default=16)
    parser.add_argument("--degree", type=int, default=7)
    parser.add_argument("--n-times", type=int, default=13)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--schedule", default="0.4:100,0.2:300,0.1:1000,0.05:3000")
    parser.add_argument("--floor", action="store_true")
    args = parser.parse_args()
    names = args.pair.split(",")
    f1, f2 = (_load(s) for s in names)
    if f1 is None or f2 is None:
        emit({"skipped": f"{args.pair}: the authors' surfaces (elastic_jax.datasets) are absent"})
        return
    f1, f2 = center_unchecked(f1), center_unchecked(f2)
    base = {"benchmark": "varifold_end", "pair": args.pair, **environment()}
    if args.floor:
        data = _triangles(f2)
        coarse = ej.resample(f2, 25, 49)
        for sigma in (0.4, 0.2, 0.1, 0.05, 0.025):
            norm = _inner(data, data, sigma)

            def residual(f, sigma=sigma, norm=norm):
                s = _triangles(center_unchecked(f))
                d2 = _inner(s, s, sigma) - 2.0 * _inner(s, data, sigma) + norm
                return float(jnp.sqrt(d2 / norm))

            emit(
                {
                    **base,
                    "sigma": sigma,
                    f"{names[1]}_25x49": residual(coarse),
                    f"{names[1]}_49x97_from_25x49": residual(ej.resample(coarse, 49, 97)),
                    f"{names[0]}_25x49": residual(ej.resample(f1, 25, 49)),
                }
            )
        return
    source = center_unchecked(ej.resample(f1, 25, 49))
    target = f2 if args.target == "data" else center_unchecked(ej.resample(f2, 25, 49))
    schedule = [tuple(float(x) for x in p.split(":")) for p in args.schedule.split(",")]
    settings = {"target": args.target, "L": args.L, "degree": args.degree, "steps": args.steps}
    for record in _relaxed(
        source,
        target,
        L=args.L,
        degree=args.degree,
        n_times=args.n_times,
        schedule=schedule,
        steps=args.steps,
    ):
        emit({**base, **settings, **record})


if __name__ == "__main__":
    main()
