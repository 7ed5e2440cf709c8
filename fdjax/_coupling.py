"""Lagrange-multiplier frequency-based substructuring (LM-FBS): the one coupling primitive.

Uncoupled substructures are stacked in a block-diagonal receptance ``Y`` over their degrees of
freedom ``u``.  Interfaces are linear constraints on the *deformation* of the joints,

    Δ = B u,

where each row of the signed, scaled Boolean matrix ``B`` describes one joint.  A compliant joint
with receptance ``Y_j`` (e.g. ``1/(k + iωc)``) carries the interface force ``λ = -Y_j⁻¹ Δ``;
eliminating ``λ`` gives the coupled receptance

    Y_c = Y − Y Bᵀ (B Y Bᵀ + Y_j)⁻¹ B Y.

With ``Y_j = 0`` the joint is rigid.  The paper's Eq. (1)/(2) are the single-interface case with
``B = [−i_sc, −1, 1]`` over (screw rotation at the nut, screw axial displacement at the nut,
carriage at the nut): the bracket in Eq. (1) is ``B Y Bᵀ + 1/(k_ja + iωc_ja)``.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Complex, Float

from ._linalg import small_solve

__all__ = ["couple", "block_diagonal", "joint_receptance"]


def couple(
    receptance: Complex[Array, "*batch n n"],
    interface: Float[ArrayLike, "m n"],
    joint: Complex[Array, "*batch m m"] | None = None,
) -> Complex[Array, "*batch n n"]:
    r"""Couple substructures by LM-FBS (paper Eq. 1, derived form of DESIGN.md §2).

    .. math:: Y_c = Y - Y B^T (B Y B^T + Y_j)^{-1} B Y

    Args:
        receptance: uncoupled (block-diagonal) receptance ``Y``, complex, shape ``(..., n, n)``;
            leading axes (frequency, position, ...) are batch axes.
        interface: signed, scaled Boolean matrix ``B`` of shape ``(m, n)``; row ``k`` gives the
            deformation of joint ``k`` as ``Δ_k = Σ_i B_ki u_i``. Scaling carries transmission
            ratios, e.g. ``-i_sc`` for a screw rotation seen at the nut.
        joint: receptance of the joints ``Y_j`` (``(..., m, m)``, broadcast against the batch),
            ``None`` for rigid joints.

    Returns:
        The coupled receptance, same shape as ``receptance``.
    """
    Y = jnp.asarray(receptance)
    if Y.ndim < 2 or Y.shape[-1] != Y.shape[-2]:
        raise ValueError(f"`couple(receptance=...)` must have shape (..., n, n), got {Y.shape}")
    if not jnp.issubdtype(Y.dtype, jnp.complexfloating):
        Y = Y.astype(jnp.complex128)
    B = jnp.asarray(interface)
    if B.ndim == 1:
        B = B[None, :]
    if B.ndim != 2 or B.shape[1] != Y.shape[-1]:
        raise ValueError(
            f"`couple(interface=...)` must have shape (m, {Y.shape[-1]}), got {B.shape}"
        )
    B = B.astype(Y.dtype)
    m = B.shape[0]
    # Products with the (small, constant) B are written as broadcast sums so XLA fuses them
    # with the surrounding elementwise work instead of issuing many tiny batched dots.
    YBt = jnp.sum(Y[..., :, None, :] * B[None, :, :], axis=-1)  # (..., n, m)
    BY = jnp.sum(B[:, :, None] * Y[..., None, :, :], axis=-2)  # (..., m, n)
    BYBt = jnp.sum(BY[..., :, None, :] * B[None, :, :], axis=-1)  # (..., m, m)
    S = BYBt if joint is None else BYBt + jnp.asarray(joint).astype(Y.dtype)
    if S.shape[-2:] != (m, m):
        raise ValueError(f"`couple(joint=...)` must have shape (..., {m}, {m}), got {S.shape}")
    X = small_solve(S, BY)  # (..., m, n) = S⁻¹ B Y
    return Y - jnp.sum(YBt[..., :, :, None] * X[..., None, :, :], axis=-2)


def block_diagonal(*blocks: Complex[Array, "*batch ni ni"]) -> Complex[Array, "*batch n n"]:
    """Stack batched square blocks into one block-diagonal array (leading axes broadcast)."""
    blocks = [jnp.asarray(b) for b in blocks]
    for k, b in enumerate(blocks):
        if b.ndim < 2 or b.shape[-1] != b.shape[-2]:
            raise ValueError(f"`block_diagonal` block {k} must be (..., n, n), got {b.shape}")
    same = len({b.dtype for b in blocks}) == 1
    dtype = blocks[0].dtype if same else jnp.complex128
    batch = jnp.broadcast_shapes(*[b.shape[:-2] for b in blocks])
    n = sum(b.shape[-1] for b in blocks)
    out = jnp.zeros((*batch, n, n), dtype)
    i = 0
    for b in blocks:
        k = b.shape[-1]
        out = out.at[..., i : i + k, i : i + k].set(jnp.broadcast_to(b, (*batch, k, k)).astype(dtype))
        i += k
    return out


def joint_receptance(stiffness, damping, omega) -> Complex[Array, "..."]:
    """Receptance of a spring–damper joint, ``1 / (k + iωc)`` (paper Eq. 1, last term)."""
    k = jnp.asarray(stiffness).astype(jnp.complex128)
    c = jnp.asarray(damping).astype(jnp.complex128)
    w = jnp.asarray(omega).astype(jnp.complex128)
    return 1.0 / (k + 1j * w * c)
