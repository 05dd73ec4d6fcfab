"""The stable order of integer keys by 16-bit radix passes against NumPy's stable merge sort; the order by key, then
value against ``np.lexsort``."""
import numpy as np
import pytest

from flightsim.core.radix import by_key_then_value, stable_order


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


@pytest.mark.parametrize("span", [1, 40, (1 << 16) - 1, 1 << 16, 10 ** 6])
def test_order_by_key_then_value(span):
    """The order by key, then value against ``np.lexsort``: the same (key, value) sequence (equal values may swap), for
    keys spanning up to 2^16 − 1 (one 16-bit radix pass) and beyond (two), offset and not in order."""
    rng = np.random.default_rng(span)
    keys = 7 + np.sort(rng.integers(0, span, 5_000))
    keys[:3] = 7 + span - 1  # the span's far end first: not in order
    values = np.round(rng.normal(0.0, 30.0, len(keys)), 1)  # equal values too
    order, expected = by_key_then_value(keys, values), np.lexsort((values, keys))
    assert np.array_equal(keys[order], keys[expected]) and np.array_equal(values[order], values[expected])
    assert np.array_equal(np.sort(order), np.arange(len(values)))
    assert len(by_key_then_value(np.zeros(0, dtype=np.int64), np.zeros(0))) == 0
