"""Hostile input: every bad option a ValueError naming it, float32 at any scale, gradients
through solves that did not converge, and the library's errors naming the file."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import io, shapes
from elastic_jax._statistics import batching as _batching

M, N = 13, 25
METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
F1 = np.asarray(shapes.sample(shapes.bumpy, M, N))
F2 = np.asarray(shapes.sample(shapes.bent_cylinder, M, N))
PAIR = np.stack([F1, F2])


def _library_cases():
    nan_init = np.full((3, 45), np.nan)
    zeros = jnp.zeros(())
    return {  # what the call gets wrong -> (call, the word the message must contain)
        "batch_size": (
            lambda: ej.distance_matrix(PAIR, METRIC, job=ej.JobOptions(batch_size=-1)),
            "batch_size",
        ),
        "karcher max_steps": (lambda: ej.karcher_mean(PAIR, METRIC, max_steps=-1), "max_steps"),
        "step_size": (
            lambda: ej.karcher_mean(PAIR, METRIC, step_size=float("nan")),
            "step_size",
        ),
        "negative tol": (lambda: ej.geodesic(F1, F2, METRIC, tol=-1.0), "tol"),
        "nan tol": (lambda: ej.geodesic(F1, F2, METRIC, tol=float("nan")), "tol"),
        "outer_tol": (lambda: ej.ShapeOptions(outer_tol=-1e-3), "outer_tol"),
        "nan init": (
            lambda: ej.geodesic(F1, F2, METRIC, degree=3, n_times=5, init=nan_init),
            "init",
        ),
        "nan mean init": (
            lambda: ej.karcher_mean(PAIR, METRIC, init=np.full_like(F1, np.nan)),
            "init",
        ),
        "zero metric of arrays": (lambda: ej.SplitMetric(zeros, zeros, zeros, zeros), "zero"),
        "complex": (lambda: ej.geodesic(F1.astype(complex), F2, METRIC), "complex"),
        "float16": (
            lambda: ej.geodesic(F1.astype(np.float16), F2.astype(np.float16), METRIC),
            "float16",
        ),
        "even n": (lambda: ej.sphere_points(13, 24), "n=24"),
        "schedule degree": (
            lambda: ej.geodesic(F1, F2, METRIC, degree=3, n_times=5, schedule=[(0, 5)]),
            "schedule[0] degree",
        ),
        "schedule level": (
            lambda: ej.geodesic(F1, F2, METRIC, degree=3, n_times=5, schedule=[(3,)]),
            "schedule[0]",
        ),
        "schedule above": (
            lambda: ej.geodesic(F1, F2, METRIC, degree=3, n_times=5, schedule=[(4, 5)]),
            "above the final degree",
        ),
        "float n_times": (lambda: ej.geodesic(F1, F2, METRIC, n_times=5.0), "n_times"),
        "saddle_checks": (lambda: ej.geodesic(F1, F2, METRIC, saddle_checks=-1), "saddle_checks"),
        "solver": (lambda: ej.geodesic(F1, F2, METRIC, solver="adam"), "solver"),
        "strategy": (
            lambda: ej.distance_matrix(PAIR, METRIC, job=ej.JobOptions(strategy="fast")),
            "strategy",
        ),
    }


@pytest.mark.parametrize("case", sorted(_library_cases()))
def test_bad_library_options_raise_input_errors_naming_them(case):
    call, word = _library_cases()[case]
    with pytest.raises(ej.InputError, match=word.replace("[", r"\[").replace("]", r"\]")):
        call()
    assert issubclass(ej.InputError, ValueError)


def test_numpy_integers_are_integers_everywhere():
    # degree accepted np.int64 and n_times refused it: one check_int serves both now.
    a = ej.geodesic(F1, F2, METRIC, degree=np.int64(3), n_times=np.int64(5))
    b = ej.geodesic(F1, F2, METRIC, degree=3, n_times=5)
    assert float(a.distance) == float(b.distance)


@pytest.mark.parametrize("scale", [1e-30, 1e-6, 1.0, 1e6, 1e30])
def test_the_immersion_check_means_the_same_at_every_scale(scale):
    # A surface is refused as "not an immersion" only for its shape: at 1e-30 the area
    # element (1e-60) is below any absolute threshold, and a flattened surface is still
    # caught at every scale.
    assert ej.validate_surface(scale * F1).shape == F1.shape
    flat = np.array(F1)
    flat[2, 3:6] = flat[2, 3:6].mean()  # rows 3-5 flattened: a crease with zero area
    flat[:, 4] = flat[:, 4, :1]  # row 4 collapsed to a point
    with pytest.raises(ej.InputError, match="not an immersion.*row i=4"):
        ej.validate_surface(scale * flat)


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 1.0, 1e3, 1e6])
def test_float32_matches_float64_at_every_scale(scale):
    """The energy is homogeneous of degree 2: solves run in the surfaces' own units."""
    offset = 0.7 * scale  # and away from the origin
    f1, f2 = scale * F1 + offset, scale * F2 + offset
    d64 = ej.geodesic(f1, f2, METRIC, degree=3, n_times=5)
    d32 = ej.geodesic(f1.astype(np.float32), f2.astype(np.float32), METRIC, degree=3, n_times=5)
    unit = ej.geodesic(F1, F2, METRIC, degree=3, n_times=5)
    assert bool(d64.converged) and bool(d32.converged)
    assert float(d32.grad_norm) <= 3e-3  # float32's default tol
    assert float(d32.distance) == pytest.approx(float(d64.distance), rel=1e-3)
    # Scale covariance of the float64 solve: d(s f1 + c, s f2 + c) = s d(f1, f2).
    assert float(d64.distance) == pytest.approx(scale * float(unit.distance), rel=1e-9)
    np.testing.assert_allclose(d64.path, scale * np.asarray(unit.path) + offset, rtol=1e-7)
    np.testing.assert_array_equal(d64.path[0], f1)  # the ends are the inputs exactly


@pytest.mark.slow
def test_tol_means_the_gradient_norm_for_both_solvers():
    results = {
        (solver, tol): ej.geodesic(F1, F2, METRIC, degree=3, n_times=5, solver=solver, tol=tol)
        for solver, tol in (("bfgs", 1e-6), ("bfgs", 1e-3), ("lbfgs", 1e-3))
    }
    for (solver, tol), res in results.items():
        assert bool(res.converged), (solver, tol)
        assert float(res.grad_norm) <= tol, (solver, tol, float(res.grad_norm))
    d = {key: float(res.distance) for key, res in results.items()}
    # Near a minimum (Hessian ~2 I) the scaled energy is within ~|grad|^2 / 4 of it.
    assert d["bfgs", 1e-3] == pytest.approx(d["bfgs", 1e-6], rel=1e-6)
    assert d["lbfgs", 1e-3] == pytest.approx(d["bfgs", 1e-6], rel=1e-6)


def test_a_tol_below_rounding_reports_a_stall_not_convergence():
    f1, f2 = F1.astype(np.float32), F2.astype(np.float32)
    with pytest.warns(ej.ConvergenceWarning, match="stopped making progress"):
        res = ej.geodesic(f1, f2, METRIC, degree=3, n_times=5, tol=1e-9)
    assert not bool(res.converged) and res.result == ej.RESULTS.stalled
    assert float(res.grad_norm) > 1e-9 and int(res.num_steps) < 1000


def _directional(fun, f, v, h=1e-5):
    """Central difference of fun at f along v, and the autodiff gradient's component."""
    fd = (float(fun(f + h * v)) - float(fun(f - h * v))) / (2 * h)
    return fd, float(jnp.sum(jax.grad(fun)(jnp.asarray(f)) * v))


def test_distance_gradients_are_the_envelope_derivative():
    """d d / d f2 at the optimum is the energy's partial derivative (envelope theorem):
    reverse mode never differentiates the solver's loops, and it agrees with finite
    differences of whole solves."""
    v = np.asarray(shapes.sample(shapes.ellipsoid, M, N, axes=(1.0, 0.8, 0.6)))

    def distance(f2):
        return ej.geodesic(F1, f2, METRIC, degree=3, n_times=5).distance

    fd, ad = _directional(distance, F2, v)
    assert ad == pytest.approx(fd, rel=1e-5)


@pytest.mark.slow
def test_gradient_through_a_shape_solve_that_did_not_converge():
    """The convergence warning reads only concrete values: jax.grad goes through."""
    options = ej.ShapeOptions(
        degree=2, vf_degree=2, n_times=3, outer_steps=1, max_steps=3, init="none",
        refinement=False, saddle_checks=0, rtol=None,
    )  # fmt: skip

    def distance(f2):
        return ej.shape_geodesic(F1, f2, METRIC, options=options).distance

    with pytest.warns(ej.ConvergenceWarning, match="not converged"):
        grad = jax.grad(distance)(jnp.asarray(F2))
    assert grad.shape == F2.shape and bool(jnp.all(jnp.isfinite(grad)))
    # Not an optimum (3 steps): the gradient is the energy's at the returned gamma, C.
    assert float(jnp.linalg.norm(grad)) > 0.1


def test_the_last_chunk_is_padded_to_the_compiled_batch():
    options = ej.ShapeOptions(degree=3, n_times=5)
    shapes3 = np.stack([F1, F2, 1.5 * F1])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        before = _batching._distances_batch.jitted()._cache_size()
        res = ej.distance_matrix(
            shapes3,
            METRIC,
            modulo="none",
            options=options,
            job=ej.JobOptions(batch_size=2, strategy="map"),
        )
        # Three pairs in chunks of 2 and 1: one compilation, not two.
        assert _batching._distances_batch.jitted()._cache_size() - before == 1
    single = ej.geodesic(F2, 1.5 * F1, METRIC, degree=3, n_times=5)
    assert float(res.distances[1, 2]) == pytest.approx(float(single.distance), rel=1e-9)


def test_library_read_errors_name_the_file(tmp_path):
    good = io.save_surface(F1, tmp_path / "good.npz")
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[:200])
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9\n")
    for path in (truncated, garbage):
        with pytest.raises(ej.InputError, match=path.name):
            io.load_surface(path)
