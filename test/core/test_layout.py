"""``layout.bit_count``'s fallback for numpy before 2.0 counts the bits numpy 2 counts."""

from __future__ import annotations

import numpy as np
import pytest

from mfp_mapper.core import layout


def test_the_swar_bit_count_equals_a_bit_by_bit_count() -> None:
    rng = np.random.default_rng(3)
    words = rng.integers(0, 2**63, (500, 8), dtype=np.uint64) * np.uint64(2)
    words[0] = [0, 2**64 - 1, 1, 2**63, 2**32 - 1, 0x5555555555555555, 0xAAAAAAAAAAAAAAAA, 7]
    words[1:] |= rng.integers(0, 2, (499, 8), dtype=np.uint64)
    by_bit = sum((words >> np.uint64(k)) & np.uint64(1) for k in range(64))
    got = layout._bit_count_swar(words)
    assert got.dtype == np.uint8
    np.testing.assert_array_equal(got, by_bit)


@pytest.mark.skipif(not hasattr(np, "bitwise_count"), reason="numpy before 2.0")
def test_bit_count_is_numpys_where_it_has_one() -> None:
    assert layout.bit_count is np.bitwise_count
