"""The writer's signatures (pipeline.store.h5file.sign with the arrays just written):
hashed from memory, they must equal what reading the file back gives, for every kind of
dataset the writer takes from memory (numeric, bool, empty, scalar) or reads back
(strings, Fortran-ordered arrays). Digests are exact: equality, no tolerance."""

import h5py
import numpy as np

from pipeline.store.h5file import _attrs_digests, content_digest, open_verified, write_file
from pipeline.store.tree import Dataset


def test_signatures_from_memory_equal_the_read_back_ones(tmp_path):
    rng = np.random.default_rng(1)
    tree = {"a/x": Dataset(rng.standard_normal((5, 3)), "m"),
            "a/scalar": Dataset(np.array(2.5), "s"),
            "a/empty": Dataset(np.zeros((0, 3)), "m"),
            "b/names": Dataset(["p", "q"], "-"),
            "b/flags": Dataset(np.array([True, False]), "-"),
            "b/ints": Dataset(np.arange(4, dtype=np.int32), "-"),
            "b/large": Dataset(rng.standard_normal((70_000, 4)), "m"),  # > 1 MB: 2nd thread
            "b/unicode": Dataset(np.array(["ab", "c"]), "-"),
            "b/fortran": Dataset(np.asfortranarray(rng.standard_normal((4, 3))), "m")}
    path = write_file(tmp_path / "t.h5", tree)
    with h5py.File(path, "r") as h5:
        assert h5.attrs["content_sha256"] == content_digest(h5)
        assert h5.attrs["attrs_sha256"].split(":")[1] == _attrs_digests(h5)[0]
    with open_verified(path):  # raises on any mismatch
        pass
