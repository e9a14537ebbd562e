"""The result protocol: ``RESULTS``, the codes every result record carries.

optimistix's codes (a subclass of its ``RESULTS``, so that its solvers' results promote
into it), a few of the package's own, and the helpers the records share. Every result
record of the package has ``converged``, ``result`` (one of these), ``message`` ('' when
converged, except for a Karcher mean, which says which criterion stopped it) and
``num_steps``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array


class _NamedEnumeration(type(optx.RESULTS)):
    """The metaclass of optimistix's RESULTS, whose items then print their name.

    equinox prints an item as ``RESULTS<message>``, and the message of ``successful`` is
    empty (``RESULTS<>``); with the name in front a result reads ``RESULTS<successful>``
    or ``RESULTS<stalled: The solver stopped ...>``. Only the text changes: items, codes
    and ``where`` / ``promote`` are equinox's own.
    """

    def __getitem__(cls, item) -> str:
        if isinstance(item._value, jax.core.Tracer):
            return "traced"
        if np.ndim(item._value) > 0:  # a batch of results (vmap): their names
            return str(np.vectorize(cls._name_of_code)(np.asarray(item._value)))
        message = cls.message(item)
        name = cls.name(item)
        return f"{name}: {message}" if message else name

    def message(cls, item) -> str:
        """The item's message alone ('' for ``successful``)."""
        return super().__getitem__(item)

    def from_code(cls, code: int):
        """The item whose code is ``code`` (a concrete int, e.g. one stored in a file)."""
        for candidate in getattr(cls, "_name_to_item", {}).values():
            if int(candidate._value) == int(code):
                return candidate
        raise ValueError(f"no result code {code}")

    def name(cls, item) -> str:
        """The item's name, e.g. ``"successful"`` (its code must be concrete)."""
        return cls._name_of_code(int(item._value))

    def _name_of_code(cls, code: int) -> str:
        # equinox keeps the items by name in _name_to_item (its own table of the class).
        for name, candidate in getattr(cls, "_name_to_item", {}).items():
            if int(candidate._value) == code:
                return name
        return f"code {code}"


class RESULTS(optx.RESULTS, metaclass=_NamedEnumeration):  # pyright: ignore
    """optimistix's result codes and more: a solve that stopped making progress or ended
    at a saddle, registration rounds that the grid's resolution stopped, how a Karcher iteration
    ended (three ways of converging, one of failing). Every result record of the package
    carries one in ``result``; it prints by name (``RESULTS<successful>``)."""

    __module__ = "elastic_jax"  # where users import it from: prints elastic_jax.RESULTS<...>

    stalled = (
        "The solver stopped making progress (steps and value changes at rounding level) "
        "before the gradient norm reached tol: the precision cannot resolve tol; raise tol "
        "or use float64."
    )
    resolution_limited = (
        "The registration rounds stopped at the edge of the reparametrizations the solver "
        "accepts: the last round's Diff step towards a lower energy folded gamma or "
        "stretched it past the area floor (5 times the grid's own area error, so about the "
        "stretch of a Moebius map with |a| = 0.64 on any grid), and shrunk until accepted, "
        "it lowered the energy little or not at all. The distance is the lowest energy the "
        "rounds reached within that edge, not a converged minimum. The edge bounds the "
        "stretch alike on every grid; another grid, init or init_candidates may still end "
        "elsewhere."
    )

    saddle_point = (
        "The solver met its tolerance at a saddle point of the energy (a negative Hessian "
        "eigenvalue), not a minimum: raise saddle_checks to escape along it."
    )
    distances_at_rounding = (
        "Converged: every distance is at rounding level, so the shapes are one orbit of the "
        "registration's group."
    )
    mean_velocity_small = "Converged: the mean velocity's norm is at most tol x RMS distance."
    sum_sq_stalled = (
        "Converged: a full step changed the sum of squared distances by less than tol (relative)."
    )
    line_search_failed = (
        "The line search failed: no step along the mean velocity, halved as often as "
        "allowed, gave a finite sum of squared distances that was not larger."
    )


def result_message(result: RESULTS) -> str:
    """The solver's words for a (concrete, unbatched) result code; '' on success."""
    return RESULTS.message(result)


def first_failure(results: RESULTS, ok: Array) -> RESULTS:
    """One code for a sequence of solves ``results`` (stacked, leading axis K) whose
    ``ok (K,)`` says which succeeded: ``successful`` when all did, else the first failed
    solve's code. Traceable (the record of a shot path, a ladder, a line of inversions)."""
    if ok.shape[0] == 0:  # nothing was solved
        return RESULTS.successful
    first = jnp.argmin(ok)  # the first False; 0 when all are True (then unused)
    failed = jax.tree_util.tree_map(lambda value: value[first], results)
    return RESULTS.where(jnp.all(ok), RESULTS.successful, failed)


def unsolved_message(record, kind: str, k: int, last: int) -> str:
    """'' for a converged ``record``; else which ``kind`` (node, rung) k of last did not
    solve and the code's words: the message of a record of sequential solves."""
    if bool(record.converged):
        return ""
    return f"{kind} {k} of {last} did not solve: {result_message(record.result)}"
