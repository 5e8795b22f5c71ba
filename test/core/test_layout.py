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


@pytest.mark.parametrize("count", [layout.bit_count, layout._bit_count_swar])
def test_block_counts_and_mask_words_count_each_row(
    count: object, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Per-row set bits and nonzero words of (B, 8) masks, with either bit count: full
    words (512 bits a row), empty rows, single bits, random rows; other shapes too."""
    monkeypatch.setattr(layout, "bit_count", count)
    rng = np.random.default_rng(3)
    masks = rng.integers(0, 2**64, size=(300, 8), dtype=np.uint64, endpoint=False)
    masks[rng.random(masks.shape) < 0.4] = 0
    masks[0] = np.uint64(2**64 - 1)  # every bit
    masks[1] = 0
    masks[2] = np.uint64(1) << np.arange(8, dtype=np.uint64) * np.uint64(9)
    bits = np.unpackbits(masks.view(np.uint8), axis=1).sum(axis=1)
    assert layout.block_counts(masks).tolist() == bits.tolist()
    assert layout.block_counts(masks)[0] == 512
    assert layout.mask_words(masks).tolist() == np.count_nonzero(masks, axis=1).tolist()
    assert layout.voxel_starts(masks)[-1] == bits.sum()
    assert layout.block_counts(masks[::2]).tolist() == bits[::2].tolist()  # not contiguous
    assert layout.block_counts(np.zeros((0, 8), np.uint64)).shape == (0,)
    assert (
        layout.block_counts(masks[:, :3]).tolist()
        == np.unpackbits(masks[:, :3].copy().view(np.uint8), axis=1).sum(axis=1).tolist()
    )
