"""The ball-screw drive: H_M(Y_table, f) by LM-FBS (paper Eq. 1/2, DESIGN.md §2)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fdjax

POS = np.array([0.1, 0.25, 0.4, 0.55, 0.7])
FREQ = np.geomspace(2.0, 3000.0, 1500)


@pytest.fixture(scope="module")
def drive():
    return fdjax.reference_drive()


@pytest.fixture(scope="module")
def H(drive):
    return np.asarray(drive.frf(POS, FREQ))


def test_shape_and_units(H):
    assert H.shape == (POS.size, FREQ.size, 3, 2)
    assert H.dtype == np.complex128
    # receptances of a machine-tool axis: x2/F3 of order 1e-9…1e-6 m/N below 1 kHz
    assert 1e-10 < np.median(np.abs(H[:, FREQ > 100, 1, 1])) < 1e-6


def test_coupled_equals_direct_assembly(drive, H):
    """LM-FBS with B = [0, −i_sc, −1, 1, 0, 0] equals one model assembled without coupling."""
    Hd = np.asarray(drive.frf_direct(POS, FREQ))
    rel = np.abs(H - Hd) / np.abs(Hd)
    assert rel.max() < 1e-8


def test_reciprocity(H):
    # θ1/F3 = x3/T1 (Maxwell–Betti; both in rad/N = m/(N·m))
    np.testing.assert_allclose(H[..., 0, 1], H[..., 2, 0], rtol=1e-12)


def test_rigid_body_asymptote(drive):
    """Far below the first mode, x2/T1 = i_sc / (−ω²J + iωc) with the reflected inertia."""
    s, r, c = drive.screw, drive.rotary, drive.carriage
    isc = float(s.ratio)
    J_screw = float(s.density) * np.pi * float(s.diameter) ** 4 / 32 * float(s.length)
    J = (float(r.motor_inertia) + float(r.drive_end_inertia) + float(r.free_end_inertia)
         + J_screw + float(c.mass) * isc**2)
    cd = (float(r.motor_damping) + float(r.drive_end_damping) + float(r.free_end_damping)
          + float(c.axial_damping) * isc**2)
    f = np.array([0.5, 1.0])
    w = 2 * np.pi * f
    rigid = isc / (-(w**2) * J + 1j * w * cd)
    Hf = np.asarray(drive.frf([0.4], f))[0]
    # the elastic correction is O((f/f1)²) ≈ 1e-4 at 1 Hz for f1 ≈ 100 Hz
    np.testing.assert_allclose(Hf[:, 1, 0], rigid, rtol=2e-4)
    np.testing.assert_allclose(Hf[:, 2, 0], rigid, rtol=2e-4)
    np.testing.assert_allclose(Hf[:, 0, 0], 1 / (-(w**2) * J + 1j * w * cd), rtol=2e-4)


def _peak_freqs(h, f, fmin, fmax):
    a = np.abs(h)
    k = np.flatnonzero((a[1:-1] > a[:-2]) & (a[1:-1] > a[2:])) + 1
    k = k[(f[k] > fmin) & (f[k] < fmax)]
    return f[k]


def test_modes_move_with_position(drive):
    f = np.linspace(50.0, 2500.0, 6000)
    H = np.asarray(drive.frf([0.1, 0.7], f))
    # first axial mode: the screw's axial stiffness at the nut falls as the nut moves away
    p_near = _peak_freqs(H[0, :, 1, 0], f, 50, 300)[0]
    p_far = _peak_freqs(H[1, :, 1, 0], f, 50, 300)[0]
    assert p_far < 0.85 * p_near
    # higher modes move more (paper Sec. 3.2): the torsional mode of the free screw span
    hi_near = _peak_freqs(H[0, :, 1, 0], f, 900, 2200)
    hi_far = _peak_freqs(H[1, :, 1, 0], f, 900, 2200)
    assert abs(hi_far[0] - hi_near[0]) / hi_near[0] > 0.1


def test_grad_matches_finite_differences(drive):
    """d|h21|/dθ for physical parameters and the table position, central differences."""

    def mag(d, y):
        h = d.receptance(y, 2 * jnp.pi * 180.0)
        return jnp.abs(h[1, 0]) * 1e6

    y = jnp.asarray(0.35)
    g_drive, g_y = jax.grad(mag, argnums=(0, 1))(drive, y)
    cases = {
        "nut.stiffness": (lambda d: d.nut.stiffness, g_drive.nut.stiffness),
        "rotary.coupling_stiffness": (lambda d: d.rotary.coupling_stiffness,
                                      g_drive.rotary.coupling_stiffness),
        "carriage.mass": (lambda d: d.carriage.mass, g_drive.carriage.mass),
        "screw.lead": (lambda d: d.screw.lead, g_drive.screw.lead),
    }
    for name, (get, g) in cases.items():
        x0 = float(get(drive))
        h = 6e-6 * abs(x0)  # ≈ eps^(1/3) · scale
        up = eqx.tree_at(get, drive, jnp.asarray(x0 + h))
        dn = eqx.tree_at(get, drive, jnp.asarray(x0 - h))
        fd = (mag(up, y) - mag(dn, y)) / (2 * h)
        np.testing.assert_allclose(float(g), float(fd), rtol=1e-6, err_msg=name)
    h = 1e-6
    fd = (mag(drive, y + h) - mag(drive, y - h)) / (2 * h)
    np.testing.assert_allclose(float(g_y), float(fd), rtol=1e-6)


def test_vmap_over_drives_equals_loop(drive):
    ks = jnp.linspace(3e8, 8e8, 4)
    w = 2 * jnp.pi * jnp.geomspace(10.0, 2000.0, 64)

    def one(k):
        return eqx.tree_at(lambda d: d.nut.stiffness, drive, k).receptance(0.3, w)

    batched = np.asarray(jax.vmap(one)(ks))
    looped = np.stack([np.asarray(one(k)) for k in ks])
    np.testing.assert_allclose(batched, looped, rtol=1e-13)


def test_frf_compiles_once_for_new_positions_and_parameters(drive):
    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def h(d, y, w):
        return d.receptance(y[:, None], w[None, :])

    w = 2 * jnp.pi * jnp.geomspace(10.0, 2000.0, 32)
    h(drive, jnp.array([0.2, 0.3]), w)
    h(eqx.tree_at(lambda d: d.nut.stiffness, drive, jnp.array(4e8, jnp.float64)),
      jnp.array([0.5, 0.6]), w)
