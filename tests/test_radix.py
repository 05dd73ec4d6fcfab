"""The stable order of integer keys by 16-bit radix passes against NumPy's stable merge sort."""
import numpy as np
import pytest

from flightsim.core.radix import stable_order


@pytest.mark.parametrize("top", [1, 300, 1 << 16, (1 << 16) + 1, 89_401, 1 << 33, (1 << 62) + 5])
def test_the_order_is_numpys_stable_argsort(top):
    rng = np.random.default_rng(top % 1000)
    keys = rng.integers(0, top, 200_003, dtype=np.int64)  # many ties: their order of appearance must be kept
    keys[:3] = top - 1  # the widest key present
    order = stable_order(keys)
    assert order.dtype == np.int64
    assert np.array_equal(order, np.argsort(keys, kind="mergesort"))


def test_unsigned_and_narrow_keys_and_an_empty_array():
    keys = np.array([5, 3, 5, 0, 3, 65535, 65536, 3], dtype=np.uint32)
    assert list(stable_order(keys)) == [3, 1, 4, 7, 0, 2, 5, 6]
    assert list(stable_order(keys.astype(np.uint8) % 4)) == [3, 6, 0, 2, 1, 4, 5, 7]  # keys 1 3 1 0 3 3 0 3
    assert len(stable_order(np.zeros(0, dtype=np.int64))) == 0


@pytest.mark.parametrize("keys, message", [
    (np.array([1, -1, 2]), "lowest is -1"),
    (np.array([1.0, 2.0]), "1-D array of integers"),
    (np.zeros((2, 2), dtype=np.int64), "1-D array of integers"),
])
def test_keys_it_cannot_sort_are_refused(keys, message):
    with pytest.raises(ValueError, match=message):
        stable_order(keys)
