"""The result protocol (issue 31): every result record carries ``converged``, ``result`` (an
``elastic_jax.RESULTS``, printed by name), ``message`` and ``num_steps``, and they agree:
converged exactly when the code is a converged one, a message exactly when it is not
(a Karcher mean always says which criterion stopped it), and ``num_steps`` the sum of the
solves the record is made of, counted independently.

One case per record, converged and (where a limit forces it cheaply) not, at 13 x 25 in
the configurations of tests/test_karcher.py, test_shooting.py, test_transport.py and
test_srnf_inverse.py: the same compiled programs (the suite's compilation cache holds
them), so that the protocol costs little more than the solves themselves.
"""

from __future__ import annotations

import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import elastic_jax as ej
from elastic_jax import io, shapes

M, N = 13, 25
METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
FAST = ej.ShapeOptions(degree=3, n_times=5)
SHAPE = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5)
KARCHER_CONVERGED = {"distances_at_rounding", "mean_velocity_small", "sum_sq_stalled"}


def _pair():
    return shapes.sample(shapes.sphere, M, N), shapes.sample(shapes.ellipsoid, M, N)


def _quiet(call):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ej.ConvergenceWarning)
        return call()


def _geodesic(**changes):
    f1, f2 = _pair()
    res = _quiet(lambda: ej.geodesic(f1, f2, METRIC, degree=3, n_times=5, **changes))
    return res, int(res.num_steps)


def _shape_geodesic():
    f1 = shapes.sample(shapes.sphere, M, N)
    f2 = shapes.sample(shapes.sphere, M, N, radius=2.0, rotation=shapes.random_rotation(3))
    res = ej.shape_geodesic(f1, f2, METRIC, modulo="rigid", options=SHAPE)
    return res, None  # its steps are the rounds' and the final solves', counted inside


def _shoot():
    f1, f2 = _pair()
    res = ej.shoot(f1, 0.2 * (f2 - f1), METRIC, degree=3, n_times=5)
    return res, int(np.sum(res.newton_steps))


def _transport():
    f1, f2 = _pair()
    path = ej.straight_path(f1, f2, 5)
    res = ej.parallel_transport(0.1 * (f2 - f1), path, METRIC, degree=3)
    return res, None


def _srnf_invert(degrees=(2, 3), **changes):
    f = shapes.sample(shapes.ellipsoid, M, N)
    res = _quiet(lambda: ej.srnf_invert(ej.srnf(f), degrees=degrees, **changes))
    return res, None


def _srnf_geodesic(**changes):
    f1, f2 = _pair()
    res = _quiet(lambda: ej.srnf_geodesic(f1, f2, 5, degrees=(2, 4), **changes))
    return res, int(np.sum(res.node_steps))


def _log():
    f1, f2 = _pair()
    res = ej.log(f1, f2, METRIC, options=FAST)
    return res, int(ej.geodesic(f1, f2, METRIC, **FAST.geodesic_kwargs()).num_steps)


def _karcher(**changes):
    spheres = jnp.stack([shapes.sample(shapes.sphere, M, N, radius=r) for r in (1.0, 1.5, 2.2)])
    res = _quiet(lambda: ej.karcher_mean(spheres, METRIC, modulo="none", options=FAST, **changes))
    return res, None


def _distance_matrix():
    f1, f2 = _pair()
    coll = jnp.stack([f1, f2, 1.5 * f1])
    res = ej.distance_matrix(coll, METRIC, modulo="none", options=FAST)
    singles = [
        ej.geodesic(coll[i], coll[j], METRIC, **FAST.geodesic_kwargs())
        for i, j in [(0, 1), (0, 2), (1, 2)]
    ]
    return res, sum(int(s.num_steps) for s in singles)


def _fit_metric(**changes):
    coll = jnp.stack(
        [
            shapes.sample(shapes.bent_cylinder, M, N, curvature=k, half_length=h)
            for k, h in [(0.1, 1.0), (0.1, 1.4), (0.5, 1.0), (0.5, 1.4)]
        ]
    )
    res = _quiet(
        lambda: ej.fit_metric(
            coll, [0, 0, 1, 1], modulo="none", options=FAST, strategy="loop", **changes
        )
    )
    return res, None


def _sphere_map():
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2)
    mesh.vertices *= np.asarray([1.0, 1.2, 0.8])
    res = io.spherical_parametrization(mesh, frame="input")  # symmetric: no principal frame
    return res, None


CASES = {
    "geodesic": (_geodesic, "successful"),
    "geodesic capped": (lambda: _geodesic(max_steps=1), "nonlinear_max_steps_reached"),
    "shape_geodesic": (_shape_geodesic, "successful"),
    "shoot": (_shoot, "successful"),
    "parallel_transport": (_transport, "successful"),
    "srnf_invert": (_srnf_invert, "successful"),
    "srnf_invert capped": (
        lambda: _srnf_invert(degrees=(2,), max_steps=2),
        "nonlinear_max_steps_reached",
    ),
    "srnf_geodesic": (_srnf_geodesic, "successful"),
    "srnf_geodesic capped": (lambda: _srnf_geodesic(max_steps=2), "nonlinear_max_steps_reached"),
    "log": (_log, "successful"),
    "karcher_mean": (_karcher, "mean_velocity_small"),
    "karcher_mean capped": (lambda: _karcher(max_steps=0), "max_steps_reached"),
    "distance_matrix": (_distance_matrix, "successful"),
    "spherical_parametrization": (_sphere_map, "successful"),
    "fit_metric": (_fit_metric, "successful"),
    "fit_metric capped": (lambda: _fit_metric(max_steps=0), "nonlinear_max_steps_reached"),
}


# The transport case (35 s: a configuration of its own) runs in the slow tier.
@pytest.mark.parametrize(
    "case",
    [pytest.param(c, marks=pytest.mark.slow) if c == "parallel_transport" else c for c in CASES],
)
def test_every_result_record_follows_the_protocol(case):
    make, expected = CASES[case]
    res, steps = make()
    # The code: an item of elastic_jax.RESULTS, printed by its name.
    assert isinstance(res.result, ej.RESULTS)
    name = ej.RESULTS.name(res.result)
    assert name == expected, (name, res.message)
    assert repr(res.result).startswith(f"elastic_jax.RESULTS<{name}")
    # converged exactly when the code is a converged one.
    karcher = isinstance(res, ej.KarcherResult)
    converged_codes = KARCHER_CONVERGED if karcher else {"successful"}
    assert bool(np.all(res.converged)) == (name in converged_codes)
    # A message exactly when it did not converge; a Karcher mean names its criterion.
    assert isinstance(res.message, str)
    if karcher:
        assert res.message.startswith("converged" if res.converged else "stopped")
    else:
        assert (res.message == "") == (name == "successful"), res.message
    # num_steps: a count, and the sum of the record's own solves where they are listed.
    assert int(res.num_steps) >= (1 if name == "successful" and not karcher else 0)
    if steps is not None:
        assert int(res.num_steps) == steps
