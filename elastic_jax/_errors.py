"""The package's exception and warning classes: a leaf module that every other imports.

``InputError`` is a ValueError, so code written against the standard library's
exceptions catches it; ``ConvergenceWarning`` is a UserWarning that a solve emits when it
returns before meeting its tolerance (its record then says ``converged=False``); the
command line reports its own bad input as the subclass ``cli.BadInput``.
"""

from __future__ import annotations


class InputError(ValueError):
    """An input or option the library cannot use; the message names it and says why."""


class ConvergenceWarning(UserWarning):
    """A solve stopped before meeting its tolerance (its result says converged=False)."""


class FrameWarning(UserWarning):
    """A mesh's principal frame is undetermined (a symmetry): its grid uses the input's axes."""


# Tracebacks and reprs name them where users import them from.
InputError.__module__ = ConvergenceWarning.__module__ = "elastic_jax"
FrameWarning.__module__ = "elastic_jax.io"
