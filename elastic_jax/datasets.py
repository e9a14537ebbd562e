"""The authors' surfaces by name: the eight shapes published with Su et al. (2020).

``load("cat1")`` returns a (3, 50, 99) float64 surface on the package's grid layout (math
§1: row 0 the north pole, column n - 1 repeating column 0), exactly as stored in the
authors' file. The files are the folder ``ShapeData/`` of the authors' repository
``zhesu1/elasticMetrics`` (GPL-3.0; the shapes come from TOSCA and SHREC'07, spherically
parametrized as in Kurtek et al. 2013), pinned to one commit by their SHA-256. They are
never shipped with the package. A file is looked up, in this order,

1. in the directory named by the environment variable ``ELASTIC_JAX_DATA``;
2. in the user cache (:func:`cache_dir`);
3. downloaded into that cache from the pinned commit, with `pooch
   <https://www.fatiando.org/pooch>`_ (``pip install "elastic-jax[data]"``).

Whichever way it comes, its SHA-256 is checked before it is read; a mismatch is an
:class:`~elastic_jax.InputError` that names the file and both checksums, and the file is
not loaded. See the documentation's data page for the source, its license and the
citation.

>>> import elastic_jax.datasets as datasets
>>> datasets.names()[:3]
('cat1', 'cat2', 'example')
"""

from __future__ import annotations

import hashlib
import os
import pathlib

import numpy as np

from ._errors import InputError

__all__ = ["REPOSITORY", "COMMIT", "cache_dir", "load", "names", "path"]

#: The authors' GitHub repository (owner/name) whose folder ``ShapeData/`` holds the files.
REPOSITORY = "zhesu1/elasticMetrics"
#: The commit of :data:`REPOSITORY` the checksums pin.
COMMIT = "a2628c3e78641a2dfadb9a85942f26d98a482c17"
_URL = f"https://raw.githubusercontent.com/{REPOSITORY}/{COMMIT}/ShapeData/"
_ENVIRONMENT = "ELASTIC_JAX_DATA"

# SHA-256 of every file of ShapeData/ at COMMIT.
_SHA256 = {
    "cat1": "23c7b4ed831f5c2ced2d7b2c66b3ae2ef6007719c174cdcd55fd2d78adab3046",
    "cat2": "189e09f97f628ccef6c0b5f1930404ee772b611010e7efd364e476f1d336660e",
    "example": "492fbc6049eca79e74f13906d2db1b47aa2cde12374a3647e36d282a14bab747",
    "hand4": "8d077e88f9b9e67207d768c55a61a3bb8f97283e392d8e06e1a4e9b169f0ccf2",
    "hand5": "9f3d22268a525521deb21b05de277617a1dac8b942f0d196b8916e219292f0fc",
    "horse0": "7db10ae7f92d6ebf6e07717d65bde0ea26d695336a5c9337dc0226cc849e8461",
    "horse2": "72820397e2af9a0a826a3ebcb0be443ce7eceb6eb8371b4bb6a0de866078abb0",
    "horse3": "8ba3609a4a652e0966cb7430ec5ab4f660e023b6504a8e59aea2b4464c544946",
}
_SHAPE = (3, 50, 99)


def names() -> tuple[str, ...]:
    """The names :func:`load` accepts, sorted: two cats, two hands, three horses and the
    authors' example surface."""
    return tuple(sorted(_SHA256))


def _file_name(name: str) -> str:
    if name not in _SHA256:
        raise InputError(f"unknown data set {name!r}: the names are {', '.join(names())}")
    return f"{name}_50_99.mat"


def cache_dir() -> pathlib.Path:
    """The user cache the files are downloaded into (pooch's ``os_cache``: e.g.
    ``~/.cache/elastic_jax`` on Linux), whether or not pooch is installed."""
    try:
        import pooch
    except ImportError:
        base = os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache"
        return pathlib.Path(base) / "elastic_jax"
    return pathlib.Path(pooch.os_cache("elastic_jax"))


def _sha256(file: pathlib.Path) -> str:
    digest = hashlib.sha256()
    with open(file, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _checked(file: pathlib.Path, name: str) -> pathlib.Path:
    found = _sha256(file)
    if found != _SHA256[name]:
        raise InputError(
            f"{file}: SHA-256 {found} is not the checksum {_SHA256[name]} of {name!r} at "
            f"{REPOSITORY}@{COMMIT[:12]}; the file was not loaded (replace or delete it)"
        )
    return file


def path(name: str) -> pathlib.Path:
    """The checked local file of ``name`` (a ``.mat`` file), downloading it if needed.

    Looks in ``$ELASTIC_JAX_DATA``, then in :func:`cache_dir`, then downloads into the
    cache with pooch. Raises :class:`~elastic_jax.InputError` for an unknown name or a
    file whose SHA-256 differs, and ImportError (with the install line) when the file must
    be downloaded and pooch is not installed.
    """
    file_name = _file_name(name)
    folder = os.environ.get(_ENVIRONMENT)
    places = ([pathlib.Path(folder)] if folder else []) + [cache_dir()]
    for place in places:
        candidate = place / file_name
        if candidate.is_file():
            return _checked(candidate, name)
    try:
        import pooch
    except ImportError as error:
        raise ImportError(
            f"{file_name} is not in ${_ENVIRONMENT} ({folder or 'unset'}) nor in "
            f"{cache_dir()}; downloading it needs pooch: pip install 'elastic-jax[data]'"
        ) from error
    try:
        fetched = pooch.retrieve(
            _URL + file_name,
            known_hash=f"sha256:{_SHA256[name]}",
            fname=file_name,
            path=cache_dir(),
            progressbar=False,
        )
    except ValueError as error:  # pooch's hash mismatch; it keeps nothing
        raise InputError(
            f"{_URL + file_name}: the download's SHA-256 is not the checksum "
            f"{_SHA256[name]} of {name!r}; nothing was kept ({error})"
        ) from error
    return pathlib.Path(fetched)


def load(name: str) -> np.ndarray:
    """The authors' surface ``name`` as a (3, 50, 99) float64 array (C order).

    The array is the file's variable ``f`` as ``scipy.io.loadmat`` reads it, bit for bit:
    coordinate k of the point at polar angle phi_i = i pi / 49 and azimuth
    theta_j = 2 pi j / 98 (math §1). The file is found or fetched by :func:`path` and
    checked against its SHA-256 first.

    >>> f = load("cat1")  # doctest: +SKIP
    >>> f.shape, f.dtype  # doctest: +SKIP
    ((3, 50, 99), dtype('float64'))
    """
    from scipy.io import loadmat

    file = path(name)
    f = loadmat(file)["f"]
    if f.shape != _SHAPE or f.dtype != np.float64:
        raise InputError(f"{file}: variable f is {f.dtype} {f.shape}, not float64 {_SHAPE}")
    return np.ascontiguousarray(f)
