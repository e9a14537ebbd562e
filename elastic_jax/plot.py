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
from mpl_toolkits.mplot3d import Axes3D
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from ._checks import check_bool, check_choice, check_int, check_positive
from ._errors import InputError
from ._geometry.grid import per_unit_area_np
from ._geometry.metric import SplitMetric
from ._geometry.validation import as_surface
from ._runtime.atomic import atomic_path
from ._statistics.pca import TangentPCA, mode_path

__all__ = [
    "parametrization_colors",
    "plot_path",
    "plot_field",
    "plot_modes",
    "plot_energy",
    "plot_distance_matrix",
    "save_figure",
]

# Frames drawn when the caller does not say: enough to read a deformation, few enough to fit.
_DEFAULT_FRAMES = 7
# Fewest frames the default takes at exactly equal steps (a 10-frame path: 0, 3, 6, 9) before
# it falls back to 7 frames at rounded steps (an 8-frame path: 0, 1, 2, 4, 5, 6, 7).
_MIN_EVEN_FRAMES = 4
# Checkerboard blocks over the whole sphere (in phi, in theta): landmarks that stay put
# whatever the grid resolution, so corresponding regions can be matched across frames.
_CHECKER = (6, 12)
# Shading maps cos(normal, light) in [-1, 1] linearly onto this brightness range, as
# matplotlib's own shading does, so faces turned away from the light keep some colour.
_SHADE_RANGE = (0.3, 1.0)
# The cameras: matplotlib's default (elevation, azimuth) in degrees, and the "fit" view, which
# looks at the principal frame of the drawn shapes (longest axis across the image, second
# axis up, thinnest axis in depth) nearly from the side and a little from above.
_VIEWS = {"default": (20.0, -60.0), "fit": (12.0, -75.0)}
# The fit view's margin round the drawn shapes, a fraction of the panel on each side, and
# the flattest panel it makes (height / width) however long the shapes are.
_FIT_MARGIN = 0.02
_FIT_MIN_ASPECT = 0.3
# Bands (inches) above the panels for one line of axes titles and for the figure title,
# and to the left of the rows of plot_modes for the mode names.
_TITLE_BAND = 0.25
_SUPTITLE_BAND = 0.4
_ROW_LABEL_BAND = 0.35


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


def _default_frames(count: int) -> list[int]:
    """Every frame of a short path; else frames at exactly equal steps when some count
    between _MIN_EVEN_FRAMES and _DEFAULT_FRAMES allows it (the most such), else
    _DEFAULT_FRAMES rounded from equal steps."""
    if count <= _DEFAULT_FRAMES:
        return list(range(count))
    for k in range(_DEFAULT_FRAMES, _MIN_EVEN_FRAMES - 1, -1):
        if (count - 1) % (k - 1) == 0:
            step = (count - 1) // (k - 1)
            return list(range(0, count, step))
    return [int(k) for k in np.rint(np.linspace(0, count - 1, _DEFAULT_FRAMES))]


def _choose_frames(frames, count: int) -> list[int]:
    if frames is None:
        return _default_frames(count)
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


def _draw_surface(ax, surface, base, light, lo, hi, *, elev, azim, shade, fit=False) -> None:
    """Draw one surface ``(3, m, n)`` on a 3D axes as its grid cells, in the box [lo, hi]."""
    quads = _cells(surface)
    face = base.copy()
    if shade:
        face[:, :3] *= _shading(quads, light)[:, None]
    # Thin edges in the face colour cover the antialiasing seams between cells.
    cells = Poly3DCollection(quads, facecolors=face, edgecolors=face, linewidths=0.25)
    if fit:
        ax.set_proj_type("ortho")
    ax.add_collection3d(cells)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(hi - lo))
    ax.view_init(elev=elev, azim=azim)
    ax.set_axis_off()


class _PanelAxes3D(Axes3D):
    """A 3D axes that fills its whole panel: matplotlib's shrinks itself to the largest
    centred square, which leaves a wide panel's sides empty. The image stays undistorted
    because :func:`_fit_windows` gives the image-plane window the panel's aspect."""

    def apply_aspect(self, position=None):
        if position is None:
            position = self.get_position(original=True)
        self._set_position(position, "active")


def _add_panel(fig: Figure, rows: int, columns: int, index: int, fit: bool):
    """Subplot ``index`` (from 1) of a rows x columns grid: a 3D axes, filling its panel
    in the fit view."""
    if fit:
        return fig.add_subplot(rows, columns, index, axes_class=_PanelAxes3D)
    return fig.add_subplot(rows, columns, index, projection="3d")


def _camera(view, elev, azim) -> tuple[float, float]:
    """The camera's (elevation, azimuth): the view's unless given."""
    check_choice("view", view, tuple(_VIEWS))
    default_elev, default_azim = _VIEWS[view]
    return (
        default_elev if elev is None else float(elev),
        default_azim if azim is None else float(azim),
    )


def _principal_frame(surfaces: np.ndarray) -> np.ndarray:
    """Surfaces ``(K, 3, m, n)`` moved rigidly (one rotation about their common centroid, the
    same for all) into their principal frame: the longest principal axis of their points
    along x, the second along z (up), the thinnest along y (depth). Each axis keeps the sign
    of its largest component, so a shape that already lies along the coordinate axes keeps
    its sides (up stays up); y completes a right-handed frame."""
    points = np.moveaxis(surfaces, 1, -1).reshape(-1, 3)
    centre = points.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov(points - centre, rowvar=False))
    longest, second = vectors[:, 2], vectors[:, 1]
    longest = longest * np.sign(longest[np.argmax(np.abs(longest))])
    second = second * np.sign(second[np.argmax(np.abs(second))])
    # Rows x, y, z of the new frame; det = longest . ((second x longest) x second) = 1.
    rotation = np.stack([longest, np.cross(second, longest), second])
    moved = np.einsum("ij,kjmn->kimn", rotation, surfaces - centre[None, :, None, None])
    return moved + centre[None, :, None, None]


def _projected(ax, surfaces: np.ndarray) -> np.ndarray:
    """Image-plane coordinates ``(2, P)`` of every point of ``surfaces`` ``(K, 3, m, n)`` in
    ``ax``'s projection (the 2D data coordinates of a 3D axes)."""
    points = np.moveaxis(surfaces, 1, -1).reshape(-1, 3)
    homogeneous = np.concatenate([points, np.ones((len(points), 1))], axis=1)
    image = ax.get_proj() @ homogeneous.T
    return image[:2] / image[3]


def _fit_aspect(ax, surfaces: np.ndarray) -> float:
    """Height over width of the drawn shapes' image, bounded below by _FIT_MIN_ASPECT and
    above by 1 (the longest axis lies across)."""
    image = _projected(ax, surfaces)
    width, height = np.ptp(image, axis=1)
    return float(np.clip(height / max(width, np.finfo(float).tiny), _FIT_MIN_ASPECT, 1.0))


def _fit_windows(fig: Figure, axes, surfaces: np.ndarray) -> None:
    """Zoom every fitted axes (a :class:`_PanelAxes3D`, filling its panel) onto the drawn
    shapes: one image-plane scale for all (so sizes compare across panels), the window
    centred on the shapes' image, as large as the panel allows with a margin of
    _FIT_MARGIN on each side, and of the panel's aspect (the same scale in x and y)."""
    image = _projected(axes[0], surfaces)
    lo, hi = image.min(axis=1), image.max(axis=1)
    centre = (lo + hi) / 2
    span = np.maximum(hi - lo, np.finfo(float).tiny)
    width_in, height_in = fig.get_size_inches()
    for ax in axes:
        box = ax.get_position(original=True)
        panel = np.array([box.width * width_in, box.height * height_in])
        scale = np.min(panel * (1 - 2 * _FIT_MARGIN) / span)  # inches per image unit
        half = panel / scale / 2
        ax.viewLim.intervalx = (centre[0] - half[0], centre[0] + half[0])
        ax.viewLim.intervaly = (centre[1] - half[1], centre[1] + half[1])


def _check_titles(titles, count: int) -> list[str] | None:
    if titles is None:
        return None
    if isinstance(titles, str | bytes) or not isinstance(titles, Sequence | np.ndarray):
        raise InputError(
            f"titles must be a sequence of strings, one per drawn frame; got {titles!r}"
        )
    titles = [str(t) for t in titles]
    if len(titles) != count:
        raise InputError(f"got {len(titles)} titles for {count} drawn frame(s)")
    return titles


def _check_suptitle(suptitle) -> str | None:
    if suptitle is not None and not isinstance(suptitle, str):
        raise InputError(f"suptitle must be a string or None; got {suptitle!r}")
    return suptitle


def plot_path(
    path,
    *,
    frames: int | Sequence[int] | None = None,
    titles: Sequence[str] | None = None,
    suptitle: str | None = None,
    colors="parametrization",
    view: str = "default",
    elev: float | None = None,
    azim: float | None = None,
    figsize: tuple[float, float] | None = None,
    shade: bool = True,
) -> Figure:
    """Draw frames of a path of surfaces side by side, coloured by the parametrization.

    One 3D axes per chosen frame, titled ``"t = k/(N-1)"`` with k the frame's index
    (``"t = 0"`` for a single surface) unless ``titles`` are given. Every frame is a mesh
    of the grid cells, lit by a light placed relative to the view, in colours that depend
    on the grid cell only (:func:`parametrization_colors`), so a colour marks the same
    point of the parameter sphere on every frame and the correspondence along the path is
    visible. All axes share the same limits, the data range of the drawn frames, and a box
    aspect equal to that range, so sizes compare across frames and nothing is stretched.

    Two cameras: ``view="default"`` is matplotlib's (elevation 20, azimuth -60 degrees,
    perspective), the surfaces as given, in panels 2.5 inches wide and 2.55 high, which
    leaves much white round a long shape standing along z. ``view="fit"`` fills the
    panels: the drawn frames are moved, all by one rotation about their common centroid, into their
    principal frame (longest principal axis across the image, second up, thinnest in
    depth; each axis keeps its sign), seen orthographically from elevation 12 and azimuth
    -75 degrees; each panel's height is the image's height over width (between 0.3 and 1)
    times its width, and the axes are zoomed onto the shapes with a 2 % margin. The fit
    is computed for the returned figure's size: save it without resizing.

    Args:
        path: ``(N, 3, m, n)`` surfaces at times k/(N-1), or one surface ``(3, m, n)``; or a
            stack of different shapes (then name them with ``titles``).
        frames: how many frames to draw, chosen evenly with the first and last included
            (rounded to the nearest frames), or a sequence of frame indices. Default: every
            frame when N <= 7; else the most frames k, from 7 down to 4, whose steps are
            exactly equal ((N-1) divisible by k-1: a 10-frame path gives 0, 3, 6, 9 and a
            13-frame path 0, 2, ..., 12); else 7 frames at rounded steps.
        titles: one title per drawn frame (in the order of ``frames``), for instance the
            shapes' names; default ``"t = k/(N-1)"``.
        suptitle: a title over the whole figure.
        colors: ``"parametrization"``; or one matplotlib colour for the whole surface; or an
            array ``(m-1, n-1, 3 or 4)`` with one RGB(A) colour per grid cell.
        view: ``"default"`` or ``"fit"``, the camera (above).
        elev, azim: the camera's elevation and azimuth in degrees (matplotlib's); default
            the view's.
        figsize: ``(width, height)`` in inches; default 2.5 inches wide per frame, and 2.8
            inches high (``view="default"``) or the fitted height plus the title bands.
        shade: darken each cell by the angle between its normal and the light. The
            unshaded colours are multiplied by a factor in [0.3, 1] per cell; hue is kept.

    Returns:
        The figure; ``fig.axes`` are the frames' axes in order.

    Raises:
        ValueError: for a malformed path (shape, NaN/inf, poles, seam), bad ``frames``,
            ``titles`` (not one per drawn frame), ``view`` or ``colors``.
    """
    x = _as_path(path)
    count, _, m, n = x.shape
    chosen = _choose_frames(frames, count)
    titles = _check_titles(titles, len(chosen))
    suptitle = _check_suptitle(suptitle)
    elev, azim = _camera(view, elev, azim)
    fit = view == "fit"
    base = _cell_colors(colors, m, n).reshape(-1, 4)
    drawn = _principal_frame(x[chosen]) if fit else x[chosen]
    lo, hi = _data_box(drawn)
    light = _light(elev, azim)

    fig = Figure(figsize=(2.5 * len(chosen), 2.8) if figsize is None else figsize)
    for slot, k in enumerate(chosen):
        ax = _add_panel(fig, 1, len(chosen), slot + 1, fit)
        _draw_surface(
            ax, drawn[slot], base, light, lo, hi, elev=elev, azim=azim, shade=shade, fit=fit
        )
        if titles is not None:
            ax.set_title(titles[slot])
        else:
            ax.set_title(f"t = {k}/{count - 1}" if count > 1 else "t = 0")
    _arrange(
        fig,
        fig.axes,
        drawn,
        rows=1,
        fit=fit,
        figsize=figsize,
        panel=(2.5, 2.8 - _TITLE_BAND),
        top_band=_TITLE_BAND,
        left_band=0.0,
        suptitle=suptitle,
    )
    return fig


# Inches added to a field's figure for its colour bar, and the bar's width in them.
_COLORBAR_BAND = 0.9
_COLORBAR_WIDTH = 0.15


def _cell_values(field: np.ndarray, per_area: bool) -> np.ndarray:
    """A grid field ``(m, n)`` as one value per grid cell ``(m - 1, n - 1)``: the mean of
    its corners, per unit area of the parameter sphere when ``per_area`` (corners of no
    quadrature weight, the poles, left out)."""
    if per_area:
        field = per_unit_area_np(field)
    corners = np.stack([field[:-1, :-1], field[1:, :-1], field[1:, 1:], field[:-1, 1:]])
    return np.nanmean(corners, axis=0)


def plot_field(
    f,
    field,
    *,
    per_area: bool = True,
    cmap: str = "viridis",
    limits: tuple[float, float] | None = None,
    label: str | None = None,
    title: str | None = None,
    view: str = "fit",
    shade: bool = True,
) -> Figure:
    """Draw a surface coloured by a value on its grid, with a colour bar.

    For instance a term of :func:`~elastic_jax.energy_density` on the geodesic's first
    frame (where the two shapes differ, and how) or any per-point quantity. Each grid cell
    takes the mean of its four corners' values; with ``per_area`` the field is first
    divided by the grid's quadrature weights (:func:`~elastic_jax.quadrature_weights`), so
    that a field of per-point integrals (an energy density's) reads as a density per unit
    area of the parameter sphere, comparable between large and small cells. The camera and
    layout are :func:`plot_path`'s.

    Args:
        f: ``(3, m, n)`` the surface to draw.
        field: ``(m, n)`` finite values on the same grid.
        per_area: divide by the quadrature weights first (the pole rows, of weight zero,
            are then left out of their cells' means).
        cmap: a matplotlib colour map name.
        limits: ``(low, high)`` of the colour scale; default the cells' range.
        label: the colour bar's label.
        title: the axes' title.
        view: ``"fit"`` or ``"default"`` (:func:`plot_path`).
        shade: darken each cell by its angle to the light (:func:`plot_path`).

    Returns:
        The figure: ``fig.axes[0]`` the surface, ``fig.axes[1]`` the colour bar.

    Raises:
        ValueError: a malformed surface, a field of another shape or not finite, or
            ``limits`` that are not increasing.
    """
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable

    x = _as_path(f)
    if x.shape[0] != 1:
        raise InputError(f"f must be one surface (3, m, n); got shape {np.shape(f)}")
    m, n = x.shape[-2:]
    values = np.asarray(field, dtype=float)
    if values.shape != (m, n):
        raise InputError(f"field must have the surface's grid shape {(m, n)}; got {values.shape}")
    if not np.isfinite(values).all():
        raise InputError("field has NaN or infinite values")
    cells = _cell_values(values, check_bool("per_area", per_area))
    low, high = (float(cells.min()), float(cells.max())) if limits is None else limits
    if not (np.isfinite(low) and np.isfinite(high) and low < high):
        if limits is not None:
            raise InputError(f"limits must be finite and increasing; got {limits!r}")
        high = low + max(abs(low), 1.0) * 1e-12  # a constant field: one colour
    if cmap not in colormaps:
        raise InputError(f"cmap {cmap!r} is not a matplotlib colour map (e.g. 'viridis')")
    norm = mcolors.Normalize(low, high, clip=True)
    colors = colormaps[cmap](norm(cells))
    titles = None if title is None else [title]
    fig = plot_path(x[0], titles=titles, colors=colors, view=view, shade=shade)
    width, height = fig.get_size_inches()
    total = width + _COLORBAR_BAND
    # Widen the figure by the bar's band, keeping each panel's size in inches (the fit
    # view's zoom was computed for it).
    for ax in fig.axes:
        box = ax.get_position()
        ax.set_position([box.x0 * width / total, box.y0, box.width * width / total, box.height])
    fig.set_size_inches(total, height)
    bar = fig.add_axes([(width + 0.2) / total, 0.15, _COLORBAR_WIDTH / total, 0.7])
    fig.colorbar(ScalarMappable(norm=norm, cmap=colormaps[cmap]), cax=bar, label=label)
    return fig


def _arrange(fig, axes, drawn, *, rows, fit, figsize, panel, top_band, left_band, suptitle):
    """Lay out a grid of 3D panels, ``rows`` by ``len(axes) // rows``.

    Unless ``figsize`` was given, the figure is sized from the panel ``(width, height)`` in
    inches, whose height in the fit view is the width times the image's aspect
    (:func:`_fit_aspect`), plus the bands: ``top_band`` inches for the titles (and
    _SUPTITLE_BAND more for ``suptitle``) and ``left_band`` for row labels. In the fit
    view every axes is then zoomed onto the drawn shapes (:func:`_fit_windows`)."""
    columns = len(axes) // rows
    if suptitle is not None:
        top_band += _SUPTITLE_BAND
    if figsize is None:
        width, height = panel
        if fit:
            height = width * _fit_aspect(axes[0], drawn)
        fig.set_size_inches(left_band + columns * width, top_band + rows * height)
    width, height = fig.get_size_inches()
    fig.subplots_adjust(
        left=min(left_band / width, 0.5),
        right=1.0,
        bottom=0.0,
        top=max(1.0 - top_band / height, 0.5),
        wspace=0.0,
        hspace=0.0,
    )
    if suptitle is not None:
        fig.suptitle(suptitle, y=1.0 - 0.06 / height, va="top")
    if fit:
        _fit_windows(fig, axes, drawn)


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
    suptitle: str | None = None,
    colors="parametrization",
    view: str = "default",
    elev: float | None = None,
    azim: float | None = None,
    figsize: tuple[float, float] | None = None,
    shade: bool = True,
) -> Figure:
    """Draw principal modes of a tangent PCA: one row per mode, from -sigmas to +sigmas.

    Row r shows the geodesic through the mean mu along the mode e_k,
    exp_mu(s sqrt(lambda_k) e_k) for s from -sigmas to +sigmas (:func:`~elastic_jax.mode_path`),
    at ``columns`` evenly chosen frames: the ends and the mean in the middle column. Each
    row is labelled once, at its left (a figure text, rotated), ``"mode k+1\\n(x%)"`` (the
    mode's explained-variance fraction in percent, 3 significant digits, on a second line;
    left out when unknown); the axes of the first row are titled with their column's s in standard
    deviations (``"-2σ"``, ``"mean"``, ``"+2σ"``), the other rows' axes are untitled.
    Colours, shading, the shared box and the cameras (``view``) are those of
    :func:`plot_path`, the box (and the fit view's rotation) now holding every drawn frame
    of every row.

    Args:
        pca_or_paths: a :class:`~elastic_jax.TangentPCA` (its modes are shot with
            ``metric``), or a sequence of R mode paths, each ``(2N-1, 3, m, n)`` as
            :func:`~elastic_jax.mode_path` returns, spanning -sigmas .. +sigmas. Frames
            that are all NaN (nodes after a failed shooting step) are drawn as empty
            axes marked "not reached".
        metric: the split metric of the PCA; required with a TangentPCA, refused with paths.
        modes: how many leading modes to draw, or a sequence of mode indices (0 is the
            first mode; with paths, indices into the sequence).
        columns: frames per row, odd and at least 3 (at most the 2N-1 frames of a path).
        sigmas: the extent in standard deviations, passed to ``mode_path`` (with a
            TangentPCA) or the one the given paths were made with (for the titles).
        explained: with paths only: R fractions of variance in [0, 1], one per path.
        n_times, degree, scheme: with a TangentPCA only: ``mode_path``'s settings
            (its defaults when None).
        suptitle: a title over the whole figure.
        colors, view, elev, azim, shade: as in :func:`plot_path`.
        figsize: ``(width, height)`` in inches; default 2.2 inches per column and 2.4 per
            row (``view="default"``; in the fit view the fitted height), plus 0.35 inches
            for the row labels and the title bands.

    Returns:
        The figure; ``fig.axes`` row by row, ``len(modes) * columns`` axes; ``fig.texts``
        the suptitle (if any), then the row labels, one per row in order.

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
        ['-2σ', 'mean', '+2σ']
        >>> [text.get_text() for text in fig.texts]
        ['mode 1\\n(80%)']
    """
    columns = check_int("columns", columns, 3)
    suptitle = _check_suptitle(suptitle)
    elev, azim = _camera(view, elev, azim)
    fit = view == "fit"
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
    reached = np.isfinite(paths[:, frames]).all(axis=(2, 3, 4))
    if not reached.any():
        reached = None  # the box from every finite frame of the paths, none being drawn
    if fit:
        # One rotation for every drawn frame (the unreached stay NaN, the rotation of the
        # reached ones from their points only).
        source = paths[:, frames] if reached is not None else paths
        finite = np.isfinite(source).all(axis=(2, 3, 4))
        moved = np.full_like(source, np.nan)
        moved[finite] = _principal_frame(source[finite])
        if reached is not None:
            paths = paths.copy()
            paths[:, frames] = moved
        else:
            paths = moved
    drawn = paths[:, frames][reached] if reached is not None else None
    if drawn is None:
        drawn = paths[np.isfinite(paths).all(axis=(2, 3, 4))]
    lo, hi = _data_box(drawn)
    light = _light(elev, azim)

    fig = Figure(figsize=(1, 1) if figsize is None else figsize)
    for r in range(rows):
        for c, frame in enumerate(frames):
            ax = _add_panel(fig, rows, columns, r * columns + c + 1, fit)
            if r == 0:
                ax.set_title(_sigma_label(sigmas * (frame - centre) / centre), fontsize="medium")
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
                ax,
                paths[r, frame],
                base,
                light,
                lo,
                hi,
                elev=elev,
                azim=azim,
                shade=shade,
                fit=fit,
            )
    _arrange(
        fig,
        fig.axes,
        drawn,
        rows=rows,
        fit=fit,
        figsize=figsize,
        panel=(2.2, 2.4),
        top_band=_TITLE_BAND,
        left_band=_ROW_LABEL_BAND,
        suptitle=suptitle,
    )
    for r, k in enumerate(chosen):
        label = f"mode {k + 1}"
        if fractions is not None:
            # On a second line: a fitted row of long shapes is about an inch high.
            label += f"\n({100 * fractions[r]:.3g}%)"
        box = fig.axes[r * columns].get_position(original=True)
        fig.text(
            0.5 * box.x0,
            0.5 * (box.y0 + box.y1),
            label,
            rotation=90,
            ha="center",
            va="center",
            fontsize="medium",
        )
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


def plot_energy(
    history,
    *,
    labels: Sequence[str] | None = None,
    logy: bool = True,
    title: str | None = None,
) -> Figure:
    """Plot optimisation records against the step number, one line per column.

    For instance the history of a :class:`~elastic_jax.KarcherResult`, whose two columns are
    the sum of squared distances to the mean and the norm of the mean velocity.

    Args:
        history: ``(steps,)`` or ``(steps, k)`` values, or a dict name -> ``(steps_i,)``
            (the lines may then have different lengths).
        labels: k names for the columns of an array (legend entries); not with a dict.
        logy: use a logarithmic y axis when every value is positive (a linear axis
            otherwise, whatever this says).
        title: the axes' title; default none.

    Returns:
        The figure, with one axes; step numbers 0, 1, ... on the x axis.

    Raises:
        ValueError: for a wrong shape, an empty record, NaN/inf, a labels mismatch or a
            title that is not a string.
    """
    if title is not None and not isinstance(title, str):
        raise InputError(f"title must be a string or None; got {title!r}")
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
    if title is not None:
        ax.set_title(title)
    ax.grid(True, which="major", alpha=0.3)
    return fig


def plot_distance_matrix(
    D,
    *,
    labels: Sequence[str] | None = None,
    title: str | None = None,
    label: str = "distance",
    annotate: bool = False,
    cmap: str = "viridis",
) -> Figure:
    """Show a matrix of pairwise distances as an image with a colourbar.

    Entry (i, j) is drawn at row i, column j (row 0 at the top), unchanged: the image's
    data is ``D`` itself.

    Args:
        D: ``(K, K)`` symmetric (to 1e-8 relative to its largest entry), finite.
        labels: K names for the rows and columns (tick labels); default indices.
        title: the matrix axes' title; default none.
        label: the colourbar's label.
        annotate: write every entry in its cell, to 3 significant digits (``f"{d:.3g}"``),
            in black on light cells and white on dark ones; for small K.
        cmap: a matplotlib colormap name.

    Returns:
        The figure: the matrix axes, then the colourbar's. With ``annotate``, the matrix
        axes' ``texts`` are the K * K entries, row by row.

    Raises:
        ValueError: if ``D`` is not square, has NaN/inf, is not symmetric, the number of
            labels is not K, or ``title``, ``label`` or ``annotate`` has the wrong type.

    Example:
        >>> import numpy as np
        >>> from elastic_jax import plot
        >>> D = np.array([[0.0, 0.7346], [0.7346, 0.0]])
        >>> fig = plot.plot_distance_matrix(D, labels=["cat1", "cat2"], annotate=True)
        >>> [text.get_text() for text in fig.axes[0].texts]
        ['0', '0.735', '0.735', '0']
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
    if title is not None and not isinstance(title, str):
        raise InputError(f"title must be a string or None; got {title!r}")
    if not isinstance(label, str):
        raise InputError(f"label must be a string; got {label!r}")
    annotate = check_bool("annotate", annotate)

    side = min(3.0 + 0.3 * k, 12.0)
    fig = Figure(figsize=(side + 1.0, side), layout="constrained")
    ax = fig.add_subplot()
    image = ax.imshow(D, cmap=cmap, interpolation="nearest")
    fig.colorbar(image, ax=ax, label=label)
    if labels is not None:
        ax.set_xticks(np.arange(k), labels, rotation=90)
        ax.set_yticks(np.arange(k), labels)
    if title is not None:
        ax.set_title(title)
    if annotate:
        # Black on light cells, white on dark ones: the cell colour's luminance (Rec. 709).
        rgb = image.to_rgba(D)[..., :3]
        light = rgb @ np.array([0.2126, 0.7152, 0.0722]) > 0.5
        for i in range(k):
            for j in range(k):
                ax.text(
                    j,
                    i,
                    f"{D[i, j]:.3g}",
                    ha="center",
                    va="center",
                    fontsize="small",
                    color="black" if light[i, j] else "white",
                )
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
