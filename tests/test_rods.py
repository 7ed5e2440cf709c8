"""Exact rod/shaft receptances against closed forms (wave solution)."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import fdjax

STEEL_ROD = dict(diameter=0.03, length=1.2)


def _kz(rod, w):
    g = lambda x: float(x)  # noqa: E731
    Z = g(rod.stiffness) * (1 + 1j * (g(rod.loss_factor) + w * g(rod.retardation)))
    return w * np.sqrt(g(rod.inertia) / Z), Z  # κ, Z*


@pytest.mark.parametrize("damped", [False, True])
def test_free_free_interior_point_receptance_closed_form(damped):
    # h(x, x) = −cos κx · cos κ(L−x) / (κ Z* sin κL) for a free–free rod
    rod = fdjax.Rod.axial(**STEEL_ROD, loss_factor=0.02 if damped else 0.0,
                          retardation=1e-6 if damped else 0.0)
    L, x = float(rod.length), 0.37
    freq = np.linspace(10.0, 5000.0, 997)
    w = 2 * np.pi * freq
    k, Z = _kz(rod, w)
    ref = -np.cos(k * x) * np.cos(k * (L - x)) / (k * Z * np.sin(k * L))
    H = np.asarray(rod.frf(freq, [x]))[:, 0, 0]
    # near an undamped resonance the relative error grows like eps·|ω|/|ω − ω_r|
    np.testing.assert_allclose(H, ref, rtol=1e-9 if damped else 1e-8)
    # end-to-end transfer −1/(κZ* sin κL)
    H2 = np.asarray(rod.frf(freq, [0.0, L]))
    np.testing.assert_allclose(
        H2[:, 0, 1], -1 / (k * Z * np.sin(k * L)), rtol=1e-9 if damped else 1e-8
    )


def _natural(rod, freq, left=None, right=None, point=None):
    """|dynamic stiffness| at the given frequency, relative to the static scale Z/L."""
    pt = float(rod.length) if point is None else point
    h = np.asarray(rod.frf(np.atleast_1d(freq), [pt], left, right))[0, 0, 0]
    return abs(1 / h) / (float(rod.stiffness) / float(rod.length))


def test_fixed_free_and_free_free_natural_frequencies():
    # A loss factor η keeps the receptance finite at resonance, where the end-point dynamic
    # stiffness κZ* tan κL (free–free) or κZ* cot κL (fixed–free), relative to Z/L, falls to
    # (κL)²η/2 with κL = rπ or (2r−1)π/2; off resonance it is O(κL).
    eta = 1e-6
    rod = fdjax.Rod.axial(**STEEL_ROD, loss_factor=eta)
    c, L = float(rod.wave_speed), float(rod.length)
    fixed = fdjax.Support(stiffness=1e9 * float(rod.stiffness) / L)  # fixed to ~1e-9
    for r in (1, 2, 3):
        kl_ff, kl_fr = r * np.pi, (2 * r - 1) * np.pi / 2
        assert _natural(rod, (2 * r - 1) * c / (4 * L), left=fixed) < kl_fr**2 * eta
        assert _natural(rod, r * c / (2 * L)) < kl_ff**2 * eta
        # half-way between, the rod is far from resonance
        assert _natural(rod, (r + 0.25) * c / (2 * L)) > 0.1


def test_shaft_in_torsion_fixed_free():
    shaft = fdjax.Rod.torsion(diameter=0.032, length=0.9, loss_factor=1e-6)
    G, rho = 7.93e10, 7850.0
    np.testing.assert_allclose(float(shaft.stiffness), G * np.pi * 0.032**4 / 32, rtol=1e-14)
    c = np.sqrt(G / rho)
    np.testing.assert_allclose(float(shaft.wave_speed), c, rtol=1e-14)
    fixed = fdjax.Support(stiffness=1e9 * float(shaft.stiffness) / 0.9)
    assert _natural(shaft, c / (4 * 0.9), left=fixed) < (np.pi / 2) ** 2 * 1e-6


def test_rod_with_tip_mass():
    # fixed–free rod with a tip mass: βL tan βL = m_rod / m_tip
    rod = fdjax.Rod.axial(**STEEL_ROD, loss_factor=1e-6)
    L, c = float(rod.length), float(rod.wave_speed)
    m_rod = float(rod.inertia) * L
    m_tip = 0.5 * m_rod
    bl = scipy.optimize.brentq(lambda x: x * np.tan(x) - m_rod / m_tip, 1e-6, np.pi / 2 - 1e-9)
    f1 = bl * c / (2 * np.pi * L)
    fixed = fdjax.Support(stiffness=1e9 * float(rod.stiffness) / L)
    tip = fdjax.Support(mass=m_tip)
    assert _natural(rod, f1, left=fixed, right=tip) < 2e-6
    assert _natural(rod, 1.1 * f1, left=fixed, right=tip) > 1e-2


def test_grad_wrt_length_matches_finite_differences():
    def mag(L):
        rod = fdjax.Rod.axial(diameter=0.03, length=L, retardation=1e-6)
        h = fdjax.rod_receptance(rod, jnp.array([2 * jnp.pi * 700.0]), [0.3])
        return jnp.abs(h[0, 0, 0]) * 1e9

    L = jnp.asarray(1.2)
    g = jax.grad(mag)(L)
    h = 1e-5
    fd = (mag(L + h) - mag(L - h)) / (2 * h)
    np.testing.assert_allclose(float(g), float(fd), rtol=5e-9)  # measured 6e-11


@pytest.mark.parametrize("kind, kwargs, name, value", [
    ("axial", {"youngs_modulus": -1e9}, "youngs_modulus", "-1e+09"),
    ("axial", {"length": -1.0}, "length", "-1"),
    ("axial", {"density": 0.0}, "density", "0"),
    ("torsion", {"shear_modulus": np.nan}, "shear_modulus", "nan"),
    ("torsion", {"diameter": 0.0}, "diameter", "0"),
])
def test_solid_rods_name_the_argument_passed(kind, kwargs, name, value):
    """The error names the constructor called and its own argument, not the Rod field it
    becomes (a negative E was reported as `Rod(stiffness=...)`, with EA's value)."""
    args = {"diameter": 0.05, "length": 1.0, **kwargs}
    with pytest.raises(ValueError, match=rf"`Rod\.{kind}\({name}=\.\.\.\)` must be finite and "
                                         rf"positive, got {re.escape(value)}$"):
        getattr(fdjax.Rod, kind)(**args)
    # and the section's closed forms: EA = E πd²/4, ρJ = ρ πd⁴/32
    rod = fdjax.Rod.axial(diameter=0.05, length=1.0)
    np.testing.assert_allclose(float(rod.stiffness), 2.06e11 * np.pi * 0.05**2 / 4, rtol=1e-15)
    shaft = fdjax.Rod.torsion(diameter=0.05, length=1.0)
    np.testing.assert_allclose(float(shaft.inertia), 7850.0 * np.pi * 0.05**4 / 32, rtol=1e-15)
