"""Lagrange-multiplier frequency-based substructuring (LM-FBS): the one coupling primitive.

Uncoupled substructures are stacked in a block-diagonal receptance ``Y`` over their degrees of
freedom ``u``.  Interfaces are linear constraints on the *deformation* of the joints,

    Δ = B u,

where each row of the signed, scaled Boolean matrix ``B`` describes one joint.  A compliant joint
with receptance ``Y_j`` (e.g. ``1/(k + iωc)``) carries the interface force ``λ = −Y_j⁻¹ Δ``;
eliminating ``λ`` gives the coupled receptance

    Y_c = Y − Y Bᵀ (B Y Bᵀ + Y_j)⁻¹ B Y.

With ``Y_j = 0`` the joint is rigid.  The paper's Eq. (1)/(2) are the single-interface case with
``B = [−i_sc, −1, 1]`` over (screw rotation at the nut, screw axial displacement at the nut,
carriage at the nut): the bracket in Eq. (1) is ``B Y Bᵀ + 1/(k_ja + iωc_ja)``.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from . import _checks
from ._linalg import Entries, add, entries, from_entries, inv_entries, matmul_entries

__all__ = ["couple", "couple_entries", "block_diagonal", "joint_receptance"]


def couple_entries(Y: Entries, B: Entries, joint: Entries | None = None) -> Entries:
    """LM-FBS on matrices stored as nested lists of entry arrays (see ``fdjax._linalg``).

    Structural zeros (the Python int 0) in ``Y``, ``B`` or ``joint`` are skipped at trace time,
    so a block-diagonal ``Y`` and a sparse ``B`` cost only their non-zero entries.
    """
    n, m = len(Y), len(B)
    Bt = [[B[k][i] for k in range(m)] for i in range(n)]
    YBt = matmul_entries(Y, Bt)  # n × m
    BY = matmul_entries(B, Y)  # m × n
    S = matmul_entries(BY, Bt)  # m × m
    if joint is not None:
        S = [[add(S[k][q], joint[k][q]) for q in range(m)] for k in range(m)]
    X = matmul_entries(inv_entries(S), BY)  # S⁻¹ B Y, m × n
    corr = matmul_entries(YBt, X)
    return [[add(Y[i][j], _neg(corr[i][j])) for j in range(n)] for i in range(n)]


def _neg(x):
    return 0 if isinstance(x, int) and x == 0 else -x


def couple(
    receptance: Complex[Array, "*batch n n"],
    interface: Float[ArrayLike, "m n"],
    joint: Complex[Array, "*batch m m"] | None = None,
) -> Complex[Array, "*batch n n"]:
    r"""Couple substructures by LM-FBS (paper Eq. 1, in the general form below; fdjax's screw
    ratio i_sc = lead/2π (m/rad) is the reciprocal of the paper's i_a^b (rad/m), so Eq. (1)'s
    h/(i_a^b)² appears as i_sc²·h).

    .. math:: Y_c = Y - Y B^T (B Y B^T + Y_j)^{-1} B Y

    Args:
        receptance: uncoupled (block-diagonal) receptance ``Y``, complex, shape ``(..., n, n)``;
            leading axes (frequency, position, ...) are batch axes.
        interface: signed, scaled Boolean matrix ``B`` of shape ``(m, n)``; row ``k`` gives the
            deformation of joint ``k`` as ``Δ_k = Σ_i B_ki u_i``.  Scaling carries transmission
            ratios, e.g. ``−i_sc`` for a screw rotation seen at the nut.
        joint: receptance of the joints ``Y_j`` (``(..., m, m)``, broadcast against the batch),
            ``None`` for rigid joints.

    Returns:
        The coupled receptance, same shape as ``receptance``.
    """
    Y = _checks.numeric(receptance, "couple(receptance=...)")
    if Y.ndim < 2 or Y.shape[-1] != Y.shape[-2]:
        raise ValueError(f"`couple(receptance=...)` must have shape (..., n, n), got {Y.shape}")
    Y = _checks.finite(Y.astype(jnp.complex128), "couple(receptance=...)")
    B = _checks.real_array(interface, "couple(interface=...)")
    if B.ndim == 1:
        B = B[None, :]
    if B.ndim != 2 or B.shape[1] != Y.shape[-1]:
        raise ValueError(
            f"`couple(interface=...)` must have shape (m, {Y.shape[-1]}), got {B.shape}"
        )
    m = B.shape[0]
    if m == 0:
        raise ValueError(f"`couple(interface=...)` must have at least one row (a joint), got "
                         f"shape {B.shape}")
    B = _checks.finite(B, "couple(interface=...)")
    Bc = B.astype(jnp.complex128)
    Be = [[Bc[k, i] for i in range(B.shape[1])] for k in range(m)]
    Je = None
    if joint is not None:
        J = _checks.numeric(joint, "couple(joint=...)").astype(jnp.complex128)
        if J.ndim < 2 or J.shape[-2:] != (m, m):
            raise ValueError(f"`couple(joint=...)` must have shape (..., {m}, {m}), got {J.shape}")
        J = _checks.finite(J, "couple(joint=...)")
        Je = entries(J)
    # Each rigid row a constraint, none repeating another: B Y Bᵀ must be invertible on them.
    # A compliant joint's row may repeat another (joints in parallel: its Y_j keeps the bracket
    # invertible); a joint whose receptance is zero (at a batch index) is rigid there.
    rank, rigid, at = _rigid_rank(B, None if joint is None else J)
    if _checks.is_concrete(rank):
        if at is not None:
            raise ValueError(
                f"`couple(interface=...)` must have independent rows for its rigid joints "
                f"(each a compatibility constraint between DOFs; a joint of zero receptance is "
                f"rigid), got rank {rank} for {rigid} rows{at}: a zero or repeated row"
            )
    else:
        Y = eqx.error_if(Y, rank < rigid, "`couple(interface=...)` must have independent rows "
                         "for its rigid joints (each a compatibility constraint between DOFs; a "
                         "joint of zero receptance is rigid): a zero or repeated row")
    if _checks.is_concrete(B):  # exact zeros of a concrete B are structural
        Bn = np.asarray(B)
        Be = [[0 if Bn[k, i] == 0 else Be[k][i] for i in range(B.shape[1])] for k in range(m)]
    batch = Y.shape[:-2]
    if joint is not None:
        try:
            batch = jnp.broadcast_shapes(Y.shape[:-2], J.shape[:-2])
        except ValueError:
            raise ValueError(f"`couple(joint=...)` must broadcast against the receptance's "
                             f"batch {Y.shape[:-2]}, got batch {J.shape[:-2]}") from None
    out = couple_entries(entries(Y), Be, Je)
    out = from_entries(out, shape=batch, dtype=jnp.complex128)
    # every input is finite: a non-finite result is a singular bracket B Y Bᵀ + Y_j
    return _checks.check(out, jnp.isfinite, "couple(receptance=..., interface=..., joint=...)",
                         "such that the interface bracket B·Y·Bᵀ + Y_j is invertible (a finite "
                         "coupled receptance)")


def _rigid_rank(B, J):
    """The rank of the rigid joints' rows of ``B`` and their number, per batch index of the
    joints ``J`` (all joints rigid when ``J`` is None); for concrete inputs, those at the first
    batch index where the rank falls short, and " at batch index i" naming it ("" without a
    batch; None if the rank falls short nowhere).

    The rows are scaled to unit length and the compliant joints' rows replaced by unit vectors
    of their own (stacked as ``[diag(r) B̂ | diag(1 − r)]``, r = 1 for a rigid joint), so the
    rows of the stack are independent exactly when the rigid rows are; its rank counts the
    singular values above ``σ_max · max(m, n + m) · eps`` (NumPy's ``matrix_rank``).  A zero
    rigid row has rank 0.
    """
    m, n = B.shape
    rigid = (jnp.ones((m,), bool) if J is None
             else jnp.diagonal(J, axis1=-2, axis2=-1) == 0)  # (*joint batch, m)
    norms = jnp.linalg.norm(B, axis=1, keepdims=True)
    unit = B / jnp.where(norms > 0, norms, 1.0)
    r = rigid[..., :, None].astype(jnp.float64)
    stack = jnp.concatenate([r * unit, (1.0 - r) * jnp.eye(m)], axis=-1)
    sv = jnp.linalg.svd(stack, compute_uv=False)
    tol = jnp.max(sv, axis=-1, keepdims=True) * max(m, n + m) * jnp.finfo(jnp.float64).eps
    rank = jnp.sum(sv > tol, axis=-1) - jnp.sum(~rigid, axis=-1)
    count = jnp.sum(rigid, axis=-1)
    if not (_checks.is_concrete(rank) and _checks.is_concrete(count)):
        return rank, count, None
    rank, count = np.asarray(rank), np.asarray(count)
    short = np.argwhere(np.atleast_1d(rank < count))  # (bad, ndim), one column without a batch
    if len(short) == 0:
        return rank, count, None
    idx = tuple(int(k) for k in short[0]) if rank.ndim else ()
    at = "" if not idx else f" at batch index {idx[0] if len(idx) == 1 else idx}"
    return int(rank[idx]), int(count[idx]), at


def block_diagonal(*blocks: Entries) -> Entries:
    """Block-diagonal matrix of entry-list blocks, off-diagonal blocks as structural zeros."""
    n = sum(len(b) for b in blocks)
    out = [[0] * n for _ in range(n)]
    i = 0
    for b in blocks:
        for r, row in enumerate(b):
            for c, x in enumerate(row):
                out[i + r][i + c] = x
        i += len(b)
    return out


def joint_receptance(stiffness: Float[ArrayLike, "*shape"], damping: Float[ArrayLike, "*shape"],
                     omega: Complex[ArrayLike, "*shape"]) -> Complex[Array, "*shape"]:
    """Receptance of a spring–damper joint, ``1 / (k + iωc)`` (paper Eq. 1, last term).

    ``stiffness`` k > 0 (N/m), ``damping`` c ≥ 0 (N·s/m), finite angular frequencies ``omega``
    (rad/s, real or complex); all broadcast against each other.
    """
    where = "joint_receptance({}=...)"
    k = _checks.positive(_checks.real_array(stiffness, where.format("stiffness")),
                         where.format("stiffness"))
    c = _checks.nonnegative(_checks.real_array(damping, where.format("damping")),
                            where.format("damping"))
    w = _checks.finite(_checks.numeric(omega, where.format("omega")), where.format("omega"))
    try:
        jnp.broadcast_shapes(k.shape, c.shape, w.shape)
    except ValueError:
        raise ValueError(f"`joint_receptance(stiffness=..., damping=..., omega=...)` must "
                         f"broadcast against each other, got shapes {k.shape}, {c.shape} and "
                         f"{w.shape}") from None
    cx = _checks.to_complex
    out = 1.0 / (cx(k) + 1j * cx(w) * cx(c))
    return _checks.finite_output(out, "joint_receptance(...)")
