"""Small dense linear algebra written elementwise, so XLA fuses it over large batches.

Batched LAPACK calls on millions of 2×2 or 3×3 systems spend their time in call overhead; the
closed forms below are a handful of fused multiply-adds per grid point.  Larger systems fall back
to ``jnp.linalg.solve``.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Inexact

__all__ = ["small_inv", "small_solve"]


def small_inv(A: Inexact[Array, "*batch n n"]) -> Inexact[Array, "*batch n n"]:
    """Inverse of a batch of square matrices; adjugate formula for n ≤ 3, LU otherwise."""
    n = A.shape[-1]
    if n == 1:
        return 1.0 / A
    if n == 2:
        a, b, c, d = A[..., 0, 0], A[..., 0, 1], A[..., 1, 0], A[..., 1, 1]
        det = a * d - b * c
        return jnp.stack([jnp.stack([d, -b], -1), jnp.stack([-c, a], -1)], -2) / det[..., None, None]
    if n == 3:
        a = [[A[..., i, j] for j in range(3)] for i in range(3)]
        cof = [
            [
                a[(i + 1) % 3][(j + 1) % 3] * a[(i + 2) % 3][(j + 2) % 3]
                - a[(i + 1) % 3][(j + 2) % 3] * a[(i + 2) % 3][(j + 1) % 3]
                for j in range(3)
            ]
            for i in range(3)
        ]
        det = a[0][0] * cof[0][0] + a[0][1] * cof[0][1] + a[0][2] * cof[0][2]
        # inverse = adjugate / det, adjugate = cofactorᵀ
        adj = jnp.stack([jnp.stack([cof[j][i] for j in range(3)], -1) for i in range(3)], -2)
        return adj / det[..., None, None]
    eye = jnp.broadcast_to(jnp.eye(n, dtype=A.dtype), A.shape)
    return jnp.linalg.solve(A, eye)


def small_solve(A: Inexact[Array, "*batch n n"], B: Inexact[Array, "*batch n k"]):
    """Solve ``A X = B`` for a batch of small systems (closed form for n ≤ 3)."""
    n = A.shape[-1]
    if n <= 3:
        Ainv = small_inv(A)
        return jnp.sum(Ainv[..., :, :, None] * B[..., None, :, :], axis=-2)
    batch = jnp.broadcast_shapes(A.shape[:-2], B.shape[:-2])
    return jnp.linalg.solve(
        jnp.broadcast_to(A, (*batch, *A.shape[-2:])), jnp.broadcast_to(B, (*batch, *B.shape[-2:]))
    )
