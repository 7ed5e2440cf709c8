r"""Banks of second-order sections in s, the building blocks of every filter.

Every filter of the toolkit is a sum/product of second-order sections ("biquads")

    G(s) = (1 + Σ_p P_p(s)) · Π_q N_q(s),

with the peak sections P_p in parallel (the constant 1 is the direct path) and the notch
sections N_q in series. A *bank* holds k sections

    (n0 s² + n1 s + n2) / (s² + d1 s + d2),

as numerator and denominator coefficients of shape (k, 3) each (d0 = 1) and the sections' own
frequencies ω0 = √d2 (rad/s, shape (k,)), used for prewarping and for a balanced realisation.

This file holds the bank type, the evaluation of a bank by Horner's rule, the balanced two-state
realisation of each section and the parallel sum 1 + Σ_k G_k as an :class:`fdjax._lti.LTI`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._checks import to_complex
from .._lti import LTI

# (num (k, 3), den (k, 3), ω0 (k,)) of a bank of k second-order sections in s.
_Bank = tuple[Float[Array, "k 3"], Float[Array, "k 3"], Float[Array, " k"]]


def _empty_bank() -> _Bank:
    return (
        jnp.zeros((0, 3), jnp.float64),
        jnp.zeros((0, 3), jnp.float64),
        jnp.zeros((0,), jnp.float64),
    )


def _biquad_s(num: Array, den: Array, x: Array) -> Array:
    """(n0 x² + n1 x + n2)/(d0 x² + d1 x + d2) by Horner, x of shape (..., 1) → (..., k)."""
    n0, n1, n2 = (to_complex(num[:, i]) for i in range(3))
    d0, d1, d2 = (to_complex(den[:, i]) for i in range(3))
    return ((n0 * x + n1) * x + n2) / ((d0 * x + d1) * x + d2)


def _block_diag(blocks: Float[Array, "k 2 2"]) -> Float[Array, "2k 2k"]:
    """The (2k, 2k) block-diagonal matrix of k 2×2 blocks."""
    k = blocks.shape[0]
    eye = jnp.eye(k, dtype=jnp.float64)
    return (eye[:, None, :, None] * blocks[:, :, None, :]).reshape(2 * k, 2 * k)


def _section_ss(num: Array, den: Array, w0: Array):
    """Balanced 2-state realisation of each section, vectorised over k sections.

    A = [[0, ω0], [−ω0, −d1]] has characteristic polynomial s² + d1 s + ω0² (= the denominator,
    d2 = ω0²); with B = [0, 1]ᵀ, (sI − A)⁻¹B = [ω0, s]ᵀ/den, so C = [(n2 − n0 d2)/ω0,
    n1 − n0 d1] and D = n0 reproduce the numerator. Every entry scales like ω0, unlike the
    companion form whose entries scale like ω0². Returns A (k, 2, 2), B (k, 2, 1), C (k, 1, 2)
    and D (k,).
    """
    zero = jnp.zeros_like(w0)
    A = jnp.stack([jnp.stack([zero, w0], -1), jnp.stack([-w0, -den[:, 1]], -1)], -2)
    B = jnp.stack([zero, jnp.ones_like(w0)], -1)[:, :, None]
    C = jnp.stack([(num[:, 2] - num[:, 0] * den[:, 2]) / w0, num[:, 1] - num[:, 0] * den[:, 1]], -1)
    return A, B, C[:, None, :], num[:, 0]


def _parallel_ss(A, B, C, D) -> LTI:
    """1 + Σ_k G_k of k two-state sections: block-diagonal A, stacked B, concatenated C,
    D = 1 + Σ D_k (continuous)."""
    k = A.shape[0]
    return LTI(
        A=_block_diag(A),
        B=B.reshape(2 * k, 1),
        C=jnp.transpose(C, (1, 0, 2)).reshape(1, 2 * k),
        D=(1 + jnp.sum(D)).reshape(1, 1),
    )
