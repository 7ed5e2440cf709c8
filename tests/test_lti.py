"""The LTI helpers' numerics: the matrix exponential and the small dense solves, against SciPy and
NumPy, with their derivatives against central differences and closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import fdjax  # noqa: F401  (float64)
from fdjax._lti import expm, solve


def _expm_decimal(A: np.ndarray, digits: int = 60) -> np.ndarray:
    """exp(A) in 60-digit decimal arithmetic: Taylor's series of A/2^s (‖A/2^s‖₁ ≤ 1/4, 40
    terms: remainder < 1e-60), squared s times; a reference free of double round-off."""
    from decimal import Decimal, localcontext

    with localcontext() as ctx:
        ctx.prec = digits
        n = A.shape[0]
        s = max(0, int(np.ceil(np.log2(np.abs(A).sum(0).max() / 0.25))))
        M = [[Decimal(float(x)) / (Decimal(2) ** s) for x in row] for row in A]

        def mul(X, Y):
            return [[sum(X[i][k] * Y[k][j] for k in range(n)) for j in range(n)]
                    for i in range(n)]

        E = [[Decimal(int(i == j)) for j in range(n)] for i in range(n)]
        T = [row[:] for row in E]
        for k in range(1, 41):
            T = [[x / k for x in row] for row in mul(T, M)]
            E = [[e + t for e, t in zip(re, rt)] for re, rt in zip(E, T)]
        for _ in range(s):
            E = mul(E, E)
        return np.array([[float(x) for x in row] for row in E])


@pytest.mark.parametrize("scale", [1e-3, 1.0, 10.0, 1e3])
def test_expm_matches_an_exact_reference(scale):
    """[13/13] Padé with scaling and squaring (after balancing) against exp(A) computed in
    60-digit arithmetic, for a random 12×12 A shifted so that its rightmost eigenvalue is −1
    (the response decays but stays of order one: no underflow to a trivial zero).
    Measured: ≤ 1e-15 of the largest entry up to ‖A‖ ~ 40, and at ‖A‖₁ ~ 4e3 1.7e-11 with
    XLA's default compilation, 1.8e-10 with the suite's (LLVM's optimisations off; the
    squarings' round-off grows with their number; scipy.linalg.expm is off by 6.7e-11 there).
    Tolerances 1e-13, and 3e-10 at 1e3; SciPy as a second oracle within its own error."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((12, 12)) * scale / np.sqrt(12)
    A -= (np.max(np.linalg.eigvals(A).real) + 1.0) * np.eye(12)
    E, ref = np.asarray(expm(jnp.asarray(A))), _expm_decimal(A)
    size = np.max(np.abs(ref))
    assert size > 1e-3  # not an underflowed comparison
    assert np.max(np.abs(E - ref)) <= (3e-10 if scale > 100 else 1e-13) * size
    assert np.max(np.abs(scipy.linalg.expm(A) - ref)) <= 1e-10 * size


def test_expm_gradient_matches_central_differences():
    rng = np.random.default_rng(1)
    A = jnp.asarray(rng.standard_normal((6, 6)))
    f = lambda a: jnp.sum(expm(a) ** 2)
    g = np.asarray(jax.grad(f)(A))
    h = 1e-6
    for i, j in [(1, 2), (0, 0), (5, 3)]:
        e = np.zeros((6, 6))
        e[i, j] = h
        fd = (float(f(A + e)) - float(f(A - e))) / (2 * h)
        # truncation O(h²) ~ 1e-12, round-off ~ 1e-16·f/h ~ 1e-8 relative
        assert abs(g[i, j] - fd) <= 1e-7 * abs(fd), (i, j, g[i, j], fd)


def test_solve_and_its_derivatives_match_numpy():
    """Batched complex solves against numpy; the first and second derivatives of
    C(zI − A)⁻¹B in z against the closed forms −C R²B and 2 C R³B (R = (zI − A)⁻¹)."""
    rng = np.random.default_rng(2)
    M = rng.standard_normal((4, 7, 7)) + 1j * rng.standard_normal((4, 7, 7))
    R = rng.standard_normal((4, 7, 3)) + 0j
    X = np.asarray(solve(jnp.asarray(M), jnp.asarray(R)))
    np.testing.assert_allclose(X, np.linalg.solve(M, R), rtol=0, atol=1e-13 * np.abs(X).max())
    A = jnp.asarray(rng.standard_normal((6, 6)))
    B, C = jnp.asarray(rng.standard_normal((6, 2))), jnp.asarray(rng.standard_normal((3, 6)))
    G = lambda z: C.astype(complex) @ solve(z * jnp.eye(6, dtype=complex) - A.astype(complex),
                                              B.astype(complex))
    z = jnp.asarray(0.4 + 1.3j)
    d1 = jax.jvp(G, (z,), (jnp.ones_like(z),))[1]
    d2 = jax.jvp(lambda x: jax.jvp(G, (x,), (jnp.ones_like(x),))[1], (z,), (jnp.ones_like(z),))[1]
    Rz = np.linalg.inv(complex(z) * np.eye(6) - np.asarray(A))
    Cn, Bn = np.asarray(C), np.asarray(B)
    np.testing.assert_allclose(d1, -Cn @ Rz @ Rz @ Bn, rtol=1e-12)
    np.testing.assert_allclose(d2, 2 * Cn @ Rz @ Rz @ Rz @ Bn, rtol=1e-12)


def test_transfer_either_side_and_its_hessian_match_numpy():
    """C(zI − A)⁻¹B + D solved against B (more outputs) or against Cᵀ (fewer outputs) equals
    numpy's; the gradient and the Hessian of f(A) = Σ_z |G(z)|² (reverse mode, and forward over
    reverse, both through the closed-form derivative of the solve) match numpy central
    differences: the gradient along 5 random directions (h = 1e-6, measured ≤ 6.4e-10
    relative, bound 2e-9), vᵀHv along 3 (second differences, h = 1e-4, whose truncation and
    round-off give the measured ≤ 6.7e-7 relative, bound 2e-6)."""
    from fdjax._lti import transfer

    rng = np.random.default_rng(5)
    n = 6
    A0 = rng.standard_normal((n, n)) * 0.4
    B, D = rng.standard_normal((n, 5)), rng.standard_normal((1, 5))
    C = rng.standard_normal((1, n))
    z = np.exp(1j * np.linspace(0.1, 3.0, 7))

    def g_np(A, B, C, D):
        return np.stack([C @ np.linalg.solve(zk * np.eye(n) - A, B) + D for zk in z])

    for (b, c, d) in ((B, C, D), (C.T, B.T, D.T)):  # 1 × 5 (against Cᵀ) and 5 × 1 (against B)
        G = np.asarray(transfer(jnp.asarray(A0), jnp.asarray(b), jnp.asarray(c),
                                jnp.asarray(d), jnp.asarray(z)))
        np.testing.assert_allclose(G, g_np(A0, b, c, d), rtol=1e-12, atol=0)

        def f_np(A):
            return float(np.sum(np.abs(g_np(A, b, c, d)) ** 2))

        def f(A):
            return jnp.sum(jnp.abs(transfer(A, jnp.asarray(b), jnp.asarray(c), jnp.asarray(d),
                                            jnp.asarray(z))) ** 2)

        grad = np.asarray(jax.jit(jax.grad(f))(jnp.asarray(A0)))
        hess = np.asarray(jax.jit(jax.jacfwd(jax.grad(f)))(jnp.asarray(A0))).reshape(n * n, n * n)
        np.testing.assert_allclose(hess, hess.T, rtol=0, atol=1e-12 * np.abs(hess).max())
        for _ in range(5):
            V = rng.standard_normal((n, n))
            h = 1e-6
            fd = (f_np(A0 + h * V) - f_np(A0 - h * V)) / (2 * h)
            assert abs(np.sum(grad * V) - fd) <= 2e-9 * abs(fd)
        for _ in range(3):
            V = rng.standard_normal((n, n))
            h = 1e-4
            fd2 = (f_np(A0 + h * V) - 2 * f_np(A0) + f_np(A0 - h * V)) / h ** 2
            vhv = V.ravel() @ hess @ V.ravel()
            assert abs(vhv - fd2) <= 2e-6 * abs(fd2), (vhv, fd2)


def test_hessenberg_frequency_response_matches_numpy_on_the_sampled_plant():
    """The Hessenberg reduction is a similarity (A = Q H Qᵀ, Q orthogonal, H zero below the
    subdiagonal) and :func:`transfer_hessenberg` equals numpy's dense solves on the
    zero-order-hold twin of the reference drive (12 states, entries 2e-9 … 1.4e4) at 400
    frequencies 5 Hz – 3.9 kHz, and on a random system: the error is round-off relative to
    the balanced matrix, measured ≤ 2e-11 of each channel's largest response (bound 1e-10);
    its derivative in the frequency (what the margin refinement takes) equals the dense
    solve's to 1e-9 of its largest value (measured 3.4e-10)."""
    from fdjax._drive._twin import TwinOptions, state_space
    from fdjax._lti import hessenberg, transfer, transfer_hessenberg, zoh

    rng = np.random.default_rng(7)
    A = rng.standard_normal((9, 9))
    H, Q = hessenberg(jnp.asarray(A))
    H, Q = np.asarray(H), np.asarray(Q)
    np.testing.assert_allclose(Q @ H @ Q.T, A, rtol=0, atol=1e-13 * np.abs(A).max())
    np.testing.assert_allclose(Q.T @ Q, np.eye(9), rtol=0, atol=1e-14)
    assert np.all(np.tril(H, -2) == 0)

    p = state_space(fdjax.reference_drive(), 0.4, twin=TwinOptions(kept_modes=6))
    Phi, Gam = zoh(p.A, p.B[:, :1], 1.25e-4)
    z = np.exp(2j * np.pi * np.geomspace(5.0, 3900.0, 400) * 1.25e-4)
    cases = [(Phi, Gam, p.C[:2], p.D[:2, :1], z),
             (A * 0.3, rng.standard_normal((9, 2)), rng.standard_normal((3, 9)),
              rng.standard_normal((3, 2)), np.exp(1j * np.linspace(0.05, 3.0, 50)))]
    for (a, b, c, d, x) in cases:
        a, b, c, d = (np.asarray(v) for v in (a, b, c, d))
        G = np.asarray(transfer_hessenberg(jnp.asarray(a), jnp.asarray(b), jnp.asarray(c),
                                           jnp.asarray(d), jnp.asarray(x)))
        ref = np.stack([c @ np.linalg.solve(xk * np.eye(a.shape[0]) - a, b) + d for xk in x])
        scale = np.abs(ref).max(axis=0)
        assert np.max(np.abs(G - ref) / scale) <= 1e-10
    w = jnp.asarray([0.3, 1.1])

    def dG(fn):
        def G(v):
            return fn(Phi, Gam, p.C[:2], p.D[:2, :1], jnp.exp(v.astype(jnp.complex128) * 1j))

        return jax.jvp(G, (w,), (jnp.ones(2),))[1]

    d_h, d_dense = np.asarray(dG(transfer_hessenberg)), np.asarray(dG(transfer))
    assert np.max(np.abs(d_h - d_dense)) <= 1e-9 * np.max(np.abs(d_dense))


def test_frf_of_one_system_below_its_nyquist_frequency():
    """LTI.frf takes one system (a batch is named, with what to do) and, for a discrete one,
    frequencies up to its Nyquist frequency: above it z = e^{i2πfT} aliases (1100 Hz at
    T = 1 ms is 100 Hz), which a grid given in rad/s would do silently."""
    from fdjax._lti import LTI

    one = LTI(jnp.array([[0.5]]), jnp.array([[1.0]]), jnp.array([[1.0]]), jnp.array([[0.0]]),
              dt=jnp.asarray(1e-3))
    f = np.array([100.0, 500.0])
    z = np.exp(2j * np.pi * f * 1e-3)
    np.testing.assert_allclose(np.asarray(one.frf(f))[:, 0, 0], 1 / (z - 0.5), rtol=1e-14)
    with pytest.raises(ValueError, match=r"`LTI\.frf\(freq_hz=\.\.\.\)` must be at most the "
                                         r"Nyquist frequency 500 Hz of the sample period 0\.001 s "
                                         r"\(3141\.59 rad/s: the grid is in Hz\), got 1100"):
        one.frf(np.array([100.0, 1100.0]))
    batch = LTI(*(jnp.ones((2, 1, 1)) for _ in range(4)))
    for call in (lambda: batch.frf(f), lambda: batch.transfer(1j)):
        with pytest.raises(ValueError, match=r"needs one system \(A of shape \(n, n\)\), got a "
                                             r"batch \(A of shape \(2, 1, 1\)\): jax\.vmap"):
            call()
    # vmapped, each system is one
    out = jax.vmap(lambda s: s.transfer(jnp.asarray(2.0 + 0j)))(batch)
    np.testing.assert_allclose(np.asarray(out)[:, 0, 0], [2.0, 2.0], rtol=1e-15)
