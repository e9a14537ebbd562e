"""elastic_jax.datasets: the authors' files by name, each checked by its SHA-256.

The tests read the files in $ELASTIC_JAX_DATA (conftest points it at the shared
ShapeData folder) and never download.
"""

from __future__ import annotations

import os
import pathlib
import shutil

import numpy as np
import pytest
import scipy.io

import elastic_jax as ej
from elastic_jax import datasets

LOCAL = ("cat1", "cat2", "hand4", "horse0")


def _local_file(name: str) -> pathlib.Path:
    file = pathlib.Path(os.environ["ELASTIC_JAX_DATA"]) / f"{name}_50_99.mat"
    if not file.is_file():
        pytest.skip(f"{file} is absent")
    return file


def test_names_are_the_eight_files_of_the_authors_folder():
    assert datasets.names() == (
        "cat1",
        "cat2",
        "example",
        "hand4",
        "hand5",
        "horse0",
        "horse2",
        "horse3",
    )
    sums = pathlib.Path(os.environ["ELASTIC_JAX_DATA"]) / "SHA256SUMS"
    if sums.is_file():  # the pinned checksums are the folder's own
        listed = dict(line.split()[::-1] for line in sums.read_text().splitlines() if line)
        assert {f"{n}_50_99.mat": datasets._SHA256[n] for n in datasets.names()} == listed


@pytest.mark.parametrize("name", LOCAL)
def test_load_is_the_files_f_to_the_bit(name):
    expected = scipy.io.loadmat(_local_file(name))["f"]
    f = ej.datasets.load(name)
    assert f.shape == (3, 50, 99) and f.dtype == np.float64 and f.flags.c_contiguous
    assert f.tobytes() == np.ascontiguousarray(expected).tobytes()


def test_a_file_with_one_byte_changed_is_refused_with_its_checksum(tmp_path, monkeypatch):
    source = _local_file("cat1")
    data = bytearray(source.read_bytes())
    data[len(data) // 2] ^= 0x01
    (tmp_path / source.name).write_bytes(bytes(data))
    monkeypatch.setenv("ELASTIC_JAX_DATA", str(tmp_path))
    with pytest.raises(ej.InputError) as error:
        datasets.load("cat1")
    message = str(error.value)
    assert source.name in message and datasets._SHA256["cat1"] in message
    assert datasets._sha256(tmp_path / source.name) in message


def test_the_user_cache_is_read_after_the_environment_folder(tmp_path, monkeypatch):
    source = _local_file("horse0")
    empty, cache = tmp_path / "empty", tmp_path / "cache"
    empty.mkdir()
    cache.mkdir()
    shutil.copy(source, cache / source.name)
    monkeypatch.setenv("ELASTIC_JAX_DATA", str(empty))
    monkeypatch.setattr(datasets, "cache_dir", lambda: cache)
    assert datasets.path("horse0") == cache / source.name
    np.testing.assert_array_equal(datasets.load("horse0"), scipy.io.loadmat(source)["f"])
    # The environment folder comes first: a bad copy there is refused even though the
    # cache holds a good one.
    (empty / source.name).write_bytes(b"not the authors' file")
    with pytest.raises(ej.InputError, match="SHA-256"):
        datasets.load("horse0")


def test_an_unknown_name_lists_the_names():
    with pytest.raises(ej.InputError, match="cat1, cat2, example"):
        datasets.load("cat3")
