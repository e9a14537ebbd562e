"""Ctrl-C and SIGTERM during a command: both stop it, leaving only complete files.

Python runs a signal handler between two bytecodes of whatever the main thread executes,
and that may be a garbage collector's callback or a ``__del__`` (JAX registers one), where
the handler's exception is printed as "Exception ignored" and dropped: the command would
run on to the end. The handlers here also record the signal, and :func:`raise_if_signalled`
(called by every progress line and before the summary is written) raises it again.
"""

from __future__ import annotations

import contextlib
import signal
import sys
from collections.abc import Iterator

__all__ = ["Terminated", "handled_signals", "raise_if_signalled"]


class Terminated(KeyboardInterrupt):
    """SIGTERM, handled like Ctrl-C (complete files only, exit 143)."""


# The signals received during the running command, in order.
_received: list[int] = []


def _exception(signum: int) -> KeyboardInterrupt:
    return Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _handler(signum, frame):
    _received.append(signum)
    raise _exception(signum)


def raise_if_signalled() -> None:
    """Raise the first signal received during the command, if any (see the module)."""
    if _received:
        raise _exception(_received[0])


def _quiet_drops(previous):
    def hook(unraisable):
        # Our own exception, dropped where Python cannot raise it, is raised again later:
        # its traceback would only alarm the user.
        if _received and isinstance(unraisable.exc_value, KeyboardInterrupt):
            return
        previous(unraisable)

    return hook


@contextlib.contextmanager
def handled_signals() -> Iterator[None]:
    """For the duration: SIGTERM raises :class:`Terminated`, and Ctrl-C, where Python's own
    handler is installed (a shell running a job in the background ignores it), raises
    KeyboardInterrupt; both are recorded for :func:`raise_if_signalled`."""
    _received.clear()
    previous = {signal.SIGTERM: signal.signal(signal.SIGTERM, _handler)}
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, _handler)
    hook = sys.unraisablehook
    sys.unraisablehook = _quiet_drops(hook)
    try:
        yield
    finally:
        sys.unraisablehook = hook
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        _received.clear()
