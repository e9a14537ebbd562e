"""One validated, hashable record of the options of a solve between shapes.

It imports only the validation layer (``_checks``), so that every module and the command
line can import it. The record is frozen and hashable: it is the static configuration of
the jitted solves, so equal options never recompile.
"""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Mapping
from types import MappingProxyType
from typing import ClassVar

from ._checks import check_bool, check_choice, check_grid_shape, check_int, check_positive
from ._errors import InputError

__all__ = [
    "FROM_OPTIONS",
    "FromOptions",
    "InputError",
    "ShapeOptions",
    "check_choice",
    "check_int",
    "check_positive",
    "options_with",
    "settings_from",
]

SOLVERS = ("bfgs", "lbfgs")
SCHEMES = ("forward", "central", "midpoint")
# Schemes whose energy couples each node to its two neighbours only: they can be shot
# (the central scheme couples five nodes; see _geodesics/shooting.py).
SHOOTING_SCHEMES = ("midpoint", "forward")
METHODS = ("joint", "coordinate")
INITS = ("moebius", "energy", "icosahedral", "none")
INTERPOLATIONS = ("bilinear", "bicubic", "spline")
DIFFERENTIALS = ("chain", "grid")
SMOOTHING_KERNELS = ("sphere", "surface")  # smooth_surface's kernels
# The fraction of the finer nodes' cells, those where gamma stretches most, that a resolved
# distance's levels integrate 4 x 4 finer by default (ShapeOptions.level_stretch).
LEVEL_STRETCH = 0.03


@dataclasses.dataclass(frozen=True)
class ShapeOptions:
    """Options of a geodesic between shapes: its path, its registration, its checks.

    One record travels from :func:`shape_geodesic` to :func:`karcher_mean`,
    :func:`distance_matrix` and the command line; every field is checked when the record
    is made (an InputError, a ValueError, names the field). Grid-dependent limits (a
    degree too high for the grid) are checked when it is used. Change fields with
    ``options.replace(...)``.

    The path fields set the parametrized geodesics (paper Algorithm 1, math §4 and §7),
    the registration fields the search over reparametrizations and rotations (paper
    sections 4.2-4.3), the check fields what is verified at the end.

    Path fields:
        degree: spherical-harmonic degree of the path perturbations.
        n_times: N >= 3 time points, end points included.
        solver: ``"bfgs"`` (optimistix) or ``"lbfgs"`` (jaxopt), for every inner solve.
        max_steps: step limit of each inner solve.
        tol: inner tolerance, for either solver a bound on the 2-norm of the gradient of
            the scaled problem (:func:`geodesic`); None: 1e-6 in float64, 3e-3 in float32.
        scheme: time discretization. ``"midpoint"`` (default): each step's metric is
            taken at the middle of the step, so the energy is the midpoint rule for the
            energy of the piecewise-linear path; second order, symmetric, and it cannot
            be lowered by large steps. ``"forward"`` (the paper's) weighs a step at its
            start and ``"central"`` has an odd-even mode: registration exploits both
            (:doc:`/guides/settings`, "What the distance means").

    Registration fields:
        method: ``"joint"`` (Algorithm 2: path and reparametrization together, default)
            or ``"coordinate"`` (alternate: the reparametrization with the path's
            perturbation held, then the path).
        vf_degree: degree of the vector fields of a Diff step.
        outer_steps: most registration rounds; the loop stops earlier once a round
            changes the energy by at most outer_tol (E + outer_tol E_0), or, for the
            rounds with the whole path, once that round's change and the one before,
            continued as a geometric series, leave at most that much.
        outer_tol: that relative change (E_0: the parametrized energy); also the coarse
            rounds' and the parametrized geodesic's comparisons.
        rounds_tol: the registration rounds' own stop, in place of outer_tol for the
            rounds with the whole path; None (default): outer_tol on one working grid,
            ``max(outer_tol, rtol / 5)`` on a resolved distance's levels
            (``ShapeOptions.level_rounds_tol``).
        init: ``"moebius"`` (default): from each of the 60 icosahedral rotations a short
            search over the Moebius group of S^2 (rotations and conformal boosts) on the
            L2 mismatch int ‖f1 o gamma - R f2‖^2, the 60 ranked by that mismatch, the best
            ``init_candidates`` that lie apart refined to the tolerance: these are the
            starts (:doc:`/guides/registration_notes`); ``"energy"``: the 60 rotations
            refined over rotations and ranked by straight-line energy, the best
            ``init_candidates`` refined over rotations and, as that many more starts, over
            the Moebius group; ``"icosahedral"``: the
            same over rotations only (the paper's Remark 4); ``"none"``: the identity
            alone. Every start then gets registration rounds on the L2 mismatch; the
            candidate whose straight line then has the lowest energy gets rounds on that
            energy and goes on to the rounds with the whole path. The result is never
            above the parametrized geodesic: when the registered one ends above it by
            more than outer_tol, the pair as given (the identity gamma and, modulo
            rigid, also its Procrustes-best rotation) gets rounds of its own (concrete
            inputs), and the lower result is kept; the parametrized geodesic itself,
            with ``RESULTS.not_registered``, when neither registration is lower.
        init_candidates: how many of the ranked searches become starts (with
            "moebius", the best that lie apart: mean distance of their maps above 0.1;
            with "energy", twice as many starts: each refined over rotations and over
            the Moebius group).
        interpolation: how an input is read off its grid (f1 o gamma, an input on
            another grid than the working one) and how gamma is composed:
            ``"spline"`` (default): the interpolating cubic B-spline,
            C^2, fourth order in value and derivative; with the chain rule gamma's
            differential is its spline's derivative too (f o phi_a, abs(a) = 0.5, at
            25 x 49: differential error 0.03 % against 1.2 % for bicubic and central
            differences; the spheres' closed form 0.3 % off at 13 x 25 against 2-4 %).
            ``"bicubic"``: Catmull-Rom, C^1, third order (the earlier
            default). ``"bilinear"``: the paper's.
        differential: how the differential of f1 o gamma is taken
            (:doc:`/guides/registration_notes`).
            ``"chain"`` (default): by the chain rule, (df1 at gamma)
            dgamma, with df1 the exact derivative of f1's interpolant and dgamma the
            derivative of gamma's spline (with ``interpolation="spline"``; otherwise
            central differences of gamma with a rotation's chords made exact); R f2's
            differential the same way at the identity. It converges under refinement
            (fourth order with splines on smooth surfaces), and every input stands for
            its interpolant, whatever its grid. An input that is a surface sampled
            through a large reparametrization on the working grid is a coarser surface
            than the one it was sampled from, and the chain rule sees that (cat1 read
            through a Moebius map with abs(a) = 0.3 at 25 x 49: 40 % of d(cat1, cat2)):
            sample such inputs finer than the map's stretch (math §10). The path's
            frames are then not the grid differences of its surfaces: ``energy`` is not
            ``path_energy(path)``, and :func:`log` returns the frames its solve used
            for :func:`shoot`.
            ``"grid"``: central differences of f1 o gamma on the grid, as of every other
            surface (the earlier default); an input that is f1 sampled through
            some gamma on the working grid is then matched exactly (d(f, R f o phi) at
            most 0.3 % of d(cat1, cat2) at 50 x 99). Where gamma stretches, those
            differences are chords across a stretch of f1, shorter than its tangents,
            and the registration can lower the energy by under-sampling f1: the cats'
            distance rises by 32 % from 25 x 49 to the same surfaces at 49 x 97, and the
            two orders differ by 4-8 %.

        stretch_quadrature: the fraction of the quadrature grid's cells (the working
            grid's, or the grid ``quadrature`` times finer), those where gamma stretches
            most (the largest J at a corner, gamma read at the quadrature's nodes),
            whose part of the path energy is integrated ``stretch_subdivision`` times
            finer in each direction (the midpoint rule on sub-cells, f1 o gamma read
            there through the interpolants). Where gamma spreads a region of f1 over a
            few cells, the nodes do not see f1 between them and a registration that
            minimizes the node rule hides f1 there
            (:doc:`/guides/registration_notes`, "What the levels' changes are made of").
            Used by every energy a registration evaluates and by the reported distance
            (the geodesics' own solves integrate by the nodes). Needs
            ``scheme="midpoint"`` and ``differential="chain"``. None (default): 0.03 on
            the levels of a resolved distance, on top of the finer nodes (the cats'
            25 x 49 level read at the nodes of the grid four times finer: +7.7 % in
            energy, against +22.6 % with the finer nodes alone), and 0 on one working
            grid (``grid=`` or ``rtol=None``: the paper's node rule); 0 on the levels
            too with another scheme or the grid differential.
        stretch_subdivision: that subdivision s >= 2 (s x s sub-cells per cell).
        quadrature: q >= 1: every energy of a registration (its rounds, the
            parametrized and the registered geodesic, the reported distance) is
            integrated at the nodes of the grid q times finer than the working grid,
            (q (m - 1) + 1) x (q (n - 1) + 1), with gamma, the rotation and the path's
            coefficients still those of the working grid: f1 o gamma is read there
            through gamma's and f1's interpolants, the path's harmonics exactly; 1:
            the working grid's own nodes (the paper's rule). Costs about q^2 times the
            points. q > 1 needs ``differential="chain"``; stretched cells
            (``stretch_quadrature``) are then the finer grid's. None (default): 2 on
            the levels of a resolved distance, where the node rule's levels converge at
            first order on real shapes (:doc:`/guides/registration_notes`, "Every
            energy at the nodes of the grid twice finer"), and 1 on one working grid
            (``grid=`` or ``rtol=None``: the paper's protocol); 1 on the levels too
            with the grid differential.

    Grid fields:
        grid: one working grid ``(m, n)`` the path is discretized on (odd n, m, n >= 5),
            whatever grids the inputs come on: each input is read through its
            interpolant (:ref:`math §10 <math-10>`); no levels (``rtol`` is then not
            used): the paper's protocol, benchmarks, and jit or vmap. None (default):
            the levels of ``rtol``, or with ``rtol=None`` the inputs' grid (the finer of
            two, more points, when they differ).
        rtol: a resolved distance (:ref:`math §10 <math-10>`), the default: the path is
            solved on each working grid of ``levels`` in turn, each level continuing the
            one below (its gamma read at this level's points, its rotation and its
            path: the rounds with the whole path resume, without a new start search or
            coarse rounds), until two successive levels' distances agree within rtol
            (relative; default 0.03); the result's ``levels`` records each level's
            distance and time and the estimate, and ``converged`` means the tolerance
            was met at a minimum. Levels compare concrete distances: under jax.jit or
            jax.vmap give ``grid`` (or rtol=None). None: one working grid.
            karcher_mean's first solves, distance_matrix, fit_metric and log (modulo
            "diff" / "rigid") resolve by levels too.
        levels: the working grids for ``rtol``, coarse to fine (default 25 x 49,
            49 x 97, 97 x 193). A 13 x 25 level is cheap but too coarse for the
            authors' shapes (its own registration read twice finer moves it by 13-28 %,
            and the next level searched a start of its own in every pair measured);
            smooth shapes resolve faster with ``levels=((13, 25), (25, 49), ...)``.
        level_vf_degrees: the Diff step's degree on each level of ``levels`` (one
            per level, each at most that grid's :func:`~elastic_jax.max_degree`); None
            (default): ``vf_degree`` on every level, so that every pair is registered in
            one class of maps and the levels resolve the grid at that degree. Richer
            steps can lower a distance: fsaverage5's pial pair by 18 % at
            ``(16, 32)`` with registrations as mild as degree 8's, the authors'
            animals by 2-16 % with registrations that compress regions towards the
            area floor (:doc:`/guides/registration_notes`, "The degrees"). The paper's
            multiresolution ``(8, 11, 14)`` resolved those pairs at 49 x 97.
        level_candidates: how many starts a resolved :func:`shape_geodesic` carries
            through its levels (default 1: the start search's starts compete in the
            coarse rounds and one goes on; one working grid ignores it). With K > 1
            the first level's start search gives up to K of its starts (as many as it
            makes at most: ``init_candidates``, twice that with ``init="energy"``), each
            gets coarse rounds, rounds and levels of its own, and the lowest final
            distance is the result; ``res.levels.candidates`` holds every candidate's,
            ``res.levels.spread`` their range relative to the lowest, and the result is
            converged only when that spread is within rtol too. About K times the
            time. Which local minimum a solve ends in turns on rounding
            (:doc:`/guides/registration_notes`, "Where rounding picks the basin"); the
            spread says how far apart the minima the candidates found are.
            The collections carry them too: each pair of ``distance_matrix`` (its
            ``spread``), each first solve of ``karcher_mean``, each registration of
            ``fit_metric`` and ``log`` is then that pair's resolved shape_geodesic,
            candidates and all, every candidate one more item of the levels' batch.
            K = 0 (only with ``search_smoothing``) carries no candidate of the start
            search, only the graduated ones (and with ``both_orders`` the other
            order's graduated one): with widths ``(1, 0.5, 0.25)`` and
            ``both_orders`` the start search's candidates never won on the shared
            animals (nine runs: they ended 5.7-18.5 % above the lowest), but on a
            surface against its own Moebius read the default's candidate is the
            lower one.
        both_orders: a resolved :func:`shape_geodesic` also searches the starts of the
            other order, f2 to f1, and carries each, inverted (gamma^-1 by Newton's
            method on gamma's interpolant, R^T), through this order's levels as one
            more candidate (default False; one working grid and a given ``start``
            ignore it). The candidates are then this order's
            (``level_candidates`` of them; with one, the default solve itself, whose
            starts compete in the coarse rounds) followed by the other order's
            ``level_candidates`` best-ranked starts, and the lowest final distance is
            the result. The continuum distance is symmetric, and a start search in one
            order misses minima that the other order's finds: on the shared cats the
            other order's start ended lower than the default solve in three of five
            runs, and the answer moved by 0.70 % under 1e-10 perturbations against
            1.5 % (:doc:`/guides/registration_notes`, "Candidates from both orders").
            Twice the candidates: 1.5-4.1 times the time on 2 CPU cores (more where
            the other order's candidate needs a finer level). The collections carry
            them as ``level_candidates`` says.
        search_smoothing: kernel widths, wide to narrow, in a level's latitude
            spacings (pi / (m - 1) on an m x n level); default () (none). A resolved
            :func:`shape_geodesic` without a ``start`` then carries one more
            candidate through the levels beside the default's: each of its levels
            that searches its own start (the first, or one whose carried
            registration folds between its points) solves first on f1 and f2
            low-passed by each width in turn (:func:`smooth_surface`, by
            ``smoothing_kernel``), each solve continuing the one before, and then on
            the data, continuing the narrowest: graduated inputs, as image
            registration's pyramids. Blurred inputs have fewer basins, and the
            data's level continues the minimum followed down from the widest instead
            of whichever one rounding picks. With ``both_orders``, one more
            candidate continues the other order's graduated solve of each such
            level, inverted (gamma^-1, R^T; left out where the inverse folds or
            misses rounding's tolerance). The lowest final distance wins, so the
            answer is never above the default's, and ``spread`` says how far apart
            the two ended. On the shared cats, with ``(1, 0.5, 0.25)`` and the sphere
            kernel, the graduated candidate ended 4-9 % below the default's in all
            five runs (those answers are therefore ``not_resolved``) and moved by
            0.33 % under three 1e-10 perturbations (the default: 1.5 %), the two
            candidates at 1.6 times the default's time (2.9-3.5 times on cat1 ->
            horse0, where a folded level is graduated too); on horse0 against its own
            Moebius read the default's candidate ends lower
            (:doc:`/guides/registration_notes`, "Graduated start searches"). One
            working grid ignores it; the collections carry the graduated candidate
            as ``level_candidates`` says (its low-passed solves one pair at a time).
        smoothing_kernel: ``"sphere"`` (default) or ``"surface"``: the kernel of
            ``search_smoothing`` (:func:`smooth_surface`'s ``kernel``). The sphere
            kernel averages the parametrization, so f and f o phi blur into
            different surfaces; the surface kernel is the surface's own heat flow,
            independent of the parametrization, but on the cats its candidate moved by
            1.6 % under the same perturbations (widths (2, 1, 0.5)).
        alternations: at most this many round trips between the two orders after
            each level's solve of a resolved :func:`shape_geodesic` (default 0:
            none): the level's registration (gamma, R), inverted (gamma^-1, R^T),
            is continued in the order f2 -> f1 from the straight line, that
            registration inverted again is continued in this order, and a round trip
            that ends lower is kept; they stop once one lowers the distance by less
            than the levels' rounds stop (``level_rounds_tol``) or does not lower
            it. A level's rounds compose gamma with steps of the degree-``vf_degree``
            basis on the right (gamma o phi); the other order's rounds move gamma
            on the left (phi o gamma), so a registration where neither order's
            steps lower the energy is a minimum over both families. On cat1 ->
            horse0 at 49 x 97 each order's rounds end where a restart of the same
            order stays (1.8145, 1.8074, 1.8083) while the orders in turn go down
            1.8145, 1.7576, 1.7430, 1.7363, 1.7247, 1.7224
            (:doc:`/guides/registration_notes`, "Both orders in turn"). A
            registration whose inverse folds on the grid is not turned: through the
            levels horse0 -> cat1 went from 1.8096 to 1.7178 while every candidate of
            cat1 -> horse0 kept its end (1.8596), so round trips alone leave the two
            orders further apart; with ``both_orders`` and ``search_smoothing`` as
            well the two orders ended at 1.7204 and 1.7178 (0.15 % apart; 2.4-3.3 %
            without round trips). Two more solves a round trip on every level; the
            collections carry them too.
            The other order's solves and the graduated candidates' low-passed
            solves do not alternate.

    Check fields:
        refinement: re-evaluate the result with every time step halved and on the
            grid twice finer than the one its energy was integrated on
            (:class:`Refinement`).
        saddle_checks: at most this many escapes from saddle points of the final
            geodesic solve (0: none).
    """

    #: The allowed values of each field that names a choice (a read-only mapping; the
    #: command line offers the same).
    CHOICES: ClassVar[Mapping[str, tuple[str, ...]]] = MappingProxyType(
        {
            "solver": SOLVERS,
            "scheme": SCHEMES,
            "method": METHODS,
            "init": INITS,
            "interpolation": INTERPOLATIONS,
            "differential": DIFFERENTIALS,
            "smoothing_kernel": SMOOTHING_KERNELS,
        }
    )

    degree: int = 7
    n_times: int = 13
    solver: str = "bfgs"
    max_steps: int = 500
    tol: float | None = None
    scheme: str = "midpoint"
    method: str = "joint"
    vf_degree: int = 8
    outer_steps: int = 20
    outer_tol: float = 1e-3
    rounds_tol: float | None = None
    init: str = "moebius"
    init_candidates: int = 3
    interpolation: str = "spline"
    differential: str = "chain"
    stretch_quadrature: float | None = None
    stretch_subdivision: int = 4
    quadrature: int | None = None
    refinement: bool = True
    saddle_checks: int = 1
    grid: tuple[int, int] | None = None
    rtol: float | None = 0.03
    levels: tuple[tuple[int, int], ...] = ((25, 49), (49, 97), (97, 193))
    level_vf_degrees: tuple[int, ...] | None = None
    level_candidates: int = 1
    both_orders: bool = False
    search_smoothing: tuple[float, ...] = ()
    smoothing_kernel: str = "sphere"
    alternations: int = 0

    def __post_init__(self):
        ints = {
            "degree": 1,
            "n_times": 3,
            "max_steps": 1,
            "vf_degree": 1,
            "outer_steps": 0,
            "init_candidates": 1,
            "saddle_checks": 0,
            "stretch_subdivision": 2,
            "level_candidates": 0,
            "alternations": 0,
        }
        for name, minimum in ints.items():
            object.__setattr__(self, name, check_int(name, getattr(self, name), minimum))
        if self.quadrature is not None:  # None: chosen per solve (level_quadrature)
            object.__setattr__(self, "quadrature", check_int("quadrature", self.quadrature, 1))
        if self.init_candidates > 60:
            raise InputError(
                f"init_candidates must be at most 60 (the icosahedral rotations); "
                f"got {self.init_candidates}"
            )
        for name, allowed in self.CHOICES.items():
            check_choice(name, getattr(self, name), allowed)
        if self.tol is not None:
            object.__setattr__(self, "tol", check_positive("tol", self.tol))
        object.__setattr__(self, "outer_tol", check_positive("outer_tol", self.outer_tol))
        if self.rounds_tol is not None:
            object.__setattr__(self, "rounds_tol", check_positive("rounds_tol", self.rounds_tol))
        object.__setattr__(self, "refinement", check_bool("refinement", self.refinement))
        object.__setattr__(self, "both_orders", check_bool("both_orders", self.both_orders))
        fraction = self.stretch_quadrature
        if fraction is not None:  # None: chosen per solve (level_stretch)
            if isinstance(fraction, bool) or not isinstance(fraction, numbers.Real):
                raise InputError(
                    f"stretch_quadrature must be None or a number in [0, 1]; got {fraction!r}"
                )
            if not 0.0 <= float(fraction) <= 1.0:
                raise InputError(f"stretch_quadrature must be in [0, 1]; got {fraction!r}")
            object.__setattr__(self, "stretch_quadrature", float(fraction))
        if self.stretch_fraction > 0.0 and (
            self.scheme != "midpoint" or self.differential != "chain"
        ):
            raise InputError(
                "stretch_quadrature integrates the midpoint scheme's energy of the chain "
                f"rule's frames; got scheme={self.scheme!r}, differential={self.differential!r}"
            )
        finer = self.quadrature is not None and self.quadrature > 1
        if finer and self.differential != "chain":
            raise InputError(
                "quadrature > 1 reads f1 o gamma between the nodes by the chain rule; got "
                f"differential={self.differential!r}"
            )
        if self.grid is not None:
            object.__setattr__(self, "grid", _checked_grid("grid", self.grid))
        try:
            levels = tuple(_checked_grid("levels", grid) for grid in self.levels)
        except TypeError:
            raise InputError(
                f"levels must be a sequence of grids (m, n); got {self.levels!r}"
            ) from None
        if not levels or any(
            a[0] * a[1] >= b[0] * b[1] for a, b in zip(levels, levels[1:], strict=False)
        ):
            raise InputError(f"levels must be grids from coarse to fine; got {levels}")
        object.__setattr__(self, "levels", levels)
        if self.level_vf_degrees is not None:
            try:
                degrees = tuple(self.level_vf_degrees)
            except TypeError:
                raise InputError(
                    f"level_vf_degrees must be one degree per level; got {self.level_vf_degrees!r}"
                ) from None
            if len(degrees) != len(levels):
                raise InputError(
                    f"level_vf_degrees must give one degree per level: {len(levels)} levels, "
                    f"got {len(degrees)} degrees ({degrees})"
                )
            degrees = tuple(check_int("level_vf_degrees", d, 1) for d in degrees)
            object.__setattr__(self, "level_vf_degrees", degrees)
        if self.rtol is not None:
            object.__setattr__(self, "rtol", check_positive("rtol", self.rtol))
        try:
            widths = tuple(self.search_smoothing)
        except TypeError:
            raise InputError(
                "search_smoothing must be a sequence of kernel widths; got "
                f"{self.search_smoothing!r}"
            ) from None
        widths = tuple(check_positive("search_smoothing", w) for w in widths)
        if any(a <= b for a, b in zip(widths, widths[1:], strict=False)):
            raise InputError(f"search_smoothing must be widths from wide to narrow; got {widths}")
        object.__setattr__(self, "search_smoothing", widths)
        if self.level_candidates == 0 and not widths:
            raise InputError(
                "level_candidates must be at least 1 without search_smoothing (0 carries "
                "only the graduated candidates); got 0"
            )

    def working_grids(self, input_grid: tuple[int, int]) -> tuple[tuple[int, int], ...]:
        """The working grids ``(m, n)`` a shape solve with these options runs on, coarse to
        fine, for inputs on ``input_grid``: every level of ``levels`` when the solve
        resolves (``rtol`` given, ``grid`` not), else ``grid`` or ``input_grid``.

        Example:
            >>> ShapeOptions().working_grids((50, 99))
            ((25, 49), (49, 97), (97, 193))
            >>> ShapeOptions(rtol=None).working_grids((50, 99))
            ((50, 99),)
        """
        if self.resolves:
            return tuple(tuple(level) for level in self.levels)
        return (tuple(self.grid or input_grid),)

    @property
    def resolves(self) -> bool:
        """Whether a shape solve runs levels of working grids (rtol given, grid not)."""
        return self.rtol is not None and self.grid is None

    @property
    def quadrature_factor(self) -> int:
        """The quadrature factor q a solve on one working grid integrates by
        (``quadrature``, 1 when None)."""
        return 1 if self.quadrature is None else self.quadrature

    @property
    def level_quadrature(self) -> int:
        """The quadrature factor q a resolved distance's levels integrate by
        (``quadrature``; when None, 2 with the chain rule, else 1)."""
        if self.quadrature is not None:
            return self.quadrature
        return 2 if self.differential == "chain" else 1

    @property
    def round_stop(self) -> float:
        """The relative energy change at which a solve on one working grid stops its
        rounds with the whole path (``rounds_tol``, outer_tol when None)."""
        return self.outer_tol if self.rounds_tol is None else self.rounds_tol

    @property
    def level_rounds_tol(self) -> float:
        """The rounds' stop on a resolved distance's levels (``rounds_tol``; when None,
        ``max(outer_tol, rtol / 5)``, or outer_tol without rtol).

        A level's distance is asked to rtol, and a round that changes the energy by less
        than rtol / 5 (a tenth of rtol in the distance) no longer moves it at that
        scale. Measured at 49 x 97 continuing 25 x 49 (2 cores, the defaults before
        this): the rounds changed the energy by 11.6, 2.1, 0.41, 0.15 % on the cats and
        17.5, 4.5, 0.31, 0.12 % on cat1 -> horse0. Stopped after the third, the distance
        is 0.08 % and 0.06 % above the full rounds', for a quarter fewer BFGS steps.
        """
        if self.rounds_tol is not None:
            return self.rounds_tol
        if self.rtol is None:
            return self.outer_tol
        return max(self.outer_tol, self.rtol / 5.0)

    @property
    def stretch_fraction(self) -> float:
        """The fraction of stretched cells a solve on one working grid integrates finer
        (``stretch_quadrature``, 0 when None)."""
        return 0.0 if self.stretch_quadrature is None else self.stretch_quadrature

    @property
    def level_stretch(self) -> float:
        """The fraction of stretched cells a resolved distance's levels integrate finer
        (``stretch_quadrature``; when None, 0.03 with the chain rule and
        the midpoint scheme, else 0)."""
        if self.stretch_quadrature is not None:
            return self.stretch_quadrature
        chain_midpoint = self.differential == "chain" and self.scheme == "midpoint"
        return LEVEL_STRETCH if chain_midpoint else 0.0

    def on_level(self, grid: tuple[int, int]) -> ShapeOptions:
        """The options of a solve on the one working grid ``grid`` (no rtol) that is a
        level of these options' solve: integrated as the levels are
        (:attr:`level_quadrature`, :attr:`level_stretch`) and with their rounds' stop
        (:attr:`level_rounds_tol`) when these resolve, else as they are."""
        if not self.resolves:
            return self.replace(grid=grid, rtol=None)
        return self.replace(
            grid=grid,
            rtol=None,
            vf_degree=self.level_vf_degree(grid),
            quadrature=self.level_quadrature,
            stretch_quadrature=self.level_stretch,
            rounds_tol=self.level_rounds_tol,
        )

    def level_vf_degree(self, grid: tuple[int, int]) -> int:
        """The Diff step's degree on the level ``grid`` of a resolved distance
        (``level_vf_degrees``' entry for that level; ``vf_degree`` when None or when
        ``grid`` is not one of ``levels``)."""
        grid = tuple(int(k) for k in grid)
        if self.level_vf_degrees is None or grid not in self.levels:
            return self.vf_degree
        return self.level_vf_degrees[self.levels.index(grid)]

    def replace(self, **changes) -> ShapeOptions:
        """A copy with some fields changed (validated again)."""
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise TypeError(f"ShapeOptions has no field(s) {unknown}")
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict:
        """The fields as a plain dict (for summaries and checkpoint fingerprints)."""
        return dataclasses.asdict(self)

    def geodesic_kwargs(self) -> dict:
        """The fields :func:`geodesic` takes, as its keywords (modulo="none": no
        registration)."""
        names = ("degree", "n_times", "solver", "max_steps", "tol", "scheme", "saddle_checks")
        return {name: getattr(self, name) for name in names}


def _checked_grid(name: str, grid) -> tuple[int, int]:
    """``grid`` as a pair (m, n) of Python ints that make a valid grid."""
    try:
        m, n = grid
    except (TypeError, ValueError):
        raise InputError(f"{name} must hold grids (m, n); got {grid!r}") from None
    m, n = check_int(f"{name}'s m", m, 5), check_int(f"{name}'s n", n, 5)
    return check_grid_shape((3, m, n), name)


class FromOptions:
    """The default of a keyword that an options record also holds: take the record's."""

    def __repr__(self) -> str:
        return "<from options>"


# One object: ``value is FROM_OPTIONS`` tells a keyword left out from one given (None is
# a value of its own for some of them: tol=None is the precision's default tolerance).
FROM_OPTIONS = FromOptions()


def settings_from(function: str, options: ShapeOptions | None, **keywords) -> dict:
    """The settings of one call: each keyword given, else the field of ``options`` (a
    :class:`ShapeOptions`; its defaults when None).

    One record holds every path and solver setting, so that a limit has one name and one
    default wherever it is used (``geodesic``, ``shoot``, ``parallel_transport`` and the
    solves between shapes). The one rule for a keyword that names a field of the record,
    here and in :func:`options_with`: left out (``FROM_OPTIONS``), it is the
    record's; given while ``options`` is None, it sets that field of the default record;
    given beside a record, it must equal the record's field (an equal value is accepted),
    and one that says otherwise is refused: which of the two was meant cannot be known.
    """
    if options is None:
        record = ShapeOptions()
    elif isinstance(options, ShapeOptions):
        record = options
    else:
        raise InputError(
            f"{function}: options must be an elastic_jax.ShapeOptions or None; "
            f"got {type(options).__name__}"
        )
    settings = {}
    for name, value in keywords.items():
        held = getattr(record, name)
        if value is FROM_OPTIONS:
            settings[name] = held
            continue
        if options is not None and value != held:
            raise InputError(
                f"{function}: {name}={value!r} given as a keyword, and options has "
                f"{name}={held!r}; give it once (options.replace({name}=...) changes it)"
            )
        settings[name] = value
    return settings


def options_with(function: str, options: ShapeOptions | None, changes: dict) -> ShapeOptions:
    """The record of a call that takes ``options`` and keyword fields (``**changes``):
    ``options`` (its defaults when None) with the keywords given, under the rule of
    :func:`settings_from`: beside a record, a keyword must agree with it (an InputError
    otherwise); without one, it sets that field. An unknown field is a TypeError, as in
    :meth:`ShapeOptions.replace`.
    """
    # Each value validated and normalized alone (grids and levels as tuples of ints), so
    # that an equal value given in another form agrees with the record's.
    given = ShapeOptions().replace(**changes) if changes else None
    settings = settings_from(function, options, **{name: getattr(given, name) for name in changes})
    record = ShapeOptions() if options is None else options
    return record.replace(**settings) if settings else record
