"""The package's exception and warning classes: a leaf module that every other imports.

``InputError`` is a ValueError, so code written against the standard library's
exceptions catches it; ``ConvergenceWarning`` is a UserWarning that a solve emits when it
returns before meeting its tolerance (its record then says ``converged=False``); the
command line reports its own bad input as the subclass ``cli.BadInput``.
"""

from __future__ import annotations

import os
import sys
import warnings


class InputError(ValueError):
    """An input or option the library cannot use; the message names it and says why."""


class ConvergenceWarning(UserWarning):
    """A solve stopped before meeting its tolerance (its result says converged=False)."""


class FrameWarning(UserWarning):
    """A mesh's principal frame is undetermined (a symmetry): its grid uses the input's axes."""


_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def warn_user(message: str, category: type[Warning]) -> None:
    """``warnings.warn`` attributed to the first line outside this package that led here:
    the user's call, however many of the package's own frames (wrappers, drivers,
    internal callers) lie between it and the warning."""
    frame, level = sys._getframe(0), 1
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(_PACKAGE):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)


# Tracebacks and reprs name them where users import them from.
InputError.__module__ = ConvergenceWarning.__module__ = "elastic_jax"
FrameWarning.__module__ = "elastic_jax.io"
