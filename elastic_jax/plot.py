"""Figures: geodesic paths, principal modes, optimisation histories, distance matrices
(matplotlib).

Everything here builds a :class:`matplotlib.figure.Figure` directly, never through pyplot,
so it works headless, needs no display backend and leaves pyplot's global state alone.
:func:`save_figure` writes a PNG atomically.

Surfaces are coloured by their parametrization: each grid cell gets a colour that depends
only on its (phi, theta) position (hue from theta, brightness from phi, and a coarse
checkerboard), the same on every frame, so that the point-to-point correspondence along a
geodesic can be followed by eye, as in the paper's figures.

Example:
    >>> from elastic_jax import plot, shapes, straight_path
    >>> path = straight_path(shapes.sample(shapes.sphere, 13, 25),
    ...                      shapes.sample(shapes.bumpy, 13, 25), 5)
    >>> fig = plot.plot_path(path, frames=3)
    >>> [ax.get_title() for ax in fig.axes]
    ['t = 0/4', 't = 2/4', 't = 4/4']
"""

from __future__ import annotations

import operator
import os
import pathlib
from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib import colors as mcolors
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator
from mpl_toolkits.mplot3d import Axes3D  # noqa: F401  (registers the "3d" projection)
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from ._checks import check_int, check_positive
from ._errors import InputError
from ._geometry.metric import SplitMetric
from ._geometry.validation import as_surface
from ._runtime.atomic import atomic_path
from ._statistics.pca import TangentPCA, mode_path

__all__ = [
    "parametrization_colors",
    "plot_path",
    "plot_modes",
    "plot_energy",
    "plot_distance_matrix",
    "save_figure",
]

# Frames drawn when the caller does not say: enough to read a deformation, few enough to fit.
_DEFAULT_FRAMES = 7
# Checkerboard blocks over the whole sphere (in phi, in theta): landmarks that stay put
# whatever the grid resolution, so corresponding regions can be matched across frames.
_CHECKER = (6, 12)
# Shading maps cos(normal, light) in [-1, 1] linearly onto this brightness range, as
# matplotlib's own shading does, so faces turned away from the light keep some colour.
_SHADE_RANGE = (0.3, 1.0)


def parametrization_colors(m: int, n: int) -> np.ndarray:
    """The colour of every grid cell, a fixed function of its position on the parameter sphere.

    Cell (i, j) spans rows i, i+1 and columns j, j+1; its colour is evaluated at the cell's
    centre (phi, theta): the hue goes once round the colour wheel with theta (so it is
    continuous across the seam), the brightness falls from the north pole to the south pole,
    and alternate blocks of a 6 x 12 checkerboard in (phi, theta) are darkened.

    Args:
        m, n: grid size (at least 2 each).

    Returns:
        ``(m - 1, n - 1, 4)`` RGBA values in [0, 1], opaque.
    """
    if m < 2 or n < 2:
        raise InputError(f"the grid needs at least 2 rows and 2 columns; got m={m}, n={n}")
    u = (np.arange(m - 1) + 0.5) / (m - 1)  # phi / pi at the cell centres
    v = (np.arange(n - 1) + 0.5) / (n - 1)  # theta / (2 pi) at the cell centres
    u, v = np.meshgrid(u, v, indexing="ij")
    checker = (np.floor(_CHECKER[0] * u) + np.floor(_CHECKER[1] * v)) % 2
    value = (0.95 - 0.45 * u) * np.where(checker == 1, 0.78, 1.0)
    hsv = np.stack([v, np.full_like(u, 0.7), value], axis=-1)
    rgb = mcolors.hsv_to_rgb(hsv)
    return np.concatenate([rgb, np.ones_like(u)[..., None]], axis=-1)


def _cell_colors(colors, m: int, n: int) -> np.ndarray:
    if isinstance(colors, str) and colors == "parametrization":
        return parametrization_colors(m, n)
    if isinstance(colors, np.ndarray | Sequence) and not isinstance(colors, str):
        arr = np.asarray(colors, dtype=float)
        if arr.ndim == 3:
            if arr.shape[:2] != (m - 1, n - 1) or arr.shape[2] not in (3, 4):
                raise InputError(
                    f"colors as an array must have shape ({m - 1}, {n - 1}, 3 or 4), one "
                    f"RGB(A) colour per grid cell; got {arr.shape}"
                )
            if not np.all(np.isfinite(arr)) or arr.min() < 0 or arr.max() > 1:
                raise InputError("colors must hold finite RGB(A) values in [0, 1]")
            return mcolors.to_rgba_array(arr.reshape(-1, arr.shape[2])).reshape(m - 1, n - 1, 4)
    try:
        rgba = mcolors.to_rgba(colors)
    except (ValueError, TypeError):
        raise InputError(
            "colors must be 'parametrization', a matplotlib colour, or an array "
            f"({m - 1}, {n - 1}, 3 or 4) of per-cell colours; got {colors!r}"
        ) from None
    return np.broadcast_to(np.asarray(rgba), (m - 1, n - 1, 4)).copy()


def _choose_frames(frames, count: int) -> list[int]:
    if frames is None:
        frames = count if count <= _DEFAULT_FRAMES else _DEFAULT_FRAMES
    if isinstance(frames, int | np.integer) and not isinstance(frames, bool):
        if not 1 <= frames <= count:
            raise InputError(f"frames={frames} must be between 1 and the path's {count} frames")
        # Spacing (count - 1) / (frames - 1) >= 1, so rounding never repeats an index.
        return [int(k) for k in np.rint(np.linspace(0, count - 1, frames))]
    if isinstance(frames, str | bytes):
        raise InputError(
            f"frames must be None, an int or a sequence of frame indices; got {frames!r}"
        )
    try:
        chosen = [int(k) for k in frames]
    except (TypeError, ValueError):
        raise InputError(
            f"frames must be None, an int or a sequence of frame indices; got {frames!r}"
        ) from None
    if not chosen:
        raise InputError("frames is an empty sequence; give at least one frame index")
    if any(isinstance(k, float) and not float(k).is_integer() for k in frames):
        raise InputError(f"frame indices must be integers; got {list(frames)!r}")
    bad = [k for k in chosen if not 0 <= k < count]
    if bad:
        raise InputError(f"frame indices {bad} are out of range for a path of {count} frames")
    return chosen


def _cells(surface: np.ndarray) -> np.ndarray:
    """Quadrilateral of every grid cell, ``(3, m, n)`` -> ``((m-1)(n-1), 4, 3)``, row-major."""
    p = np.moveaxis(surface, 0, -1)
    # Corners in the order (i, j), (i+1, j), (i+1, j+1), (i, j+1): increasing phi then theta,
    # which makes the cross product below point outward for a positively oriented surface.
    quads = np.stack([p[:-1, :-1], p[1:, :-1], p[1:, 1:], p[:-1, 1:]], axis=2)
    return quads.reshape(-1, 4, 3)


def _shading(quads: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Brightness factor per cell from the angle between its outward normal and the light."""
    # The cross product of the diagonals stays nonzero on the pole cells, which are
    # triangles (two corners coincide), where edge-based normals would vanish.
    normals = np.cross(quads[:, 2] - quads[:, 0], quads[:, 3] - quads[:, 1])
    # Twice the signed volume (divergence theorem): negative for an inward-facing
    # parametrization, whose normals must be flipped for the light to fall outside.
    if np.sum(quads.mean(axis=1) * normals) < 0:
        normals = -normals
    length = np.linalg.norm(normals, axis=1)
    cos = np.divide(normals @ light, length, out=np.zeros(len(quads)), where=length > 0)
    lo, hi = _SHADE_RANGE
    return lo + (hi - lo) * 0.5 * (1.0 + cos)


def _as_path(path) -> np.ndarray:
    ndim = np.ndim(path)
    if ndim not in (3, 4):
        raise InputError(
            f"path must be a surface (3, m, n) or a path (N, 3, m, n); got shape {np.shape(path)}"
        )
    # Drawing does not need an immersion: a geodesic may pass through a pinched surface.
    x = np.asarray(as_surface(path, "path", check_immersion=False), dtype=float)
    return x[None] if ndim == 3 else x


def _data_box(surfaces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners ``(3,)`` of the box holding every surface ``(K, 3, m, n)``."""
    lo = surfaces.min(axis=(0, 2, 3))
    hi = surfaces.max(axis=(0, 2, 3))
    span = hi - lo
    # A flat frame set (zero extent along one axis) would give a degenerate box.
    floor = 1e-3 * span.max()
    pad = np.maximum(floor - span, 0.0) / 2
    return lo - pad, hi + pad


def _light(elev: float, azim: float) -> np.ndarray:
    """Unit vector towards the light: 45 degrees round from the camera (clockwise seen from
    above; matplotlib's view azimuth is counterclockwise, LightSource's clockwise) and 30
    degrees above it, so that the visible side is lit obliquely."""
    return mcolors.LightSource(azdeg=90 - (azim - 45), altdeg=min(elev + 30, 90)).direction


def _draw_surface(ax, surface, base, light, lo, hi, *, elev, azim, shade) -> None:
    """Draw one surface ``(3, m, n)`` on a 3D axes as its grid cells, in the box [lo, hi]."""
    quads = _cells(surface)
    face = base.copy()
    if shade:
        face[:, :3] *= _shading(quads, light)[:, None]
    # Thin edges in the face colour cover the antialiasing seams between cells.
    ax.add_collection3d(Poly3DCollection(quads, facecolors=face, edgecolors=face, linewidths=0.25))
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(hi - lo))
    ax.view_init(elev=elev, azim=azim)
    ax.set_axis_off()


def plot_path(
    path,
    *,
    frames: int | Sequence[int] | None = None,
    colors="parametrization",
    elev: float = 20,
    azim: float = -60,
    figsize: tuple[float, float] | None = None,
    shade: bool = True,
) -> Figure:
    """Draw frames of a path of surfaces side by side, coloured by the parametrization.

    One 3D axes per chosen frame, titled ``"t = k/(N-1)"`` with k the frame's index
    (``"t = 0"`` for a single surface). Every frame is a mesh of the grid cells, lit by a
    light placed relative to the view, in colours that depend on the grid cell only
    (:func:`parametrization_colors`), so a colour marks the same point of the parameter
    sphere on every frame and the correspondence along the path is visible. All axes share
    the same limits, the data range of the drawn frames, and a box aspect equal to that
    range, so sizes compare across frames and nothing is stretched.

    Args:
        path: ``(N, 3, m, n)`` surfaces at times k/(N-1), or one surface ``(3, m, n)``.
        frames: how many frames to draw, chosen evenly with the first and last included,
            or a sequence of frame indices; default all when N <= 7, else 7.
        colors: ``"parametrization"``; or one matplotlib colour for the whole surface; or an
            array ``(m-1, n-1, 3 or 4)`` with one RGB(A) colour per grid cell.
        elev, azim: the camera's elevation and azimuth in degrees (matplotlib's).
        figsize: ``(width, height)`` in inches; default 2.5 inches wide per frame.
        shade: darken each cell by the angle between its normal and the light. The
            unshaded colours are multiplied by a factor in [0.3, 1] per cell; hue is kept.

    Returns:
        The figure; ``fig.axes`` are the frames' axes in order.

    Raises:
        ValueError: for a malformed path (shape, NaN/inf, poles, seam), bad ``frames`` or
            bad ``colors``.
    """
    x = _as_path(path)
    count, _, m, n = x.shape
    chosen = _choose_frames(frames, count)
    base = _cell_colors(colors, m, n).reshape(-1, 4)
    lo, hi = _data_box(x[chosen])
    light = _light(elev, azim)

    if figsize is None:
        figsize = (2.5 * len(chosen), 2.8)
    fig = Figure(figsize=figsize)
    for slot, k in enumerate(chosen):
        ax = fig.add_subplot(1, len(chosen), slot + 1, projection="3d")
        _draw_surface(ax, x[k], base, light, lo, hi, elev=elev, azim=azim, shade=shade)
        ax.set_title(f"t = {k}/{count - 1}" if count > 1 else "t = 0")
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.92, wspace=0.0)
    return fig


def _solved_frames(paths: np.ndarray) -> np.ndarray:
    """Mode paths ``(R, P, 3, m, n)`` checked frame by frame: a frame is a surface or all
    NaN (a node after a failed shooting step, which :func:`~elastic_jax.shoot` leaves NaN:
    drawn empty); a frame with some non-finite values is an error, as are paths with no
    finite frame."""
    finite = np.isfinite(paths).all(axis=(-3, -2, -1))
    nan = np.isnan(paths).all(axis=(-3, -2, -1))
    broken = ~(finite | nan)
    if broken.any():
        r, k = np.argwhere(broken)[0]
        raise InputError(
            f"mode paths: frame {k} of path {r} is partly non-finite (a shooting failure "
            "leaves whole frames NaN)"
        )
    if not finite.any():
        raise InputError("mode paths: no frame is finite (every shooting step failed)")
    as_surface(paths[finite], "mode paths", check_immersion=False)
    return paths


def _mode_rows(pca_or_paths, metric, modes, sigmas, explained, shooting):
    """The paths to draw ``(R, P, 3, m, n)``, their mode numbers and explained fractions."""
    if isinstance(pca_or_paths, TangentPCA):
        if metric is None:
            raise InputError("metric is needed to shoot the modes of a TangentPCA")
        if explained is not None:
            raise InputError(
                "explained is read from the TangentPCA; give it only with precomputed paths"
            )
        pca = pca_or_paths
        chosen = _choose_modes(modes, pca.modes.shape[0], "the PCA")
        options = {k: v for k, v in shooting.items() if v is not None}
        paths = [mode_path(pca, k, metric, sigmas=sigmas, **options) for k in chosen]
        paths = _solved_frames(np.stack([np.asarray(p, dtype=float) for p in paths]))
        fractions = np.asarray(pca.explained, dtype=float)[chosen]
        return paths, chosen, fractions

    if metric is not None:
        raise InputError("metric is only used with a TangentPCA; precomputed paths need none")
    unused = [k for k, v in shooting.items() if v is not None]
    if unused:
        raise InputError(f"{', '.join(unused)} only apply to a TangentPCA, not to given paths")
    is_array = hasattr(pca_or_paths, "__array__") and np.ndim(pca_or_paths) > 0
    is_sequence = isinstance(pca_or_paths, Sequence) and not isinstance(pca_or_paths, str)
    if not (is_array or is_sequence):
        raise InputError(
            "pca_or_paths must be a TangentPCA or a sequence of mode paths (2N-1, 3, m, n); "
            f"got {type(pca_or_paths).__name__}"
        )
    found = [np.shape(p) for p in pca_or_paths]
    if any(len(shape) != 4 for shape in found) or len(set(found)) != 1:
        raise InputError(
            "mode paths must all have one shape (2N-1, 3, m, n), as mode_path returns; got "
            f"shapes {found}"
        )
    count = found[0][0]
    if count < 3 or count % 2 == 0:
        raise InputError(
            f"a mode path needs an odd number of frames 2N-1 >= 3, the mean in the middle; "
            f"got {count}"
        )
    paths = _solved_frames(np.stack([np.asarray(p, dtype=float) for p in pca_or_paths]))
    chosen = _choose_modes(modes, len(paths), "the given paths")
    fractions = None
    if explained is not None:
        fractions = np.asarray(explained, dtype=float)
        if fractions.shape != (len(paths),):
            raise InputError(
                f"explained must hold one fraction per path, shape ({len(paths)},); got "
                f"{fractions.shape}"
            )
        if not (np.all(np.isfinite(fractions)) and fractions.min() >= 0 and fractions.max() <= 1):
            raise InputError(f"explained must hold fractions in [0, 1]; got {fractions.tolist()}")
        fractions = fractions[chosen]
    return paths[chosen], chosen, fractions


def _choose_modes(modes, available: int, source: str) -> list[int]:
    if isinstance(modes, int | np.integer) and not isinstance(modes, bool):
        if not 1 <= modes <= available:
            raise InputError(
                f"modes={modes} must be between 1 and the {available} modes of {source}"
            )
        return list(range(int(modes)))
    try:
        chosen = [operator.index(k) for k in modes]
    except TypeError:
        raise InputError(
            f"modes must be a number of leading modes or a sequence of mode indices; got {modes!r}"
        ) from None
    if not chosen:
        raise InputError("modes is an empty sequence; give at least one mode index")
    bad = [k for k in chosen if not 0 <= k < available]
    if bad:
        raise InputError(
            f"mode indices {bad} are out of range: {source} has {available} modes (0 to "
            f"{available - 1})"
        )
    return chosen


def _sigma_label(sigma: float) -> str:
    return "mean" if sigma == 0 else f"{sigma:+.3g}\N{GREEK SMALL LETTER SIGMA}"


def plot_modes(
    pca_or_paths,
    metric: SplitMetric | None = None,
    *,
    modes: int | Sequence[int] = 2,
    columns: int = 5,
    sigmas: float = 2.0,
    explained: Sequence[float] | None = None,
    n_times: int | None = None,
    degree: int | None = None,
    scheme: str | None = None,
    colors="parametrization",
    elev: float = 20,
    azim: float = -60,
    figsize: tuple[float, float] | None = None,
    shade: bool = True,
) -> Figure:
    """Draw principal modes of a tangent PCA: one row per mode, from -sigmas to +sigmas.

    Row r shows the geodesic through the mean mu along the mode e_k,
    exp_mu(s sqrt(lambda_k) e_k) for s from -sigmas to +sigmas (:func:`~elastic_jax.mode_path`),
    at ``columns`` evenly chosen frames: the ends and the mean in the middle column. Each
    axes is titled ``"mode k+1 (x%)"`` (the mode's explained-variance fraction in percent,
    3 significant digits; left out when unknown) over the column's s in standard
    deviations (``"-2σ"``, ``"mean"``, ``"+2σ"``). Colours, shading and the shared box
    are those of :func:`plot_path`, the box now holding every drawn frame of every row.

    Args:
        pca_or_paths: a :class:`~elastic_jax.TangentPCA` (its modes are shot with
            ``metric``), or a sequence of R mode paths, each ``(2N-1, 3, m, n)`` as
            :func:`~elastic_jax.mode_path` returns, spanning -sigmas .. +sigmas. Frames
            that are all NaN (nodes after a failed shooting step) are drawn as empty
            axes titled as usual and marked "not reached".
        metric: the split metric of the PCA; required with a TangentPCA, refused with paths.
        modes: how many leading modes to draw, or a sequence of mode indices (0 is the
            first mode; with paths, indices into the sequence).
        columns: frames per row, odd and at least 3 (at most the 2N-1 frames of a path).
        sigmas: the extent in standard deviations, passed to ``mode_path`` (with a
            TangentPCA) or the one the given paths were made with (for the titles).
        explained: with paths only: R fractions of variance in [0, 1], one per path.
        n_times, degree, scheme: with a TangentPCA only: ``mode_path``'s settings
            (its defaults when None).
        colors, elev, azim, shade: as in :func:`plot_path`.
        figsize: ``(width, height)`` in inches; default 2.2 inches per column and 2.6 per row.

    Returns:
        The figure; ``fig.axes`` row by row, ``len(modes) * columns`` axes.

    Raises:
        ValueError: for a mode index out of range, an even ``columns`` or one below 3 or
            above the paths' frames, paths of different or wrong shapes, a metric missing
            (TangentPCA) or given (paths), or shooting options with paths.

    Example:
        >>> import numpy as np
        >>> from elastic_jax import plot, shapes
        >>> f = np.asarray(shapes.sample(shapes.ellipsoid, 9, 17))
        >>> path = np.stack([(1 + 0.1 * s) * f for s in range(-2, 3)])  # (5, 3, 9, 17)
        >>> fig = plot.plot_modes([path], modes=1, columns=3, explained=[0.8])
        >>> [ax.get_title() for ax in fig.axes]
        ['mode 1 (80%)\\n-2σ', 'mode 1 (80%)\\nmean', 'mode 1 (80%)\\n+2σ']
    """
    columns = check_int("columns", columns, 3)
    if columns % 2 == 0:
        raise InputError(f"columns={columns} must be odd, so that the mean is the middle column")
    sigmas = check_positive("sigmas", sigmas)
    shooting = {"n_times": n_times, "degree": degree, "scheme": scheme}
    paths, chosen, fractions = _mode_rows(pca_or_paths, metric, modes, sigmas, explained, shooting)
    rows, count, _, m, n = paths.shape
    if columns > count:
        raise InputError(f"columns={columns} is more than the mode paths' {count} frames")
    # An odd count of evenly spread frames over 2c + 1 frames puts frame c in the middle,
    # and rounding is symmetric about it, so the columns' sigmas are symmetric too.
    frames = _choose_frames(columns, count)
    centre = (count - 1) // 2
    base = _cell_colors(colors, m, n).reshape(-1, 4)
    drawn = paths[:, frames].reshape(-1, 3, m, n)
    drawn = drawn[np.isfinite(drawn).all(axis=(1, 2, 3))]
    lo, hi = _data_box(drawn if len(drawn) else paths[np.isfinite(paths).all(axis=(2, 3, 4))])
    light = _light(elev, azim)

    if figsize is None:
        figsize = (2.2 * columns, 2.6 * rows)
    fig = Figure(figsize=figsize)
    for r, k in enumerate(chosen):
        head = f"mode {k + 1}"
        if fractions is not None:
            head += f" ({100 * fractions[r]:.3g}%)"
        for c, frame in enumerate(frames):
            ax = fig.add_subplot(rows, columns, r * columns + c + 1, projection="3d")
            sigma = sigmas * (frame - centre) / centre
            ax.set_title(f"{head}\n{_sigma_label(sigma)}", fontsize="medium")
            if not np.isfinite(paths[r, frame]).all():
                # A node the shooting did not reach (its step failed): said, not drawn.
                ax.set_axis_off()
                ax.text2D(
                    0.5,
                    0.5,
                    "not reached\n(shooting failed)",
                    ha="center",
                    va="center",
                    transform=ax.transAxes,
                )
                continue
            _draw_surface(
                ax, paths[r, frame], base, light, lo, hi, elev=elev, azim=azim, shade=shade
            )
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.9, wspace=0.0, hspace=0.15)
    return fig


def _history_columns(history, labels) -> list[tuple[str | None, np.ndarray]]:
    if isinstance(history, Mapping):
        if labels is not None:
            raise InputError("labels cannot be given with a dict history: its keys are the labels")
        if not history:
            raise InputError("history is an empty dict")
        columns = []
        for key, values in history.items():
            arr = np.asarray(values, dtype=float)
            if arr.ndim != 1:
                raise InputError(f"history[{key!r}] must be 1-D; got shape {arr.shape}")
            columns.append((str(key), arr))
        return columns
    arr = np.asarray(history, dtype=float)
    if arr.ndim not in (1, 2):
        raise InputError(f"history must have shape (steps,) or (steps, k); got {arr.shape}")
    arr = arr.reshape(arr.shape[0], -1)
    k = arr.shape[1]
    if labels is None:
        names = [None] if k == 1 else [f"column {j}" for j in range(k)]
    else:
        names = [str(s) for s in labels]
        if len(names) != k:
            raise InputError(f"got {len(names)} labels for {k} history column(s)")
    return [(name, arr[:, j]) for j, name in enumerate(names)]


def plot_energy(history, *, labels: Sequence[str] | None = None, logy: bool = True) -> Figure:
    """Plot optimisation records against the step number, one line per column.

    For instance the history of a :class:`~elastic_jax.KarcherResult`, whose two columns are
    the sum of squared distances to the mean and the norm of the mean velocity.

    Args:
        history: ``(steps,)`` or ``(steps, k)`` values, or a dict name -> ``(steps_i,)``
            (the lines may then have different lengths).
        labels: k names for the columns of an array (legend entries); not with a dict.
        logy: use a logarithmic y axis when every value is positive (a linear axis
            otherwise, whatever this says).

    Returns:
        The figure, with one axes; step numbers 0, 1, ... on the x axis.

    Raises:
        ValueError: for a wrong shape, an empty record, NaN/inf, or a labels mismatch.
    """
    columns = _history_columns(history, labels)
    for name, values in columns:
        which = "history" if name is None else repr(name)
        if values.size == 0:
            raise InputError(f"{which} has no steps")
        bad = ~np.isfinite(values)
        if bad.any():
            raise InputError(
                f"{which} has {int(bad.sum())} non-finite value(s), the first at step "
                f"{int(np.argmax(bad))}"
            )

    fig = Figure(figsize=(5.0, 3.5), layout="constrained")
    ax = fig.add_subplot()
    for name, values in columns:
        ax.plot(
            np.arange(values.size), values, marker="." if values.size < 50 else None, label=name
        )
    if logy and all(np.all(values > 0) for _, values in columns):
        ax.set_yscale("log")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("step")
    ax.set_ylabel("value")
    if any(name is not None for name, _ in columns):
        ax.legend()
    ax.grid(True, which="major", alpha=0.3)
    return fig


def plot_distance_matrix(
    D, *, labels: Sequence[str] | None = None, cmap: str = "viridis"
) -> Figure:
    """Show a matrix of pairwise distances as an image with a colourbar.

    Entry (i, j) is drawn at row i, column j (row 0 at the top), unchanged: the image's
    data is ``D`` itself.

    Args:
        D: ``(K, K)`` symmetric (to 1e-8 relative to its largest entry), finite.
        labels: K names for the rows and columns (tick labels); default indices.
        cmap: a matplotlib colormap name.

    Returns:
        The figure: the matrix axes, then the colourbar's.

    Raises:
        ValueError: if ``D`` is not square, has NaN/inf, is not symmetric, or the number of
            labels is not K.
    """
    D = np.asarray(D, dtype=float)
    if D.ndim != 2 or D.shape[0] != D.shape[1]:
        raise InputError(f"D must be a square matrix (K, K); got shape {D.shape}")
    bad = ~np.isfinite(D)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise InputError(
            f"D has {int(bad.sum())} non-finite value(s) (NaN or inf), the first at ({i}, {j})"
        )
    asym = np.abs(D - D.T)
    scale = np.max(np.abs(D)) if D.size else 0.0
    if asym.size and asym.max() > 1e-8 * scale:
        i, j = np.unravel_index(np.argmax(asym), asym.shape)
        raise InputError(
            f"D is not symmetric: D[{i}, {j}] = {D[i, j]:.6g} but D[{j}, {i}] = {D[j, i]:.6g} "
            f"(difference {asym[i, j]:.3g}, more than 1e-8 times max |D| = {scale:.3g})"
        )
    k = D.shape[0]
    if labels is not None:
        labels = [str(s) for s in labels]
        if len(labels) != k:
            raise InputError(f"got {len(labels)} labels for a {k} x {k} matrix")

    side = min(3.0 + 0.3 * k, 12.0)
    fig = Figure(figsize=(side + 1.0, side), layout="constrained")
    ax = fig.add_subplot()
    image = ax.imshow(D, cmap=cmap, interpolation="nearest")
    fig.colorbar(image, ax=ax, label="distance")
    if labels is not None:
        ax.set_xticks(np.arange(k), labels, rotation=90)
        ax.set_yticks(np.arange(k), labels)
    return fig


def save_figure(fig: Figure, path: str | os.PathLike, dpi: float = 120) -> pathlib.Path:
    """Write ``fig`` as a PNG of ``figsize * dpi`` pixels, atomically.

    The image goes to a temporary file beside ``path`` that is renamed onto it once
    complete: an error or Ctrl-C while saving leaves the old file (or none), never a
    truncated PNG and no temporary. Missing parent directories are created.

    Args:
        fig: the figure.
        path: destination; PNG whatever its suffix.
        dpi: pixels per inch.

    Returns:
        ``path`` as a :class:`pathlib.Path`.
    """
    if not dpi > 0:
        raise InputError(f"dpi must be positive; got {dpi}")
    path = pathlib.Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return path
