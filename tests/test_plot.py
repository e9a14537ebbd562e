import os

import matplotlib.image
import numpy as np
import pytest
from matplotlib import colors as mcolors
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from elastic_jax import InputError, plot, shapes

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


def _texts(fig):
    """The figure's own texts other than the suptitle: plot_modes' row labels."""
    return [t.get_text() for t in fig.texts if t is not fig._suptitle]


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
    # More than 7 frames: the most frames (7 down to 4) at exactly equal steps, ends
    # included; 7 at rounded steps when no such count divides N - 1.
    assert _titles(plot.plot_path(_path(9))) == [f"t = {k}/8" for k in (0, 2, 4, 6, 8)]
    assert _titles(plot.plot_path(_path(8))) == [f"t = {k}/7" for k in (0, 1, 2, 4, 5, 6, 7)]


def test_default_frames_are_evenly_spaced_when_the_path_allows():
    """The default takes the most frames (7 down to 4) whose steps are exactly equal."""
    for count, expected in [
        (10, [0, 3, 6, 9]),
        (13, list(range(0, 13, 2))),
        (11, [0, 2, 4, 6, 8, 10]),
        (26, [0, 5, 10, 15, 20, 25]),
        (12, [0, 2, 4, 6, 7, 9, 11]),  # 11 steps: no count from 4 to 7 divides them
    ]:
        chosen = plot._choose_frames(None, count)
        assert chosen == expected
        if count != 12:
            assert len(set(np.diff(chosen))) == 1
    fig = plot.plot_path(np.stack([_path(5)[0]] * 10))
    assert _titles(fig) == ["t = 0/9", "t = 3/9", "t = 6/9", "t = 9/9"]


def test_plot_path_titles_and_suptitle():
    stack = _path(5)[[0, 2, 4]]  # three different shapes, not a path
    names = ["sphere", "half way", "bumpy"]
    fig = plot.plot_path(stack, titles=names, suptitle="three shapes")
    assert _titles(fig) == names
    assert fig._suptitle.get_text() == "three shapes"
    # The suptitle gets its own band: the figure is 0.4 inches higher, the axes below it.
    assert fig.get_size_inches()[1] == pytest.approx(2.8 + 0.4)
    assert max(ax.get_position().y1 for ax in fig.axes) <= 1 - 0.65 / 3.2 + 1e-12
    # Titles follow the chosen frames, in their order.
    fig = plot.plot_path(_path(5), frames=[4, 1], titles=["last", "second"])
    assert _titles(fig) == ["last", "second"]
    assert plot.plot_path(_path(5))._suptitle is None


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"titles": ["a", "b"]}, r"got 2 titles for 5 drawn frame\(s\)"),
        ({"titles": ["a"], "frames": 3}, r"got 1 titles for 3 drawn frame\(s\)"),
        ({"titles": "abcde"}, r"titles must be a sequence of strings"),
        ({"suptitle": 3}, r"suptitle must be a string or None; got 3"),
        ({"view": "side"}, r"view must be one of \('default', 'fit'\); got 'side'"),
    ],
)
def test_plot_path_rejects_bad_titles_and_views(kwargs, message):
    with pytest.raises(InputError, match=message):
        plot.plot_path(_path(5), **kwargs)


def _white_fraction(fig, dpi=50):
    """Share of near-white pixels (R, G and B >= 0.95) in each axes' panel of the image."""
    canvas = FigureCanvasAgg(fig)
    fig.set_dpi(dpi)
    canvas.draw()
    rgb = np.asarray(canvas.buffer_rgba())[..., :3] / 255.0
    height, width = rgb.shape[:2]
    fractions = []
    for ax in fig.axes:
        box = ax.get_position(original=True)
        rows = slice(round((1 - box.y1) * height), round((1 - box.y0) * height))
        cols = slice(round(box.x0 * width), round(box.x1 * width))
        fractions.append(float(np.mean(np.all(rgb[rows, cols] >= 0.95, axis=-1))))
    return np.array(fractions)


def _long_ellipsoid():
    """An ellipsoid 4 long along z (matplotlib's default vertical), 1.2 and 0.6 across."""
    return np.array(shapes.sample(shapes.ellipsoid, M, N, axes=(0.6, 0.3, 2.0)))


def test_fit_view_fills_the_panel():
    f = _long_ellipsoid()
    default = _white_fraction(plot.plot_path(f))
    fig = plot.plot_path(f, view="fit")
    fitted = _white_fraction(fig)
    # Measured 0.81 (default: the ellipsoid stands in a tall panel) and 0.25 (fit).
    assert default[0] > 0.75
    assert fitted[0] < 0.3
    assert fitted[0] < default[0] - 0.5
    # The panel takes the image's aspect: 2.5 inches wide, flatter than the default's 2.55.
    width, height = fig.get_size_inches()
    assert width == 2.5 and height - 0.25 < 1.5
    # A rigid motion of the surface: every edge keeps its length; the longest axis (z) is
    # across (x), the second (x) up (z), the thinnest (y) in depth.
    (drawn,) = (np.asarray(ax.collections[0]._faces) for ax in fig.axes)
    given = plot._cells(f)
    for a, b in [(0, 1), (1, 2), (0, 2)]:
        np.testing.assert_allclose(
            np.linalg.norm(drawn[:, a] - drawn[:, b], axis=-1),
            np.linalg.norm(given[:, a] - given[:, b], axis=-1),
            rtol=0,
            atol=1e-12,
        )
    extent = np.ptp(drawn.reshape(-1, 3), axis=0)
    np.testing.assert_allclose(extent, np.ptp(given.reshape(-1, 3), axis=0)[[2, 1, 0]], atol=1e-9)
    # Given angles override the view's; the fit is kept.
    ax = plot.plot_path(f, view="fit", elev=5, azim=-90).axes[0]
    assert (ax.elev, ax.azim) == (5, -90)


def test_fit_view_of_modes_fills_the_panels():
    _, paths = _mode_paths(9)
    long = [p * np.array([0.6, 0.3, 2.0])[:, None, None] for p in paths]
    default = _white_fraction(plot.plot_modes(long, columns=3))
    fitted = _white_fraction(plot.plot_modes(long, columns=3, view="fit", suptitle="modes"))
    # Measured 0.78-0.88 and 0.38-0.66 (one box for frames of different sizes).
    assert default.min() > 0.75
    assert fitted.max() < 0.7
    assert np.all(fitted < default - 0.15)
    assert fitted.mean() < default.mean() - 0.25


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


def test_plot_energy_title():
    fig = plot.plot_energy(np.array([3.0, 2.0, 1.5]), title="path energy per round")
    assert fig.axes[0].get_title() == "path energy per round"
    assert plot.plot_energy(np.array([3.0, 2.0])).axes[0].get_title() == ""
    with pytest.raises(InputError, match=r"title must be a string or None; got 1"):
        plot.plot_energy(np.array([3.0, 2.0]), title=1)


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


def test_plot_distance_matrix_title_label_and_annotations():
    D = _distances()
    fig = plot.plot_distance_matrix(
        D, labels=["a", "b", "c", "d"], title="shape distances", label="d (rigid)", annotate=True
    )
    ax, colorbar = fig.axes
    assert ax.get_title() == "shape distances"
    assert colorbar.get_ylabel() == "d (rigid)"
    texts = ax.texts
    assert [t.get_text() for t in texts] == [f"{d:.3g}" for d in D.ravel()]
    # Each at its cell's centre, in a colour that reads on the cell.
    assert [t.get_position() for t in texts[:2]] == [(0, 0), (1, 0)]
    assert {mcolors.to_hex(t.get_color()) for t in texts} <= {"#000000", "#ffffff"}
    assert mcolors.to_hex(texts[0].get_color()) == "#ffffff"  # D[0, 0] = 0: dark viridis
    assert len(plot.plot_distance_matrix(D).axes[0].texts) == 0
    assert plot.plot_distance_matrix(D).axes[0].get_title() == ""
    for kwargs, message in [
        ({"title": 1}, r"title must be a string or None; got 1"),
        ({"label": None}, r"label must be a string; got None"),
        ({"annotate": "yes"}, r"annotate must be True or False; got 'yes'"),
    ]:
        with pytest.raises(InputError, match=message):
            plot.plot_distance_matrix(D, **kwargs)


def test_plot_distance_matrix_rejects_wrong_labels():
    with pytest.raises(ValueError, match=r"got 2 labels for a 4 x 4 matrix"):
        plot.plot_distance_matrix(_distances(), labels=["a", "b"])


# plot_modes: tiny grids, so that shooting a mode compiles and runs in seconds.
MM, NM = 9, 17


def _drawn_quads(ax):
    # A 3D collection keeps its faces only privately (``_faces``, matplotlib >= 3.10).
    (coll,) = ax.collections
    return np.asarray(coll._faces)


def _mode_paths(count=9):
    """Two synthetic mode paths through one ellipsoid: x stretched, then z stretched."""
    mean = np.array(shapes.sample(shapes.ellipsoid, MM, NM))
    s = np.linspace(-1.0, 1.0, count)[:, None, None, None]
    along_x = mean * (1 + 0.2 * s * np.array([1.0, 0.0, 0.0])[:, None, None])
    along_z = mean * (1 + 0.3 * s * np.array([0.0, 0.0, 1.0])[:, None, None])
    return mean, [along_x, along_z]


def test_plot_modes_draws_rows_of_modes_through_the_mean():
    mean, paths = _mode_paths(9)
    fig = plot.plot_modes(paths, explained=[0.7312, 0.2449], columns=5, sigmas=1.5)
    assert len(fig.axes) == 2 * 5
    assert [ax.name for ax in fig.axes] == ["3d"] * 10
    # The columns' sigmas title the first row only; each row is named once, at its left.
    assert _titles(fig) == ["-1.5σ", "-0.75σ", "mean", "+0.75σ", "+1.5σ"] + [""] * 5
    assert _texts(fig) == ["mode 1\n(73.1%)", "mode 2\n(24.5%)"]
    # Frames 0, 2, 4, 6, 8 of each path, cell by cell; the middle column is the mean.
    for r in range(2):
        for c, frame in enumerate((0, 2, 4, 6, 8)):
            drawn = _drawn_quads(fig.axes[5 * r + c])
            np.testing.assert_array_equal(drawn, plot._cells(paths[r][frame]))
        np.testing.assert_array_equal(_drawn_quads(fig.axes[5 * r + 2]), plot._cells(mean))
    # One box for every row and column: sizes compare across modes.
    shown = np.stack([p[::2] for p in paths])
    lo, hi = shown.min(axis=(0, 1, 3, 4)), shown.max(axis=(0, 1, 3, 4))
    for ax in fig.axes:
        limits = np.array([ax.get_xlim(), ax.get_ylim(), ax.get_zlim()])
        np.testing.assert_allclose(limits, np.column_stack([lo, hi]), rtol=0, atol=1e-12)


def test_plot_modes_row_labels_and_suptitle():
    _, paths = _mode_paths(9)
    fig = plot.plot_modes(paths, explained=[0.7312, 0.2449], columns=3, suptitle="PCA")
    assert fig._suptitle.get_text() == "PCA"
    labels = [t for t in fig.texts if t is not fig._suptitle]
    assert [t.get_text() for t in labels] == ["mode 1\n(73.1%)", "mode 2\n(24.5%)"]
    # One label per row, rotated, left of the row's first axes and level with its middle;
    # no title repeats it.
    for r, label in enumerate(labels):
        box = fig.axes[3 * r].get_position(original=True)
        x, y = label.get_position()
        assert label.get_rotation() == 90
        assert x < box.x0
        assert y == pytest.approx((box.y0 + box.y1) / 2)
    assert not any("mode" in title for title in _titles(fig))
    assert _titles(fig) == ["-2σ", "mean", "+2σ", "", "", ""]


def test_plot_modes_marks_the_nodes_a_failed_shot_did_not_reach():
    """A shot that failed leaves its later nodes NaN (shoot): those columns are empty
    axes that say so, the others are drawn, and the box holds the drawn frames only."""
    _, paths = _mode_paths(9)
    failed = paths[0].copy()
    failed[:2] = np.nan  # the -sigma shot stopped after two nodes from the mean's side
    fig = plot.plot_modes([failed, paths[1]], columns=5)
    texts = [[t.get_text() for t in ax.texts] for ax in fig.axes]
    assert texts[0] == ["not reached\n(shooting failed)"]
    assert all(t == [] for t in texts[1:])
    # The fit view rotates the drawn frames only; the unreached node stays a marked panel.
    fit = plot.plot_modes([failed, paths[1]], columns=5, view="fit")
    assert [t.get_text() for t in fit.axes[0].texts] == ["not reached\n(shooting failed)"]
    assert [len(ax.collections) for ax in fit.axes] == [0] + [1] * 9
    assert _titles(fig)[0] == "-2σ"
    assert _texts(fig) == ["mode 1", "mode 2"]
    np.testing.assert_array_equal(_drawn_quads(fig.axes[1]), plot._cells(failed[2]))
    shown = np.concatenate([failed[[2, 4, 6, 8]], paths[1][::2]])
    lo, hi = shown.min(axis=(0, 2, 3)), shown.max(axis=(0, 2, 3))
    limits = np.array([fig.axes[1].get_xlim(), fig.axes[1].get_ylim(), fig.axes[1].get_zlim()])
    np.testing.assert_allclose(limits, np.column_stack([lo, hi]), rtol=0, atol=1e-12)


def test_plot_modes_selects_modes_and_columns():
    _, paths = _mode_paths(9)
    fig = plot.plot_modes(paths, modes=[1], columns=3)
    # Without fractions the row label is the mode number only.
    assert _titles(fig) == ["-2σ", "mean", "+2σ"]
    assert _texts(fig) == ["mode 2"]
    np.testing.assert_array_equal(_drawn_quads(fig.axes[2]), plot._cells(paths[1][8]))
    # Nine columns over 9 frames: every frame, in steps of sigmas / 4.
    fig = plot.plot_modes(paths, modes=1, columns=9, explained=[0.99951, 0.0004])
    assert len(fig.axes) == 9
    assert _titles(fig)[5] == "+0.5σ"
    assert _texts(fig) == ["mode 1\n(100%)"]


@pytest.mark.slow  # shooting compiles for about 20 s on 2 cores
def test_plot_modes_shoots_the_modes_of_a_tangent_pca():
    import elastic_jax as ej

    metric = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
    mean = np.array(shapes.sample(shapes.ellipsoid, MM, NM))
    # Two hand-made directions (not from a solve): stretch along x, bulge along z.
    modes = np.stack([mean * np.eye(3)[k][:, None, None] for k in (0, 2)])
    pca = ej.TangentPCA(
        mean=mean,
        modes=modes,
        variances=np.array([0.02, 0.005]),
        explained=np.array([0.8, 0.2]),
        scores=np.zeros((3, 2)),
        mean_velocity=np.zeros_like(mean),
    )
    fig = plot.plot_modes(pca, metric, columns=5, sigmas=1.0, n_times=3, degree=3)
    assert _titles(fig) == ["-1σ", "-0.5σ", "mean", "+0.5σ", "+1σ"] + [""] * 5
    assert _texts(fig) == ["mode 1\n(80%)", "mode 2\n(20%)"]
    for r in range(2):
        path = np.asarray(ej.mode_path(pca, r, metric, sigmas=1.0, n_times=3, degree=3))
        assert path.shape == (5, 3, MM, NM)
        for c in range(5):
            np.testing.assert_array_equal(_drawn_quads(fig.axes[5 * r + c]), plot._cells(path[c]))
        np.testing.assert_array_equal(_drawn_quads(fig.axes[5 * r + 2]), plot._cells(mean))
    # The shot ends are not the mean: the modes were drawn, not the base point five times.
    ends = _drawn_quads(fig.axes[0]), _drawn_quads(fig.axes[4])
    assert all(np.max(np.abs(e - plot._cells(mean))) > 0.02 for e in ends)
    with pytest.raises(ValueError, match=r"mode indices \[2\] are out of range: the PCA has 2"):
        plot.plot_modes(pca, metric, modes=[2])
    with pytest.raises(ValueError, match=r"metric is needed to shoot the modes"):
        plot.plot_modes(pca)
    with pytest.raises(ValueError, match=r"explained is read from the TangentPCA"):
        plot.plot_modes(pca, metric, explained=[0.5, 0.5])


@pytest.mark.parametrize(
    ("change", "kwargs", "message"),
    [
        (None, {"columns": 4}, r"columns=4 must be odd"),
        (None, {"columns": 1}, r"columns must be an integer >= 3; got 1"),
        (None, {"columns": 11}, r"columns=11 is more than the mode paths' 9 frames"),
        (None, {"modes": 3}, r"modes=3 must be between 1 and the 2 modes of the given paths"),
        (None, {"modes": [0, 2]}, r"mode indices \[2\] are out of range"),
        (None, {"modes": []}, r"modes is an empty sequence"),
        (None, {"modes": [0.5]}, r"modes must be a number of leading modes or a sequence"),
        (None, {"sigmas": 0}, r"sigmas must be a positive finite number"),
        (None, {"explained": [0.5]}, r"explained must hold one fraction per path, shape \(2,\)"),
        (None, {"explained": [0.5, 1.5]}, r"explained must hold fractions in \[0, 1\]"),
        (None, {"n_times": 5}, r"n_times only apply to a TangentPCA"),
        (lambda p: [p[0], p[1][:, :, :-1]], {}, r"mode paths must all have one shape"),
        (lambda p: [p[0][4]], {}, r"mode paths must all have one shape \(2N-1, 3, m, n\)"),
        (lambda p: [p[0][:8]], {}, r"odd number of frames 2N-1 >= 3.*got 8"),
        (lambda p: "paths", {}, r"pca_or_paths must be a TangentPCA or a sequence"),
        (
            lambda p: [np.where(np.arange(NM) == 3, np.nan, p[0])],
            {},
            r"frame 0 of path 0 is partly non-finite",
        ),
        (lambda p: [np.full_like(p[0], np.nan)], {}, r"no frame is finite"),
    ],
)
def test_plot_modes_rejects_bad_input(change, kwargs, message):
    _, paths = _mode_paths(9)
    if change is not None:
        paths = change(paths)
    with pytest.raises(ValueError, match=message):
        plot.plot_modes(paths, **kwargs)


def test_plot_modes_refuses_a_metric_with_paths():
    import elastic_jax as ej

    _, paths = _mode_paths(5)
    with pytest.raises(ValueError, match=r"metric is only used with a TangentPCA"):
        plot.plot_modes(paths, ej.SplitMetric(1.0, 1.0, 0.1, 0.0))


def test_a_field_colours_each_cell_by_its_corners_through_the_colour_map():
    from matplotlib import colormaps

    import elastic_jax as ej

    sphere = np.array(shapes.sample(shapes.sphere, M, N))
    scaling = ej.straight_path(sphere, 1.4 * sphere, 3)
    field = np.asarray(ej.energy_density(ej.SplitMetric(1.0, 1.0, 0.1, 0.0), scaling).area)
    fig = plot.plot_field(sphere, field, label="area term", shade=False)
    surface, bar = fig.axes
    # Per unit area: the field over the quadrature weights, then each cell's corners.
    weights = np.asarray(ej.quadrature_weights(M, N))
    per_area = np.where(weights > 0, field / np.where(weights > 0, weights, 1.0), np.nan)
    corners = [per_area[:-1, :-1], per_area[1:, :-1], per_area[1:, 1:], per_area[:-1, 1:]]
    cells = np.nanmean(np.stack(corners), axis=0)
    # A uniform scaling of the round sphere has a constant area density, 2 b (1.4 - 1)^2
    # per unit area, up to the grid differential's error.
    np.testing.assert_allclose(cells, 2.0 * 0.4**2, rtol=0.05)
    low, high = bar.get_ylim()
    assert (low, high) == pytest.approx((cells.min(), cells.max()), rel=1e-12)
    expected = colormaps["viridis"](mcolors.Normalize(low, high)(cells)).reshape(-1, 4)
    np.testing.assert_allclose(_grid_order_colors(surface), expected, atol=1e-12)
    assert bar.get_ylabel() == "area term"
    # A varying field on another surface, on a fixed scale.
    f = np.array(shapes.sample(shapes.bumpy, M, N))
    bumpy = np.asarray(f[2]) ** 2
    fig = plot.plot_field(f, bumpy, per_area=False, shade=False, limits=(0.0, 2.0))
    cells = np.mean([bumpy[:-1, :-1], bumpy[1:, :-1], bumpy[1:, 1:], bumpy[:-1, 1:]], axis=0)
    expected = colormaps["viridis"](np.clip(cells.reshape(-1) / 2.0, 0.0, 1.0))
    np.testing.assert_allclose(_grid_order_colors(fig.axes[0]), expected, atol=1e-12)
    with pytest.raises(InputError, match="grid shape"):
        plot.plot_field(f, bumpy[:, :-1])
    with pytest.raises(InputError, match="increasing"):
        plot.plot_field(f, bumpy, limits=(1.0, 1.0))
    with pytest.raises(InputError, match="cmap 'no-such-map'"):
        plot.plot_field(f, bumpy, cmap="no-such-map")
