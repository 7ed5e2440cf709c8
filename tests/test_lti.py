"""The LTI helpers' numerics: the matrix exponential and the small dense solves, against SciPy and
NumPy, with their derivatives against central differences and closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import fdjax  # noqa: F401  (float64)
from fdjax._lti import expm, solve


@pytest.mark.parametrize("scale", [1e-3, 1.0, 10.0, 1e3])
def test_expm_matches_scipy(scale):
    """[13/13] Padé with scaling and squaring (after balancing) against scipy.linalg.expm.
    Measured: 2e-16 relative at ‖A‖ ~ 1, 1.5e-15 at 10, 2e-14 at 1e3 (the squarings' round-off
    grows with their number); tolerance 1e-13."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((12, 12)) * scale / np.sqrt(12)
    A -= (np.max(np.linalg.eigvals(A).real) + scale) * np.eye(12)  # stable: no overflow at 1e3
    E, ref = np.asarray(expm(jnp.asarray(A))), scipy.linalg.expm(A)
    assert np.max(np.abs(E - ref)) <= 1e-13 * np.max(np.abs(ref))


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
