"""The optional second sliding body (`fdjax.Table`) on the carriage.

Oracles, independent of the closed form in ``Carriage._receptance`` (which works in the relative
coordinates (x_c, ψ, δ)): the direct assembly ``frf_direct`` over (…, x_c, ψ, x_t); NumPy solves
of the carriage's 3-DOF dynamic stiffness; a rigid carriage of mass m + m_t (the stiff-table
limit); the finite-element twin and its mesh convergence; central finite differences.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jit_errors import CHECK_FAILED
from test_drive import check_rigid_asymptote  # rigid-body asymptote, independent J and c
from test_statespace import normwise_error  # ‖H − H_ref‖₂/‖H_ref‖₂ in consistent units

import fdjax
from fdjax._drive._twin import _rigid_mode

POS = np.array([0.1, 0.25, 0.4, 0.55, 0.7])
FREQ = np.geomspace(5.0, 3000.0, 400)

# The X table with its workpiece: 400 kg on the saddle, tuned to 95 Hz with the saddle held,
# k_t = m_t (2π·95 Hz)², and ζ = c_t / (2√(k_t m_t)) = 0.15.  (With the saddle free the reduced
# mass m_t M/(m_t + M) is within 2 % of m_t: the drive reflects M ≈ 2e4 kg to the saddle.  On the
# reference drive, whose own 95 Hz mode sits at the same frequency, the two veer apart to 90
# and 129 Hz.)
M_T = 400.0
K_T = M_T * (2 * np.pi * 95.0) ** 2
C_T = 2 * 0.15 * np.sqrt(K_T * M_T)
H_T = 0.1


def with_table(drive, table):
    return eqx.tree_at(lambda d: d.carriage.table, drive, table, is_leaf=lambda x: x is None)


@pytest.fixture(scope="module")
def plain():
    return fdjax.table1_drive()


@pytest.fixture(scope="module")
def drive(plain):
    return with_table(plain, fdjax.Table(mass=M_T, stiffness=K_T, damping=C_T, height=H_T))


@pytest.fixture(scope="module")
def H(drive):
    return np.asarray(drive.frf(POS, FREQ))


def carriage_oracle(c, omega):
    """NumPy: the carriage's receptance over (x_n, x2, x3) from its dynamic stiffness over
    (x_c, ψ, x_t) (the table's connection b = (−1, −h_t, 1)) and the points on saddle and table."""
    t = c.table
    m, J, kp = float(c.mass), float(c.pitch_inertia), float(c.pitch_stiffness)
    cx, cp = float(c.axial_damping), float(c.pitch_damping)
    mt, kt, ct, ht = float(t.mass), float(t.stiffness), float(t.damping), float(t.height)
    hn, hs, h3 = float(c.nut_height), float(c.scale_height), float(c.tool_height)
    b = np.array([-1.0, -ht, 1.0])
    P = np.array([[1.0, hn, 0.0], [1.0, hs, 0.0], [0.0, h3 - ht, 1.0]])
    out = []
    for w in omega:
        D = np.diag([-w * w * m + 1j * w * cx, kp - w * w * J + 1j * w * cp, -w * w * mt])
        D = D + (kt + 1j * w * ct) * np.outer(b, b)
        out.append(P @ np.linalg.solve(D, P.T))
    return np.stack(out)


# ------------------------------------------------------------------------------------ tests
def test_coupled_equals_direct_assembly(drive, H):
    """LM-FBS on the closed-form carriage receptance equals the 10-DOF direct assembly.

    Both are exact; the difference is the round-off of the direct solve, ≈ eps·cond(D) of the
    largest response.  Measured: 8.9e-12 normwise; entrywise ≤ 4.3e-11, except θ1/F3 at 3 kHz
    (2.8e-10 with XLA's fusion emitters, 6.7e-10 with the classic ones the tests compile with),
    where that entry is 1e-12 of its own peak (the reference drive without a table shows the
    same there, 2.9e-9)."""
    Hd = np.asarray(drive.frf_direct(POS, FREQ))
    assert normwise_error(H, Hd, drive).max() < 2e-11
    np.testing.assert_allclose(H, Hd, rtol=1e-9, atol=0)


def test_reciprocity_and_a_new_mode(drive, plain, H):
    """The force F3 acts where x3 is read (on the table): θ1/F3 = x3/T1 (Maxwell–Betti); the
    table adds exactly one mode below 4 kHz to the twin (10 against 9, rigid body included)."""
    np.testing.assert_allclose(H[..., 0, 1], H[..., 2, 0], rtol=1e-14)  # measured 6.5e-16
    assert fdjax.count_modes(drive) == fdjax.count_modes(plain) + 1


def test_carriage_receptance_against_numpy(drive):
    """Closed form in (x_c, ψ, δ) against a NumPy solve over (x_c, ψ, x_t): two round-off
    paths of the same 3×3 system, measured 1.9e-14 to 2.2e-14 entrywise over 5 Hz–3 kHz."""
    c = drive.carriage
    omega = 2 * np.pi * FREQ
    Y = np.asarray(fdjax._linalg.from_entries(c.receptance(omega)))
    np.testing.assert_allclose(Y, carriage_oracle(c, omega), rtol=1e-13, atol=0)


def test_stiff_table_is_one_rigid_body(plain):
    """k_t → ∞: the table rides rigidly on the saddle.

    At h_t = 0 that is a carriage of mass m + m_t (the tool point x_t + h_3 ψ → x_c + h_3 ψ).
    The physical difference is O(ω²m_t/k_t) = 4e-9 at 500 Hz for k_t = 1e18 N/m, raised by the
    drive's modal amplification to 3.5e-8 measured (θ1/F3; ≤ 1.5e-9 on the other entries);
    the closed form forms no difference of large numbers (the direct 10×10 solve, with 1e18
    on its diagonal, loses 1e-5 … 2e-2 here).  At h_t = 0.1 m the rigid body has the mass
    matrix [[m + m_t, m_t h_t], [m_t h_t, J + m_t h_t²]] (NumPy), which a Carriage without
    table cannot represent."""
    f = np.geomspace(5.0, 500.0, 100)
    stiff = with_table(plain, fdjax.Table(mass=M_T, stiffness=1e18))
    merged = eqx.tree_at(lambda d: d.carriage.mass, plain, plain.carriage.mass + M_T)
    np.testing.assert_allclose(np.asarray(stiff.frf(POS, f)), np.asarray(merged.frf(POS, f)),
                               rtol=1e-7, atol=0)

    c = eqx.tree_at(lambda c: c.table, plain.carriage,
                    fdjax.Table(mass=M_T, stiffness=1e18, height=H_T), is_leaf=lambda x: x is None)
    w = 2 * np.pi * f
    m, J, kp = float(c.mass), float(c.pitch_inertia), float(c.pitch_stiffness)
    cx, cp = float(c.axial_damping), float(c.pitch_damping)
    Mr = np.array([[m + M_T, M_T * H_T], [M_T * H_T, J + M_T * H_T**2]])
    P = np.array([[1.0, float(h)] for h in (c.nut_height, c.scale_height, c.tool_height)])
    ref = np.stack([P @ np.linalg.solve(np.diag([1j * wk * cx, kp + 1j * wk * cp])
                                        - wk * wk * Mr, P.T) for wk in w])
    Y = np.asarray(fdjax._linalg.from_entries(c.receptance(w)))
    # O(ω²m_t/k_t) ≤ 4e-9 again, amplified near the carriage's antiresonances (measured 3.6e-8)
    np.testing.assert_allclose(Y, ref, rtol=1e-7, atol=0)


def test_fe_twin_converges(drive):
    """The damped FE receptance with the table converges to the exact drive.frf at O(h²)
    (mirrors tests/test_statespace.py::test_frf_converges; the table is lumped, exact in both).
    At Y = 0.6 m the nut sits mid-element for n = 18, 54, 162; measured slopes 1.995–1.999."""
    f = np.array([30.0, 70.0, 120.0, 1000.0])  # around the first modes (39, 90, 129, 132 Hz)
    H_ref = np.asarray(drive.frf(0.6, f))[0]
    w = 2 * np.pi * f
    meshes = np.array([18, 54, 162])
    errors = []
    for n in meshes:
        fe = fdjax.fe_matrices(drive, 0.6, twin=fdjax.TwinOptions(n_elements=int(n)))
        M, C, K, F, S = (np.asarray(x) for x in (
            fe.mass, fe.damping, fe.stiffness, fe.inputs, fe.outputs))
        assert M.shape == (2 * n + 6, 2 * n + 6)
        H = np.stack([S @ np.linalg.solve(K + 1j * wk * C - wk**2 * M, F) for wk in w])
        errors.append(normwise_error(H, H_ref, drive))
    errors = np.array(errors)
    for j in range(f.size):
        p = np.polyfit(np.log(1.0 / meshes), np.log(errors[:, j]), 1)[0]
        assert abs(p - 2.0) < 0.1, (f[j], p, errors[:, j])
    assert errors[-1].max() < 2e-6  # measured 9.6e-7 at 1 kHz


def test_twin_rigid_mode_and_state_space(drive):
    """The rigid-body mode (x_t = x_c = i_sc θ) is K's null vector; the default state space
    follows the exact FRF (1e-4 normwise at these frequencies off resonance, measured 9e-5;
    the budget of tests/test_statespace.py allows 1 %)."""
    n = fdjax.DEFAULT_ELEMENTS
    fe = fdjax.fe_matrices(drive, 0.4)
    K, r = np.asarray(fe.stiffness), np.asarray(_rigid_mode(drive, n))
    assert np.linalg.norm(K @ r) < 1e-13 * np.linalg.norm(K) * np.linalg.norm(r)
    ss = fdjax.state_space(drive, 0.4)
    f = np.array([30.0, 70.0, 500.0, 1000.0])
    err = normwise_error(np.asarray(ss.frf(f)), np.asarray(drive.frf(0.4, f))[0], drive)
    assert err.max() < 1e-4, err


def test_rigid_body_asymptote(drive, plain):
    """Far below the first mode x2/T1 = i_sc / (−ω²J + iωc) with J including m_t i_sc² and c
    unchanged (the table's damper is internal); four low modes (39, 90, 129, 132 Hz)."""
    assert float(drive.reflected_damping()) == float(plain.reflected_damping())
    check_rigid_asymptote(drive, n_low_modes=4, first_mode_hz=38.7)


def test_grad_matches_finite_differences(drive):
    """d|h21|/dk_t at 120 Hz (near the table mode) by jax.grad against central differences.

    Step √eps·k_t: truncation (h/k_t)² ~ eps and round-off eps/√eps = 1.5e-8, relative."""
    omega = 2 * np.pi * 120.0

    def mag(k):
        d = eqx.tree_at(lambda d: d.carriage.table.stiffness, drive, k)
        return jnp.abs(d.receptance(0.4, omega)[1, 0])

    k = jnp.asarray(K_T)
    g = jax.jit(jax.grad(mag))(k)
    h = np.sqrt(np.finfo(float).eps) * K_T
    fd = (mag(k + h) - mag(k - h)) / (2 * h)
    assert abs(float(fd)) > 0
    np.testing.assert_allclose(float(g), float(fd), rtol=5e-8)  # measured 1.2e-8


def test_vmap_and_jit(drive):
    """vmap over table stiffnesses equals a loop; a jitted FRF compiles once for new values."""
    ks = jnp.asarray([0.5, 1.0, 2.0]) * K_T
    omega = 2 * np.pi * np.array([50.0, 120.0, 800.0])

    def rec(k):
        return eqx.tree_at(lambda d: d.carriage.table.stiffness, drive, k).receptance(0.4, omega)

    batched = np.asarray(jax.vmap(rec)(ks))
    looped = np.stack([np.asarray(rec(k)) for k in ks])
    np.testing.assert_allclose(batched, looped, rtol=1e-13, atol=0)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def frf(d, f):
        return d.frf(jnp.asarray([0.3]), f)

    f = jnp.asarray([50.0, 120.0])
    frf(drive, f)
    other = eqx.tree_at(lambda d: (d.carriage.table.mass, d.carriage.table.height), drive,
                        (jnp.asarray(300.0, jnp.float64), jnp.asarray(0.05, jnp.float64)))
    frf(other, f)


def test_update_model_fits_a_table_parameter(drive):
    """"carriage.table.mass" is an ordinary parameter path of update_model: from 400 kg it
    recovers the 450 kg whose four lowest modes are the data (the solver's rtol is 1e-6 on the
    log-scaled parameter; measured 2e-12 to 4.8e-12 in 6 steps)."""
    truth = eqx.tree_at(lambda d: d.carriage.table.mass, drive, jnp.asarray(450.0))
    m = fdjax.drive_modes(truth, 0.4, n_modes=4)
    data = fdjax.ModalData(m.frequency_hz[:4], m.damping_ratio[:4], m.phase_deg[:4])
    res = fdjax.update_model(drive, data, {"carriage.table.mass": (200.0, 800.0)}, 0.4,
                             n_modes=4, max_steps=50)
    assert bool(res.success)
    np.testing.assert_allclose(res.parameters["carriage.table.mass"], 450.0, rtol=1e-9)


def test_bad_input():
    with pytest.raises(ValueError, match=r"`Table\(mass=\.\.\.\)` must be finite and positive, "
                                         r"got -1"):
        fdjax.Table(mass=-1.0, stiffness=K_T)
    with pytest.raises(ValueError, match=r"`Table\(stiffness=\.\.\.\)` must be finite and posi"):
        fdjax.Table(mass=M_T, stiffness=0.0)
    with pytest.raises(ValueError, match=r"`Table\(damping=\.\.\.\)` must be finite and non-neg"):
        fdjax.Table(mass=M_T, stiffness=K_T, damping=-1.0)
    with pytest.raises(ValueError, match=r"`Table\(height=\.\.\.\)` must be finite"):
        fdjax.Table(mass=M_T, stiffness=K_T, height=np.nan)
    with pytest.raises(ValueError, match=r"`Carriage\(table=\.\.\.\)` must be a fdjax\.Table or "
                                         r"None, got float"):
        fdjax.Carriage(mass=700.0, pitch_inertia=36.0, pitch_stiffness=5e6, table=400.0)
    # traced: the converter's check becomes an eqx.error_if on the stored leaf
    with pytest.raises(CHECK_FAILED,
                       match=r"`Table\(mass=\.\.\.\)` must be finite and positive"):
        jax.block_until_ready(jax.jit(lambda m: fdjax.Table(mass=m, stiffness=K_T).mass)(-1.0))


def test_a_table_drive_keeps_all_of_its_modes(drive, plain):
    """With a table the mesh has 2·n + 6 DOFs, one more than without: the twin can keep all of
    them (the options' cap was the plain drive's 2·n + 5), and one more is refused for the
    drive it is asked of; drive_modes reaches its 2·n + 5 pairs."""
    full = fdjax.TwinOptions(n_elements=4, kept_modes=14)
    assert fdjax.state_space(drive, 0.3, twin=full).A.shape == (28, 28)
    with pytest.raises(ValueError, match=r"`state_space\(twin=\.\.\.\)` keeps 14 modes, more "
                                         r"than the 13 DOFs of this drive's mesh"):
        fdjax.state_space(plain, 0.3, twin=full)
    m = fdjax.drive_modes(drive, 0.3, n_modes=13, twin=fdjax.TwinOptions(n_elements=4))
    assert np.all(np.diff(np.asarray(m.frequency_hz)) > 0)  # 13 distinct modes
    with pytest.raises(ValueError, match=r"`drive_modes\(n_modes=\.\.\.\)` must be an integer "
                                         r"between 1 and 12"):
        fdjax.drive_modes(plain, 0.3, n_modes=13, twin=fdjax.TwinOptions(n_elements=4))
