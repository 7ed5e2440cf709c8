r"""Running a discrete LTI loop fast, and telling when it fails.

* :func:`lifted_outputs`: the outputs of s_{k+1} = A s_k + B w_k by the lifted (block)
  recursion, K samples per sequential step;
* :func:`growth_rate`: the growth rate of the least stable pole from matrix products only
  (works under ``jit`` and ``vmap``);
* :func:`first_bad`: where a run diverged, with the outputs frozen from there on.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

CHUNK = 16  # samples per block of the lifted recursion
_HOLD = 1e30  # a run's state beyond it has diverged (physical states are ≲ 1e3)

MARGINAL = 1e-9
"""A pole with |Re s| T below this (T the servo's period; ln|z| for the sampled loop) is on
the stability boundary: marginal, neither decaying nor growing.  Round-off puts the sampled
loop's z = 1 at 1 − 3e-14, and :func:`growth_rate`'s estimate lies 1e-10–1e-9 1/s above the
spectral radius (|s| T ~ 1e-13), while a PID whose integral gain is a thousandth of the
reference's still has its slowest pole at |s| T = 8e-8."""


def held(new, old, alive):
    """(``new`` while every entry of it stays below :data:`_HOLD` and the run is ``alive``,
    else ``old``; whether it is still alive): a diverging state is held at its last value, so
    the reverse pass multiplies the zero cotangents of the samples after the failure by finite
    states, not 0 · ∞ = NaN."""
    alive = alive & jnp.all(jnp.abs(new) < _HOLD)
    return jnp.where(alive, new, old), alive


def growth_rate(Phi, h, squarings: int = 48):
    r"""σ = ln ρ(Φ)/h (1/s): the growth rate of the least stable pole of a loop whose state
    advances by Φ every h seconds, from ‖Φ^N‖^{1/N} → ρ(Φ) at N = 2^48 (Gelfand's formula),
    by repeated squaring with the scale carried in logarithms.  Only matrix products, so it
    runs under jit and vmap (a batched non-symmetric eig has dead-locked XLA:CPU); the error of
    ln ρ is the 1/N-th power of the eigenvector condition, negligible, plus a few ulps.

    Differentiable: X = Φ^N/‖Φ^N‖ (held fixed) spans the dominant eigenspace, and the moments
    s_k = tr(X Φ^k X) = Σ_dominant A_μ μ^k vary to first order as if only the dominant
    eigenvalues μ moved (the cross terms P_λ dΦ P_μ̄ have zero trace).  For one real dominant
    eigenvalue ρ = s₁/s₀; for a complex pair, s₂ − t s₁ + d s₀ = 0 and s₃ − t s₂ + d s₁ = 0
    give d = |μ|² = (s₂² − s₁ s₃)/(s₁² − s₀ s₂).  The derivative of ln ρ/h is that of these
    (first-order exact); the value is the squaring's."""
    P0 = jax.lax.stop_gradient(Phi)
    nrm = jnp.linalg.norm(P0)

    def square(_, carry):
        M, log_s = carry
        M = M @ M
        nrm = jnp.linalg.norm(M)
        return M / nrm, 2.0 * log_s + jnp.log(nrm)

    # a loop, not unrolled: one squaring to compile instead of 48
    M, log_s = jax.lax.fori_loop(0, squarings, square, (P0 / nrm, jnp.log(nrm)))
    value = log_s / (2.0**squarings * h)
    X = jax.lax.stop_gradient(M)
    XP = X @ Phi
    s0 = jnp.trace(X @ X)
    s1 = jnp.trace(XP @ X)
    s2 = jnp.trace(XP @ Phi @ X)
    s3 = jnp.trace(XP @ Phi @ Phi @ X)
    det = s1 * s1 - s0 * s2
    pair = jnp.abs(det) > 1e-9 * (s1 * s1 + jnp.abs(s0 * s2))
    safe_det = jnp.where(pair, det, 1.0)
    d = jnp.abs((s2 * s2 - s1 * s3) / safe_det)
    safe_s0 = jnp.where(pair | (s0 == 0), 1.0, s0)
    r = jnp.abs(jnp.where(pair, 1.0, s1) / safe_s0)
    ln_rho = jnp.where(pair, 0.5 * jnp.log(jnp.where(pair, d, 1.0)),
                       jnp.log(jnp.where(pair, 1.0, r)))
    smooth = ln_rho / h
    return value + (smooth - jax.lax.stop_gradient(smooth))


def lifted_outputs(A, B, C, D, W, K: int = CHUNK):
    r"""Outputs y_k = C s_k + D w_k of s_{k+1} = A s_k + B w_k, s_0 = 0, by the lifted
    (block) recursion: with s_c the state at the start of block c of K samples,

        s_{c+1} = A^K s_c + Σ_{i<K} A^{K−1−i} B w_{cK+i},
        y_{cK+j} = C A^j s_c + Σ_{i<j} C A^{j−1−i} B w_{cK+i} + D w_{cK+j}.

    Only the block states are sequential (n/K steps); the input terms of every block and the
    outputs from the block states are large matrix products.  The same arithmetic as the plain
    recursion, regrouped: on a CPU, a scan of one small matrix–vector product per sample is
    bound by its per-step overhead, and under ``vmap`` over positions by one tiny batched dot
    per position and step.  Returns the outputs (n, n_out) and, per sample, whether its block
    state is finite."""
    n, m = W.shape
    nb = -(-n // K)
    Wp = jnp.concatenate([W, jnp.zeros((nb * K - n, m))]).reshape(nb, K, m)

    def power(P, _):
        return A @ P, P

    AK, powers = jax.lax.scan(power, jnp.eye(A.shape[0]), None, length=K)  # A^K; A^0 … A^{K−1}
    # Input to block state: G = [A^{K−1}B, …, AB, B] (n × K·m).
    G = jnp.einsum("kij,jm->ikm", powers[::-1], B).reshape(A.shape[0], K * m)
    U = Wp.reshape(nb, K * m) @ G.T

    def body(carry, u):
        s, alive = carry
        # a diverging state is held at its last value below _HOLD, never carried to overflow
        return held(AK @ s + u, s, alive), (s, alive)

    _, (S, alive) = jax.lax.scan(body, (jnp.zeros(A.shape[0]), jnp.ones((), bool)), U)
    obs = jnp.einsum("pi,kin->kpn", C, powers)  # (K, p, n): C A^j
    markov = jnp.einsum("kpn,nm->kpm", obs, B)  # C A^k B
    p = C.shape[0]
    # T: (K·p, K·m), block lower triangular, block (j, i) = D (i = j), C A^{j−1−i} B (i < j)
    j, i = jnp.arange(K)[:, None], jnp.arange(K)[None, :]
    blocks = jnp.where((i < j)[:, :, None, None], markov[jnp.clip(j - 1 - i, 0, K - 1)], 0.0)
    blocks = jnp.where((i == j)[:, :, None, None], D, blocks)
    T = blocks.transpose(0, 2, 1, 3).reshape(K * p, K * m)
    Y = jnp.einsum("jon,cn->cjo", obs, S) + (Wp.reshape(nb, K * m) @ T.T).reshape(nb, K, p)
    # a block is good when its start state was reached without a hold
    finite = jnp.repeat(jnp.concatenate([jnp.ones(1, bool), alive[:-1]]), K)[:n]
    return Y.reshape(nb * K, p)[:n], finite


def first_bad(finite, Y, W, bound):
    """Index of the first output sample whose state is non-finite (``finite`` false) or whose
    scale error is beyond ``bound`` (n when none); the outputs from there on are frozen at the
    last good sample, so a diverging run never hands NaN or overflow to the user."""
    n = W.shape[0]
    e = W[:, 0] - Y[:, 1]
    good = jnp.isfinite(e) & (jnp.abs(e) <= bound) & finite & jnp.all(jnp.isfinite(Y), axis=1)
    first = jnp.where(jnp.all(good), n, jnp.argmin(good)).astype(jnp.int32)
    keep = jnp.arange(n, dtype=jnp.int32) < first
    last = jnp.maximum(first - 1, 0)
    Y = jnp.where(jnp.isfinite(Y), Y, 0.0)
    Y = jnp.where(keep[:, None], Y, Y[last][None, :])
    return first, Y
