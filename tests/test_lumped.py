"""Lumped models and the paper's 3M2S example (Sec. 2, Figs. 1–3)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import fdjax
from fdjax import LumpedModel


def _numpy_frf(model, freq_hz):
    w = 2 * np.pi * np.asarray(freq_hz)[:, None, None]
    M, K, C = (np.asarray(x) for x in (model.mass, model.stiffness, model.damping))
    return np.linalg.inv(K - w**2 * M + 1j * w * C)


def test_three_mass_resonances_match_paper():
    model = fdjax.three_mass()
    f, _ = model.modes()
    # independent oracle: scipy's generalized symmetric eigensolver
    lam = scipy.linalg.eigh(np.asarray(model.stiffness), np.asarray(model.mass), eigvals_only=True)
    f_ref = np.sqrt(np.clip(lam, 0, None)) / (2 * np.pi)
    np.testing.assert_allclose(np.asarray(f)[1:], f_ref[1:], rtol=1e-12)
    assert abs(float(f[0])) < 1e-3  # rigid-body mode
    # the paper quotes "104 Hz" and "155 Hz" (rounded to the nearest Hz)
    assert abs(float(f[1]) - 104.0) < 0.5 and abs(float(f[2]) - 155.0) < 0.6


def test_three_mass_frf_matches_numpy_inverse():
    model = fdjax.three_mass()
    freq = np.linspace(1.0, 400.0, 2001)
    H = np.asarray(model.frf(freq))
    np.testing.assert_allclose(H, _numpy_frf(model, freq), rtol=1e-11, atol=0)


def test_three_mass_modal_expansion():
    # C = 2e-5 K exactly (c1/k1 = c2/k2), so the damping is proportional and the receptance
    # is the modal sum Σ φφᵀ/(ω_r² − ω² + iω·β ω_r²) plus the rigid-body term φ0φ0ᵀ/(−ω²).
    model = fdjax.three_mass()
    f, phi = (np.asarray(x) for x in model.modes())
    wr = 2 * np.pi * f
    beta = 2e-5
    freq = np.linspace(5.0, 300.0, 501)
    w = 2 * np.pi * freq
    H = np.zeros((freq.size, 3, 3), complex)
    for r in range(3):
        den = -(w**2) if r == 0 else wr[r] ** 2 - w**2 + 1j * w * beta * wr[r] ** 2
        H += np.einsum("i,j->ij", phi[:, r], phi[:, r])[None] / den[:, None, None]
    np.testing.assert_allclose(np.asarray(model.frf(freq)), H, rtol=1e-9)


def test_three_mass_sign_pattern_f1_x3():
    """Pair F1–x3: mode 1 (104 Hz) is out of phase with the rigid-body motion, mode 2 in phase."""
    model = fdjax.three_mass()
    f, phi = (np.asarray(x) for x in model.modes())
    modal_constant = phi[2, :] * phi[0, :]  # x3/F1 residue of each mode
    assert modal_constant[0] > 0  # rigid body
    assert modal_constant[1] < 0  # 104 Hz: opposite sign → out of phase
    assert modal_constant[2] > 0  # 155 Hz: same sign → in phase
    # seen on the FRF itself: at resonance an in-phase term is −i·|A|/(2ζω²) (Im < 0);
    # the collocated h11 is in phase for every mode.
    H = np.asarray(model.frf(f[1:]))
    assert np.all(H[:, 0, 0].imag < 0)
    assert H[0, 2, 0].imag > 0 and H[1, 2, 0].imag < 0
    # and the rigid-body term −1/(Mω²) has the in-phase sign far below the first mode
    assert np.asarray(model.frf(np.array([1.0])))[0, 2, 0].real < 0


def test_grad_of_frf_magnitude_matches_finite_differences():
    def mag(k1):
        m = fdjax.chain_model([100.0, 150.0, 50.0], jnp.stack([k1, jnp.asarray(2e7)]), [1e3, 4e2])
        return jnp.abs(m.receptance(2 * jnp.pi * 90.0)[2, 0]) * 1e9

    k1 = jnp.asarray(5e7)
    g = jax.grad(mag)(k1)
    h = 1e-5 * 5e7  # ≈ eps^(1/3) · scale for a central difference
    fd = (mag(k1 + h) - mag(k1 - h)) / (2 * h)
    np.testing.assert_allclose(float(g), float(fd), rtol=5e-9)  # measured 4e-10


def test_vmap_over_models_equals_loop():
    ks = jnp.linspace(3e7, 7e7, 5)
    make = lambda k: fdjax.chain_model([100.0, 150.0, 50.0], jnp.stack([k, k / 2.5]), [1e3, 4e2])
    w = 2 * jnp.pi * jnp.linspace(10.0, 300.0, 64)
    batched = jax.vmap(lambda k: make(k).receptance(w))(ks)
    looped = jnp.stack([make(k).receptance(w) for k in ks])
    np.testing.assert_allclose(np.asarray(batched), np.asarray(looped), rtol=1e-13)


def test_frf_does_not_retrace():
    model = fdjax.three_mass()

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def f(m, w):
        return m.receptance(w)

    w = jnp.linspace(1.0, 2.0, 8)
    f(model, w)
    f(eqx.tree_at(lambda m: m.stiffness, model, model.stiffness * 1.1), w * 2)


def test_a_non_symmetric_matrix_is_refused_under_jit_too():
    """The FRF mirrors its upper triangle (reciprocity): a non-symmetric stiffness built inside
    jit, where the constructor cannot see its values, is refused there, not answered with the
    receptance of another model (a third of the true h21 here)."""
    M = np.eye(2)
    K = np.array([[2e4, -1e4], [-3e4, 3e4]])
    C = 0.01 * np.array([[2e4, -1e4], [-1e4, 3e4]])  # symmetric
    f = np.array([10.0, 20.0])
    run = eqx.filter_jit(lambda k: LumpedModel(M, k, C).frf(f))
    with pytest.raises(eqx.EquinoxRuntimeError, match=r"`LumpedModel\(stiffness=\.\.\.\)` must be "
                                                      r"symmetric"):
        jax.block_until_ready(run(K))
    Ks = np.array([[2e4, -1e4], [-1e4, 3e4]])
    np.testing.assert_allclose(run(Ks), LumpedModel(M, Ks, C).frf(f), rtol=1e-14)


def test_modes_of_a_free_model_differentiate_and_a_traced_bad_mass_is_named():
    """The rigid-body mode (ω² = 0 up to round-off) gives the natural frequencies a finite
    gradient (it was NaN: √ differentiated at 0), equal to central differences (h = 1e3 N/m on
    k ~ 1e7, measured 3e-10 relative); a mass matrix that is not positive definite is named
    under jit, where construction cannot check it; a model without degrees of freedom, or a
    scalar mass, is refused."""
    from jit_errors import CHECK_FAILED

    def total(k):
        return fdjax.chain_model([100.0, 150.0, 50.0], k, [1e3, 4e2]).modes()[0].sum()

    k = np.array([5e7, 2e7])
    g = np.asarray(jax.grad(total)(jnp.asarray(k)))
    h = 1e3
    fd = [(float(total(k + e)) - float(total(k - e))) / (2 * h) for e in h * np.eye(2)]
    np.testing.assert_allclose(g, fd, rtol=5e-9)  # measured 5.6e-11 and 3.0e-10
    assert float(fdjax.three_mass().modes()[0][0]) == 0.0
    eye = jnp.eye(2)
    with pytest.raises(CHECK_FAILED, match=r"`LumpedModel\.modes\(\)` must be computed from a "
                                           r"symmetric positive definite mass matrix"):
        eqx.filter_jit(lambda M: LumpedModel(M, eye, 0 * eye).modes()[0])(-eye)
    for bad in (1.0, np.zeros((0, 0))):
        with pytest.raises(ValueError, match=r"`LumpedModel\(mass=\.\.\.\)` must be a square "
                                             r"matrix \(n, n\) with n ≥ 1"):
            LumpedModel(bad, bad, bad)
    with pytest.raises(ValueError, match=r"`chain_model\(masses=\.\.\.\)` must hold at least one"):
        fdjax.chain_model([], [], [])


def test_symmetry_and_passivity_are_checked_eagerly_and_under_jit():
    """Matrices that are not symmetric, or a stiffness or damping with a negative eigenvalue
    (a divergent mode, an active damper) are refused: eagerly by the constructor, and under
    jit where they are used.  Under jit an asymmetric mass had given the FRF of its mirrored
    upper triangle (h21 1.706e-5 − 2.084e-5j against numpy's 1.626e-5 − 1.699e-5j), an
    asymmetric stiffness wrong modes (8.92/28.41 Hz against scipy's 11.25/27.57 Hz), and a
    negative stiffness eigenvalue a 0 Hz 'rigid-body' mode."""
    from jit_errors import CHECK_FAILED

    eye = np.eye(2)
    K = np.array([[2e4, -1e4], [-1e4, 3e4]])
    f = np.array([10.0, 20.0])
    cases = [  # (M, K, C, the matrix named)
        (np.array([[1.0, 0.5], [0.0, 1.0]]), K, 0.01 * K, "mass"),
        (eye, np.array([[2e4, -1e4], [-3e4, 3e4]]), 0.01 * K, "stiffness"),
        (eye + 9e-6 * np.array([[0.0, 1.0], [0.0, 0.0]]), K, 0.01 * K, "mass"),  # 1e-12 max|M|
    ]
    for M, Kb, C, name in cases:
        with pytest.raises(ValueError, match=rf"`LumpedModel\({name}=\.\.\.\)` must be "
                                             r"symmetric \(a reciprocal structure\), got max"):
            LumpedModel(M, Kb, C)
        pattern = rf"`LumpedModel\({name}=\.\.\.\)` must be symmetric"
        with pytest.raises(CHECK_FAILED, match=pattern):
            jax.block_until_ready(eqx.filter_jit(lambda m, k, c: LumpedModel(m, k, c).frf(f))(
                M, Kb, C))
        with pytest.raises(CHECK_FAILED, match=pattern):
            jax.block_until_ready(eqx.filter_jit(lambda m, k: LumpedModel(m, k, 0 * k).modes())(
                M, Kb))
    with pytest.raises(ValueError, match=r"`LumpedModel\(stiffness=\.\.\.\)` must be positive "
                                         r"semi-definite \(a passive structure\), got "
                                         r"eigenvalues \[-10000\.,  10000\.\]"):
        LumpedModel(eye, np.diag([1e4, -1e4]), 0 * eye)
    with pytest.raises(ValueError, match=r"`LumpedModel\(damping=\.\.\.\)` must be positive "
                                         r"semi-definite"):
        LumpedModel(eye, K, -eye)
    with pytest.raises(CHECK_FAILED, match=r"`LumpedModel\.modes\(\)` must be computed from a "
                                           r"positive semi-definite stiffness matrix"):
        jax.block_until_ready(eqx.filter_jit(lambda k: LumpedModel(eye, k, 0 * k).modes())(
            np.diag([1e4, -1e4])))
    # and the FRF under jit (it returned finite receptances of these models)
    frf = eqx.filter_jit(lambda m, k, c: LumpedModel(m, k, c).frf(f))
    for args, pattern in (((eye, K, -eye), r"`LumpedModel\(damping=\.\.\.\)` must be positive "
                                           r"semi-definite"),
                          ((eye, np.diag([1e4, -1e4]), 0 * eye),
                           r"`LumpedModel\(stiffness=\.\.\.\)` must be positive semi-definite"),
                          ((np.diag([1.0, -1.0]), K, 0 * eye),
                           r"`LumpedModel\(mass=\.\.\.\)` must be positive definite")):
        with pytest.raises(CHECK_FAILED, match=pattern):
            jax.block_until_ready(frf(*args))
    # symmetry is judged against the largest entry: a transformed matrix whose small
    # off-diagonal entry differs from its mirror by 1e-11 of itself (1e-14 absolute) is
    # accepted, eagerly as under jit
    M = np.array([[2.0, 1e-3 * (1 + 1e-11)], [1e-3, 2.0]])
    np.testing.assert_allclose(frf(M, K, 0.01 * K), LumpedModel(M, K, 0.01 * K).frf(f),
                               rtol=1e-13)
    # the free chain's rigid-body eigenvalue (round-off either side of 0) stays accepted
    assert float(fdjax.three_mass().modes()[0][0]) == 0.0
    np.testing.assert_allclose(eqx.filter_jit(lambda k: LumpedModel(eye, k, 0 * k).modes()[0])(K),
                               np.sqrt(scipy.linalg.eigh(K, eye, eigvals_only=True)) / (2 * np.pi),
                               rtol=1e-14)


def test_dampers_to_ground_enter_the_chain():
    """``chain_model(mass_dampings=...)`` adds c_g,i to C's diagonal: the FRF equals numpy's
    inverse of K − ω²M + iω(C + diag(c_g)), and differs from the chain without them (by 4 % of
    the largest receptance, measured)."""
    m, k, c, cg = [100.0, 150.0, 50.0], [5e7, 2e7], [1e3, 4e2], [0.0, 5e3, 0.0]
    f = np.array([50.0, 103.7, 154.5, 300.0])
    H = np.asarray(fdjax.chain_model(m, k, c, cg).frf(f))
    K = np.array([[5e7, -5e7, 0], [-5e7, 7e7, -2e7], [0, -2e7, 2e7]])
    C = np.array([[1e3, -1e3, 0], [-1e3, 1.4e3, -4e2], [0, -4e2, 4e2]]) + np.diag(cg)
    w = 2 * np.pi * f[:, None, None]
    ref = np.linalg.inv(K - w**2 * np.diag(m) + 1j * w * C)
    np.testing.assert_allclose(H, ref, rtol=1e-12)
    assert np.max(np.abs(H - np.asarray(fdjax.chain_model(m, k, c).frf(f)))) > 0.02 * np.max(
        np.abs(H))
