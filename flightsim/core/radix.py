"""Stable orders of large arrays of non-negative integer keys (an ATLAS beam's photons by pulse) by radix passes, and
orders by an integer key, then a value (an ATLAS beam's photons by window or segment, then height).

NumPy's stable sort of 16-bit integers is a radix sort; of wider integers a merge sort (~1 s a 1e7 int64 keys, ~3×
as long as two 16-bit passes). :func:`stable_order` sorts the keys 16 bits at a time, least significant first, each
pass stable, so the result is ``np.argsort(keys, kind="stable")`` exactly.
"""
from __future__ import annotations

import numpy as np

DIGIT_BITS = 16


def stable_order(keys: np.ndarray) -> np.ndarray:
    """The permutation (int64) that sorts the non-negative integer ``keys`` (1-D) stably: equal keys keep their
    order, as ``np.argsort(keys, kind="stable")``."""
    keys = np.asarray(keys)
    if keys.ndim != 1 or not np.issubdtype(keys.dtype, np.integer):
        raise ValueError(f"stable_order sorts a 1-D array of integers, not {keys.dtype} of shape {keys.shape}")
    if keys.size == 0:
        return np.zeros(0, dtype=np.int64)
    if keys.min() < 0:
        raise ValueError(f"stable_order sorts non-negative keys; the lowest is {keys.min()}")
    if keys.dtype.itemsize * 8 <= DIGIT_BITS:  # one radix sort already
        return np.argsort(keys, kind="stable").astype(np.int64, copy=False)
    top, order, shift = int(keys.max()), None, 0
    while True:
        digits = ((keys if order is None else keys[order]) >> shift) & ((1 << DIGIT_BITS) - 1)
        step = np.argsort(digits.astype(np.uint16), kind="stable")
        order = step if order is None else order[step]
        shift += DIGIT_BITS
        if top >> shift == 0:
            return order.astype(np.int64, copy=False)


def by_key_then_value(keys: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The order by integer ``keys`` (1-D), then by ``values`` (equal values of a key in any order): a sort by value,
    then :func:`stable_order` of the keys (one 16-bit radix pass where they span fewer than 2^16). The (key, value)
    sequence of ``np.lexsort((values, keys))`` in a quarter of its time on an ATLAS beam of 4e6 photons."""
    keys = np.asarray(keys)
    if keys.size == 0:
        return np.zeros(0, dtype=np.int64)
    by_value = np.argsort(values)
    return by_value[stable_order(keys[by_value] - keys.min())]
