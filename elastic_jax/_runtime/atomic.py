"""Atomic file writes: a temporary file beside the destination, then a rename.

A job killed (or interrupted with Ctrl-C) while writing leaves either the old file or
the new one, never half of one, and no temporary behind.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import tempfile
from collections.abc import Iterator

import numpy as np

# Marks the temporaries (".NAME.tmp-XXXXXXXX.SUFFIX"), so that a later run can sweep up
# those of a killed one (``stale_temporaries``) without touching anything else.
TEMPORARY = ".tmp-"


def stale_temporaries(directory: str | os.PathLike) -> list[pathlib.Path]:
    """The temporaries of atomic writes under ``directory`` (left by killed runs)."""
    return [p for p in pathlib.Path(directory).rglob(f".*{TEMPORARY}*") if p.is_file()]


def _umask() -> int:
    # os.umask can only be read by setting it; set it straight back.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[pathlib.Path]:
    """Yield a temporary path in ``path``'s directory; rename it onto ``path`` on success.

    The temporary keeps ``path``'s suffix (or ``suffix``) so that writers which pick a
    format from the file name (numpy, trimesh, matplotlib) still do. On any exception,
    KeyboardInterrupt included, the temporary is removed and ``path`` is untouched.
    """
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(
        dir=path.parent, prefix=f".{path.name}{TEMPORARY}", suffix=suffix or "".join(path.suffixes)
    )
    os.close(fd)
    tmp = pathlib.Path(name)
    try:
        yield tmp
        # mkstemp makes the file private (0600); give it the mode a plain open() would.
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def save_npz_atomic(path: str | os.PathLike, **arrays) -> pathlib.Path:
    """``np.savez`` to ``path`` atomically; returns the path."""
    path = pathlib.Path(path)
    with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
    return path


def write_text_atomic(path: str | os.PathLike, text: str) -> pathlib.Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    path = pathlib.Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path
