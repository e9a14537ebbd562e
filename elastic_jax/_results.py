"""The result protocol: ``RESULTS``, the codes every result record carries.

optimistix's codes (a subclass of its ``RESULTS``, so that its solvers' results promote
into it), a few of the package's own, and the helpers the records share. Every result
record of the package has ``converged``, ``result`` (one of these), ``message`` ('' when
converged, except for a Karcher mean, which says which criterion stopped it) and
``num_steps``.
"""

from __future__ import annotations

import dataclasses

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
        if not _concrete(item._value):
            return "traced"
        if np.ndim(item._value) > 0:  # a batch of results (vmap): their names
            return str(np.vectorize(cls._name_of_code)(np.asarray(item._value)))
        message = cls.message(item)
        name = cls.name(item)
        return f"{name}: {message}" if message else name

    def message(cls, item) -> str:
        """The item's message alone ('' for ``successful``)."""
        return super().__getitem__(item)

    def from_code(cls, code: int | np.integer):
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

    not_registered = (
        "The registration ended above the pair as given: the registered geodesic's energy "
        "was higher than the parametrized geodesic's (identity reparametrization and "
        "rotation), so the result is the parametrized geodesic, an upper bound of the shape "
        "distance. The rounds ended in a worse basin than the identity's; more "
        "init_candidates, init='energy' or a start of your own may find a lower one."
    )
    not_resolved = (
        "The working grid's levels ran out before two successive levels' distances agreed "
        "within rtol: the distance is the finest level's, and levels.estimate states how "
        "far it moved from the level before. Give finer levels, or a larger rtol."
    )
    below_area_bound = (
        "The distance came out below the area lower bound sqrt(2 b) |sqrt(A(f2)) - "
        "sqrt(A(f1))| (math §9) by more than the grid's quadrature can explain: the "
        "arithmetic lost the energy's precision (the distance is NaN, not a number that "
        "could be read as a result). Solve in float64."
    )
    saddle_point = (
        "The solver met its tolerance at a saddle point of the energy (a negative Hessian "
        "eigenvalue), not a minimum: raise saddle_checks to escape along it."
    )
    distances_at_rounding = (
        "converged: every distance is at rounding level (at most sqrt(eps) x the mean's "
        "size): the shapes are one orbit of the registration's group."
    )
    mean_velocity_small = "converged: the mean velocity's norm is at most tol x RMS distance."
    sum_sq_stalled = (
        "converged: the line search's step (the full one, or the halved one it took after the "
        "full one raised the sum) changed the sum of squared distances by less than tol "
        "(relative)."
    )
    line_search_failed = (
        "The line search failed: no step along the mean velocity, halved as often as "
        "allowed, gave a finite sum of squared distances that was not larger."
    )


# The result protocol's fields, in the order that ends every record, and how each is
# annotated (a 0-d array; a record computed in numpy, a mesh's map, holds numpy's).
_PROTOCOL = ("converged", "result", "num_steps")
_ANNOTATIONS = {
    "converged": ('Bool[Array, ""]', 'Bool[np.ndarray, ""]'),
    "result": ("RESULTS",),
    "num_steps": ('Int[Array, ""]', 'Int[np.ndarray, ""]'),
}


def status_record(cls):
    """Give a result record (a NamedTuple) the members the result protocol shares.

    Every result of the package carries ``converged`` (a 0-d bool array: the solve met
    its criterion), ``result`` (one ``RESULTS`` member per cause), ``num_steps`` and
    ``message``; this decorator checks the first three are there (as fields or
    properties), that those held as fields end the record in that order, annotated
    ``Bool[Array, ""]``, ``RESULTS`` and ``Int[Array, ""]`` (a TypeError when the class
    is defined, not when a long job returns one), and installs the last two members the
    records share: ``message``, the code's own words from ``RESULTS`` ('' for
    ``successful``) passed through the record's ``_explain(words)`` when it has one
    (which node, which pair, the saddle's eigenvalue), and the short repr of
    :func:`record_repr`. A class decorator rather than a base class: a NamedTuple cannot
    take a mixin.
    """
    missing = [k for k in _PROTOCOL if not hasattr(cls, k)]
    if missing:
        raise TypeError(f"{cls.__name__} lacks the result protocol's {missing}")
    fields = tuple(getattr(cls, "_fields", ()))
    # The protocol's fields end the record, in one order; a record that derives some of
    # them (properties: a mesh's map) ends with the ones it holds.
    held = tuple(k for k in _PROTOCOL if k in fields)
    if fields[len(fields) - len(held) :] != held:
        raise TypeError(
            f"{cls.__name__}: the result protocol's fields {list(held)} must end the record "
            f"in that order; its fields end with {list(fields[-len(held) :])}"
        )
    annotations = getattr(cls, "__annotations__", {})
    for name in held:
        annotation = annotations.get(name, "")
        # A NamedTuple keeps postponed annotations as ForwardRefs of their source text.
        written = str(getattr(annotation, "__forward_arg__", annotation)).replace("'", '"')
        written = " ".join(written.split())
        if written not in _ANNOTATIONS[name]:
            raise TypeError(
                f"{cls.__name__}.{name} must be annotated {_ANNOTATIONS[name][0]}; got {written!r}"
            )
    explain = getattr(cls, "_explain", None)

    def message(self) -> str:
        words = result_message(self.result)
        return words if explain is None else explain(self, words)

    message.__doc__ = (
        "Why the solve stopped, in words: the result code's own ('' when it converged; a "
        "Karcher mean names its criterion), with what this record adds to them."
    )
    cls.message = property(message)
    cls.__repr__ = record_repr
    return cls


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


def unsolved_message(record, kind: str, k: int, last: int, words: str) -> str:
    """'' for a converged ``record``; else which ``kind`` (node, rung) k of last did not
    solve and the code's ``words``: the message of a record of sequential solves."""
    if bool(record.converged):
        return ""
    return f"{kind} {k} of {last} did not solve: {words}"


# How a result record prints: Equinox's short form, arrays as dtype[shape].
_WIDTH = 100  # one line when it fits, else one field per line
_MAX_CHARS = 2000  # the most any record prints
_MAX_ITEMS = 6  # items shown of a tuple, list or dict field
_MAX_TEXT = 60  # characters shown of a string or another object's repr
_MAX_DEPTH = 3  # records nested deeper print as their class name
_DTYPES = {"float": "f", "int": "i", "uint": "u", "complex": "c", "bfloat": "bf"}


def record_repr(self) -> str:
    """A result record in at most 2,000 characters: each field by name, arrays as their
    dtype and shape (``path=f64[13,3,25,49]``), scalars by value (``distance=0.735123``,
    ``converged=True``), the result code by name (``result=successful``), nested records
    alike. Batches (vmap) print as summaries (``converged=bool[3](2 of 3 True)``), traced
    records as shapes; nothing is computed and nothing fails on a tracer.

    Example:
        >>> import numpy as np
        >>> from elastic_jax import Refinement
        >>> Refinement(np.array(0.7351234), np.array(True), np.zeros((2, 3)))
        Refinement(distance_time=0.735123, distance_grid=True, relative_change=f64[2,3])
    """
    text = _pformat(self, 0, 0)
    if len(text) > _MAX_CHARS:
        text = text[: _MAX_CHARS - 5] + " ...)"
    return text


def _pformat(value, indent: int, depth: int, lead: int = 0) -> str:
    """``value`` printed at ``indent`` spaces, after ``lead`` characters of its line (a
    field's name and '=')."""
    if _is_result(value):
        return _result_text(value)
    fields = _fields(value)
    if fields is not None:
        name = type(value).__name__
        if depth >= _MAX_DEPTH:
            return f"{name}(...)"
        parts = [f"{k}={_pformat(v, indent + 2, depth + 1, len(k) + 1)}" for k, v in fields]
        return _wrap(name + "(", parts, ")", indent, lead)
    if isinstance(value, (list, tuple)):
        parts = [_pformat(v, indent + 2, depth + 1) for v in value[:_MAX_ITEMS]]
        if len(value) > _MAX_ITEMS:
            parts.append(f"... ({len(value)} items)")
        return _wrap("[", parts, "]", indent, lead)
    if isinstance(value, dict):
        items = [(_cut(repr(k)), v) for k, v in value.items()]
        parts = [
            f"{k}: {_pformat(v, indent + 2, depth + 1, len(k) + 2)}" for k, v in items[:_MAX_ITEMS]
        ]
        if len(items) > _MAX_ITEMS:
            parts.append(f"... ({len(items)} items)")
        return _wrap("{", parts, "}", indent, lead)
    if isinstance(value, str):
        return repr(value) if len(value) <= _MAX_TEXT else repr(value[: _MAX_TEXT - 3] + "...")
    if value is None or isinstance(value, (bool, int, float, complex, np.generic)):
        return _scalar_text(value)
    if isinstance(value, (jax.Array, np.ndarray)):  # tracers included
        return _array_text(value)
    return _cut(repr(value))


def _fields(value) -> list | None:
    """A record's (name, value) pairs: a NamedTuple's or a dataclass's (a SplitMetric). A
    record whose ``result`` is a property (SphericalParametrization) shows it last."""
    if isinstance(value, tuple) and hasattr(type(value), "_fields"):
        fields = list(zip(type(value)._fields, value, strict=True))
        if "result" not in type(value)._fields and isinstance(
            getattr(type(value), "result", None), property
        ):
            try:
                fields.append(("result", value.result))
            except Exception:  # a property that needs concrete values; leave it out
                pass
        return fields
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return [(f.name, getattr(value, f.name)) for f in dataclasses.fields(value) if f.repr]
    return None


def _wrap(opening: str, parts: list[str], closing: str, indent: int, lead: int) -> str:
    """One line when it fits in _WIDTH (with a trailing comma), else one part per line."""
    line = opening + ", ".join(parts) + closing
    if indent + lead + len(line) + 1 <= _WIDTH and "\n" not in line:
        return line
    pad = " " * (indent + 2)
    return opening + "\n" + "".join(f"{pad}{p},\n" for p in parts) + " " * indent + closing


def _cut(text: str) -> str:
    return text if len(text) <= _MAX_TEXT else text[: _MAX_TEXT - 3] + "..."


def _is_result(value) -> bool:
    return isinstance(getattr(value, "_enumeration", None), type) and hasattr(value, "_value")


def _short_dtype(dtype) -> str:
    dtype = np.dtype(dtype)
    if dtype == np.bool_:
        return "bool"
    for kind, short in _DTYPES.items():
        if dtype.name.startswith(kind):
            return short + dtype.name[len(kind) :]
    return dtype.name


def _shape_text(value) -> str:
    return f"{_short_dtype(value.dtype)}[{','.join(str(s) for s in np.shape(value))}]"


def _concrete(value) -> bool:
    return not isinstance(value, jax.core.Tracer)


def _scalar_text(value) -> str:
    """A concrete scalar's value: True, 7, 0.735123 (6 significant digits), nan."""
    if value is None or isinstance(value, (bool, np.bool_)):
        return str(None if value is None else bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.6g}"
    return _cut(repr(value))


def _array_text(value) -> str:
    """An array: its dtype and shape, a concrete scalar its value, a concrete boolean
    array how many are True (``bool[3](2 of 3 True)``)."""
    if not _concrete(value):
        return _shape_text(value)
    try:  # a donated (deleted) or not fully addressable array has no values to read
        if np.ndim(value) == 0:
            return _scalar_text(np.asarray(value)[()])
        if value.dtype == np.bool_ and np.size(value) > 0:
            true, size = int(np.count_nonzero(np.asarray(value))), int(np.size(value))
            count = "all" if true == size else "none" if true == 0 else f"{true} of {size}"
            return f"{_shape_text(value)}({count} True)"
    except Exception:
        pass
    return _shape_text(value)


def _result_text(item) -> str:
    """A result code by name (``successful``); a batch (vmap) as its names and counts
    (``RESULTS[3](2 successful, 1 stalled)``); a traced code as ``RESULTS(traced)``."""
    code = item._value
    shape = ",".join(str(s) for s in np.shape(code))
    if not _concrete(code):
        return f"RESULTS[{shape}](traced)" if shape else "RESULTS(traced)"
    codes = np.asarray(code)
    table = getattr(item._enumeration, "_name_to_item", {})  # equinox's items by name
    by_code = {int(i._value): name for name, i in table.items()}
    if codes.ndim == 0:
        return by_code.get(int(codes), f"code {int(codes)}")
    values, counts = np.unique(codes, return_counts=True)
    names = [f"{c} {by_code.get(int(v), f'code {v}')}" for v, c in zip(values, counts, strict=True)]
    return f"RESULTS[{shape}]({', '.join(names)})"
