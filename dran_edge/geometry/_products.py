"""Matrix products of small matrices that round the same on every CPU.

``A @ B`` on 3×3 / 4×4 matrices goes to OpenBLAS, whose kernels sum the k products of an
entry with fused multiply-adds, in an order chosen per CPU. x86-64 and aarch64 therefore
differ in the last bit of a pose product, and one discrete decision later (is a separator
worth sending?) a replay of the same recording on the robot and on a laptop parts
(docs/notes/arm64-check.md has the trace).

``matmul`` here computes every entry as ``((a₀b₀ + a₁b₁) + a₂b₂) + …``: separate elementwise
multiplies and adds, each rounded by IEEE-754, in that fixed order, so the result is the same
bit pattern wherever numpy runs. Two evaluation paths give the identical sums (checked by
tests/test_geometry_products.py): one broadcast multiply and a reduction over k for few
matrices (fewer calls), a loop over k for large batches (contiguous memory). The reduction sums
in order because k < 8 (numpy's pairwise summation only splits longer runs); longer inner
dimensions go through the loop.
"""

from __future__ import annotations

import numpy as np

# Batches up to this many matrices take the one-reduction path (call overhead dominates there).
_FEW = 16
# numpy's add.reduce sums sequentially below 8 terms (pairwise blocks start at 8).
_SEQUENTIAL_REDUCE_MAX_K = 7


def matmul(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` for ``(..., n, k) @ (..., k, m)`` (leading axes broadcast), summed in fixed order."""
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    n, k = A.shape[-2:]
    m = B.shape[-1]
    if B.shape[-2] != k:
        raise ValueError(f"matmul: inner dimensions differ, {A.shape} @ {B.shape}")
    matrices = max(A.size // max(n * k, 1), B.size // max(k * m, 1))  # no broadcast_shapes call
    if k <= _SEQUENTIAL_REDUCE_MAX_K and matrices <= _FEW:
        return np.add.reduce(A[..., :, :, None] * B[..., None, :, :], axis=-2)
    out = A[..., :, 0:1] * B[..., 0:1, :]
    for j in range(1, k):
        out += A[..., :, j : j + 1] * B[..., j : j + 1, :]
    return out


def matvec(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``A v`` for ``(..., n, k)`` and ``(..., k)``, summed in the same fixed order."""
    return matmul(A, np.asarray(v, dtype=np.float64)[..., None])[..., 0]
