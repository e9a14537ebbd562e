import os

import matplotlib.image
import numpy as np
import pytest
from matplotlib import colors as mcolors
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from elastic_jax import plot, shapes

M, N = 13, 25
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _path(count=5):
    """A straight line from a small sphere to the bumpy surface: frames of different sizes."""
    f0 = np.array(shapes.sample(shapes.sphere, M, N, radius=0.5))
    f1 = np.array(shapes.sample(shapes.bumpy, M, N))
    t = np.linspace(0.0, 1.0, count)[:, None, None, None]
    return (1 - t) * f0 + t * f1


def _grid_order_colors(ax):
    # Poly3DCollection.get_facecolor returns the colours sorted by depth for the current
    # view; the PolyCollection level keeps them in the order the cells were given.
    (coll,) = ax.collections
    return np.asarray(PolyCollection.get_facecolor(coll))


def _titles(fig):
    return [ax.get_title() for ax in fig.axes]


def test_plot_path_draws_one_3d_axes_per_frame():
    fig = plot.plot_path(_path(5))
    assert isinstance(fig, Figure)
    assert [ax.name for ax in fig.axes] == ["3d"] * 5
    assert _titles(fig) == [f"t = {k}/4" for k in range(5)]
    # One quadrilateral per grid cell.
    assert all(len(_grid_order_colors(ax)) == (M - 1) * (N - 1) for ax in fig.axes)


def test_plot_path_frame_selection():
    path = _path(5)
    assert _titles(plot.plot_path(path, frames=3)) == ["t = 0/4", "t = 2/4", "t = 4/4"]
    assert _titles(plot.plot_path(path, frames=[4, 1])) == ["t = 4/4", "t = 1/4"]
    assert _titles(plot.plot_path(path, frames=1)) == ["t = 0/4"]
    # More than 7 frames: 7 chosen evenly, ends included.
    long = plot.plot_path(_path(9))
    assert _titles(long) == [f"t = {k}/8" for k in (0, 1, 3, 4, 5, 7, 8)]


def test_plot_path_accepts_a_single_surface():
    fig = plot.plot_path(_path(5)[2])
    assert _titles(fig) == ["t = 0"]


def test_all_frames_share_the_global_data_range():
    path = _path(5)
    lo, hi = path.min(axis=(0, 2, 3)), path.max(axis=(0, 2, 3))
    # The first frame alone is much smaller, so per-frame autoscaling would differ.
    assert np.all(path[0].max(axis=(1, 2)) < 0.7 * hi)
    fig = plot.plot_path(path)
    for ax in fig.axes:
        limits = np.array([ax.get_xlim(), ax.get_ylim(), ax.get_zlim()])
        np.testing.assert_allclose(limits[:, 0], lo, rtol=0, atol=1e-12)
        np.testing.assert_allclose(limits[:, 1], hi, rtol=0, atol=1e-12)
        # Equal aspect: the box's sides are proportional to the data ranges.
        box = np.asarray(ax.get_box_aspect())
        np.testing.assert_allclose(box / box.max(), (hi - lo) / (hi - lo).max(), rtol=1e-12)


def test_colours_follow_the_parametrization_not_the_geometry():
    fig = plot.plot_path(_path(5), shade=False)
    first, last = _grid_order_colors(fig.axes[0]), _grid_order_colors(fig.axes[4])
    np.testing.assert_array_equal(first, last)
    np.testing.assert_array_equal(first, plot.parametrization_colors(M, N).reshape(-1, 4))
    # Every grid cell has its own colour.
    assert len(np.unique(first, axis=0)) == (M - 1) * (N - 1)


def test_shading_scales_each_cell_and_keeps_its_hue():
    base = plot.parametrization_colors(M, N).reshape(-1, 4)
    fig = plot.plot_path(_path(5))
    factors = []
    for ax in (fig.axes[0], fig.axes[4]):
        shaded = _grid_order_colors(ax)
        ratio = shaded[:, :3] / base[:, :3]
        # One brightness factor per cell, the same on the three channels: hue unchanged.
        np.testing.assert_allclose(ratio, ratio[:, :1].repeat(3, axis=1), rtol=1e-12)
        np.testing.assert_array_equal(shaded[:, 3], 1.0)
        factors.append(ratio[:, 0])
    sphere, bumpy = factors
    assert sphere.min() >= 0.3 - 1e-12 and sphere.max() <= 1.0 + 1e-12
    # A sphere has a cell facing the light and one facing away.
    assert sphere.max() > 0.97 and sphere.min() < 0.33
    # The shading follows the geometry, unlike the colours.
    assert np.max(np.abs(sphere - bumpy)) > 0.05


def test_shading_does_not_depend_on_the_orientation():
    sphere = np.array(shapes.sample(shapes.sphere, M, N))
    mirrored = sphere[:, :, ::-1]  # theta -> -theta: the same sphere, inward normals
    ones = np.ones((M - 1, N - 1, 3))
    outward = plot.plot_path(sphere, colors=ones).axes[0]
    inward = plot.plot_path(mirrored, colors=ones).axes[0]
    a = _grid_order_colors(outward)[:, 0].reshape(M - 1, N - 1)
    b = _grid_order_colors(inward)[:, 0].reshape(M - 1, N - 1)
    # Cell (i, j) of the mirrored grid is the cell (i, N - 2 - j) of the original.
    np.testing.assert_allclose(b, a[:, ::-1], rtol=1e-12)


def test_uniform_colour():
    fig = plot.plot_path(_path(3), colors="tab:red", shade=False)
    colours = _grid_order_colors(fig.axes[1])
    np.testing.assert_array_equal(colours, np.tile(mcolors.to_rgba("tab:red"), (len(colours), 1)))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"frames": 0}, r"frames=0 must be between 1 and the path's 5 frames"),
        ({"frames": 6}, r"frames=6 must be between 1"),
        ({"frames": [0, 5]}, r"frame indices \[5\] are out of range for a path of 5 frames"),
        ({"frames": []}, r"empty"),
        ({"frames": [0.5]}, r"must be integers"),
        ({"colors": "not-a-colour"}, r"colors must be 'parametrization'"),
        ({"colors": np.ones((M, N, 3))}, r"one RGB\(A\) colour per grid cell; got \(13, 25, 3\)"),
    ],
)
def test_plot_path_rejects_bad_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        plot.plot_path(_path(5), **kwargs)


def test_plot_path_rejects_bad_surfaces():
    path = _path(5)
    with pytest.raises(ValueError, match=r"path must be a surface \(3, m, n\) or a path"):
        plot.plot_path(path[None])
    with pytest.raises(ValueError, match=r"must have shape \(\.\.\., 3, m, n\)"):
        plot.plot_path(path[:, :2])
    path[3, 1, 4, 7] = np.nan
    with pytest.raises(ValueError, match=r"non-finite.*row i=4, column j=7 of item 3"):
        plot.plot_path(path)


def test_save_figure_writes_a_png_of_the_requested_size(tmp_path):
    fig = plot.plot_path(_path(3), figsize=(4.0, 2.0))
    target = tmp_path / "path.png"
    assert plot.save_figure(fig, target, dpi=30) == target
    assert target.read_bytes()[:8] == PNG_MAGIC
    pixels = matplotlib.image.imread(target)
    assert pixels.shape[:2] == (60, 120)  # (height, width) = figsize * dpi
    # The surfaces were drawn: the picture is not blank.
    assert len(np.unique(pixels.reshape(-1, pixels.shape[-1]), axis=0)) > 10
    assert os.listdir(tmp_path) == ["path.png"]


def test_save_figure_interrupted_leaves_no_file(tmp_path, monkeypatch):
    def half_written(self, fname, **kwargs):
        with open(fname, "wb") as fh:
            fh.write(PNG_MAGIC)
        raise KeyboardInterrupt

    monkeypatch.setattr(Figure, "savefig", half_written)
    fig = plot.plot_energy(np.arange(1.0, 5.0))
    with pytest.raises(KeyboardInterrupt):
        plot.save_figure(fig, tmp_path / "energy.png")
    assert os.listdir(tmp_path) == []
    # An existing file is left as it was.
    old = tmp_path / "energy.png"
    old.write_bytes(b"old")
    with pytest.raises(KeyboardInterrupt):
        plot.save_figure(fig, old)
    assert os.listdir(tmp_path) == ["energy.png"]
    assert old.read_bytes() == b"old"


def test_plot_energy_array_columns():
    history = np.array([[10.0, 1.0], [4.0, 0.3], [3.5, 0.02], [3.49, 1e-4]])
    fig = plot.plot_energy(history, labels=["sum of squares", "velocity"])
    (ax,) = fig.axes
    lines = ax.get_lines()
    assert len(lines) == 2
    for j, line in enumerate(lines):
        np.testing.assert_array_equal(line.get_ydata(), history[:, j])
        np.testing.assert_array_equal(line.get_xdata(), np.arange(4))
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["sum of squares", "velocity"]
    assert ax.get_yscale() == "log"
    assert plot.plot_energy(history, logy=False).axes[0].get_yscale() == "linear"
    one = plot.plot_energy(history[:, 0]).axes[0]
    np.testing.assert_array_equal(one.get_lines()[0].get_ydata(), history[:, 0])
    assert one.get_legend() is None


def test_plot_energy_dict_and_nonpositive_values():
    history = {"energy": [3.0, 2.0, 1.5], "gradient": [1.0, 0.5, 0.0, 0.0]}
    (ax,) = plot.plot_energy(history).axes
    lines = ax.get_lines()
    assert [line.get_label() for line in lines] == ["energy", "gradient"]
    np.testing.assert_array_equal(lines[1].get_ydata(), history["gradient"])
    # A zero cannot go on a log axis.
    assert ax.get_yscale() == "linear"


@pytest.mark.parametrize(
    ("history", "kwargs", "message"),
    [
        (np.array([1.0, 2.0, 3.0, np.nan]), {}, r"1 non-finite value\(s\), the first at step 3"),
        (np.ones((3, 2, 2)), {}, r"shape \(steps,\) or \(steps, k\); got \(3, 2, 2\)"),
        (np.ones((3, 2)), {"labels": ["a"]}, r"got 1 labels for 2 history column\(s\)"),
        ({"a": [1.0, np.inf]}, {}, r"'a' has 1 non-finite"),
        ({"a": [1.0]}, {"labels": ["b"]}, r"labels cannot be given with a dict"),
        ({}, {}, r"empty dict"),
    ],
)
def test_plot_energy_rejects_bad_input(history, kwargs, message):
    with pytest.raises(ValueError, match=message):
        plot.plot_energy(history, **kwargs)


def _distances(k=4, seed=0):
    points = np.random.default_rng(seed).standard_normal((k, 3))
    return np.linalg.norm(points[:, None] - points[None], axis=-1)


def test_plot_distance_matrix_shows_the_matrix():
    D = _distances()
    names = ["a", "b", "c", "d"]
    fig = plot.plot_distance_matrix(D, labels=names)
    ax, colorbar = fig.axes
    (image,) = ax.get_images()
    np.testing.assert_array_equal(image.get_array(), D)
    assert image.get_clim() == (D.min(), D.max())
    assert [t.get_text() for t in ax.get_xticklabels()] == names
    assert [t.get_text() for t in ax.get_yticklabels()] == names
    assert colorbar.get_ylabel() == "distance"
    # Asymmetry below 1e-8 relative is rounding, accepted.
    D[0, 1] *= 1 + 1e-10
    plot.plot_distance_matrix(D)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda D: D[:3], r"square matrix \(K, K\); got shape \(3, 4\)"),
        (lambda D: D[0], r"square matrix"),
        (lambda D: D + 1e-6 * (np.arange(16).reshape(4, 4) == 7), r"not symmetric: D\[1, 3\]"),
        (
            lambda D: np.where(np.arange(4) == 2, np.nan, D),
            r"non-finite value\(s\) \(NaN or inf\), the first at \(0, 2\)",
        ),
    ],
)
def test_plot_distance_matrix_rejects_bad_matrices(change, message):
    with pytest.raises(ValueError, match=message):
        plot.plot_distance_matrix(change(_distances()))


def test_plot_distance_matrix_rejects_wrong_labels():
    with pytest.raises(ValueError, match=r"got 2 labels for a 4 x 4 matrix"):
        plot.plot_distance_matrix(_distances(), labels=["a", "b"])
