"""`ingest.rows.rows` picks exactly what numpy's indexing picks."""

from typing import Any

import numpy as np
import pytest

from ingest.rows import rows


@pytest.mark.parametrize("shape", [(7,), (7, 3), (7, 2, 2)])
@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64, np.int64, np.uint8])
def test_rows_equal_numpy_indexing(shape: tuple[int, ...], dtype: type) -> None:
    a: np.ndarray[Any, Any] = (np.arange(np.prod(shape)) * 3 % 11).reshape(shape).astype(dtype)
    mask = np.array([True, False, True, True, False, False, True])
    for which in (
        mask,
        ~mask,
        np.zeros(7, bool),
        np.ones(7, bool),
        np.array([6, 0, -1, 3, 3]),
        np.zeros(0, int),
    ):
        got = rows(a, which)
        want = a[which]
        assert got.dtype == want.dtype and got.shape == want.shape
        assert np.array_equal(got, want)
        assert got.flags.c_contiguous


def test_an_index_out_of_range_raises_as_numpy_does() -> None:
    with pytest.raises(IndexError):
        rows(np.zeros((3, 3)), np.array([3]))
