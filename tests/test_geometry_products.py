"""Fixed-order small-matrix products (dran_edge/geometry/_products.py): every entry is the
left-to-right sum of separately rounded products, whatever the batch size, so the bits do not
depend on the CPU's BLAS kernel."""

from __future__ import annotations

import numpy as np
import pytest

from dran_edge import geometry as geo


def _reference(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The same sums in Python floats (each * and + rounded on its own, no fused multiply-add)."""
    n, k = A.shape
    m = B.shape[1]
    out = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            acc = float(A[i, 0]) * float(B[0, j])
            for t in range(1, k):
                acc = acc + float(A[i, t]) * float(B[t, j])
            out[i, j] = acc
    return out


@pytest.mark.parametrize("k", [2, 3, 4, 6])
@pytest.mark.parametrize("batch", [(), (5,), (40,), (3, 7)])
def test_every_entry_is_the_left_to_right_sum(k, batch):
    rng = np.random.default_rng(k * 100 + len(batch))
    # magnitudes over many decades, so that a different summation order would show in the bits
    A = rng.normal(size=batch + (3, k)) * 10.0 ** rng.integers(-8, 8, size=batch + (3, k))
    B = rng.normal(size=batch + (k, 4)) * 10.0 ** rng.integers(-8, 8, size=batch + (k, 4))
    C = geo.matmul(A, B)
    assert C.shape == batch + (3, 4)
    flat_A, flat_B = A.reshape(-1, 3, k), B.reshape(-1, k, 4)
    expected = np.stack([_reference(a, b) for a, b in zip(flat_A, flat_B, strict=True)])
    assert np.array_equal(C.reshape(-1, 3, 4), expected)


def test_few_and_many_matrices_give_the_same_bits():
    """The two evaluation paths (one reduction for few matrices, a loop for many) agree bit for
    bit: a pose composed alone equals the same pose composed inside a batch."""
    rng = np.random.default_rng(7)
    T = geo.se3_exp(rng.normal(size=(200, 6)))
    U = geo.se3_exp(rng.normal(size=(200, 6)))
    batch = geo.se3_compose(T, U)
    one_by_one = np.stack([geo.se3_compose(t, u) for t, u in zip(T, U, strict=True)])
    assert np.array_equal(batch, one_by_one)


def test_broadcasting_and_vectors():
    rng = np.random.default_rng(3)
    R = rng.normal(size=(5, 3, 3))
    v = rng.normal(size=(5, 3))
    np.testing.assert_allclose(geo.matvec(R, v), np.einsum("nij,nj->ni", R, v), rtol=1e-14)
    np.testing.assert_allclose(geo.matmul(R, np.eye(3)), R, rtol=0, atol=0)
    with pytest.raises(ValueError, match="inner dimensions"):
        geo.matmul(R, np.ones((4, 2)))
