"""Checkpoints of long jobs: a fingerprint of the inputs and settings, and the reading
of a checkpoint written atomically (a truncated or foreign file is an InputError).
"""

from __future__ import annotations

import hashlib
import json
import pathlib

import numpy as np

from .._errors import InputError


def fingerprint_of(*arrays, **settings) -> str:
    digest = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(np.asarray(a))
        digest.update(str((a.shape, a.dtype.str)).encode())
        digest.update(a.tobytes())
    digest.update(json.dumps(settings, sort_keys=True, default=str).encode())
    return digest.hexdigest()


def load_checkpoint(path: pathlib.Path, fingerprint: str) -> dict | None:
    """The arrays of the checkpoint at ``path`` (None if there is none); an InputError
    naming the file if it cannot be read or was written for other inputs."""
    if not path.exists():
        return None
    try:
        # Our own handle: np.load leaves the file open when the archive is truncated.
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as data:
            saved = {k: data[k] for k in data.files}
        saved_fingerprint = str(saved["fingerprint"])
    except Exception as err:  # a truncated or foreign file: zipfile, numpy or KeyError
        raise InputError(
            f"checkpoint {str(path)!r} cannot be read ({type(err).__name__}: {err}); "
            "remove it to start over"
        ) from err
    if saved_fingerprint != fingerprint:
        raise InputError(
            f"checkpoint {str(path)!r} was written for other shapes or settings "
            f"(fingerprint {saved_fingerprint[:12]} != {fingerprint[:12]}); resume it with "
            "the inputs that wrote it, or start over without resuming"
        )
    return saved
