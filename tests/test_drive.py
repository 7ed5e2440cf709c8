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
    return fdjax.table1_drive()


@pytest.fixture(scope="module")
def H(drive):
    return np.asarray(drive.frf(POS, FREQ))


def test_shape_and_units(H):
    assert H.shape == (POS.size, FREQ.size, 3, 2)
    assert H.dtype == np.complex128
    # receptances of a machine-tool axis: x2/F3 above 100 Hz lies near the mass line of the
    # 700 kg saddle, 1/(mω²) = 3.6e-12 m/N at its geometric-mean frequency ≈ 550 Hz
    # (measured median 2.74e-12: a unit error of 10 falls outside)
    assert 2e-12 < np.median(np.abs(H[:, FREQ > 100, 1, 1])) < 5e-12


def test_coupled_equals_direct_assembly(drive, H):
    """LM-FBS with B = [0, −i_sc, −1, 1, 0, 0] equals one model assembled without coupling.

    Both are exact; they differ by the round-off of the solves, ≈ eps·cond of the largest
    response.  Measured: 6.5e-11 normwise; entrywise 7.5e-11, except θ1/F3 where it is small
    against its own peak: there the error is 5.8e-11 of that peak (5.0e-11 with XLA's default
    compilation), and entrywise 5.9e-11 where the entry is above 1e-6 of the peak (near
    2.3 kHz, at 1e-12 of the peak, 9.9e-9; at 3e-9 of the peak 3.0e-10, 4.9e-10 with XLA's
    default compilation)."""
    from test_statespace import normwise_error

    Hd = np.asarray(drive.frf_direct(POS, FREQ))
    assert normwise_error(H, Hd, drive).max() < 2e-10
    rel = np.abs(H - Hd) / np.abs(Hd)
    assert np.delete(rel, 1, axis=-1)[..., 0].max() < 3e-10  # θ1/T1
    assert rel[..., 1:, :].max() < 3e-10  # x2 and x3 rows
    peak = np.abs(Hd[..., 0, 1]).max()
    assert np.abs(H - Hd)[..., 0, 1].max() < 1e-10 * peak
    assert rel[..., 0, 1][np.abs(Hd[..., 0, 1]) > 1e-6 * peak].max() < 1e-10


def test_reciprocity(H):
    # θ1/F3 = x3/T1 (Maxwell–Betti; both in rad/N = m/(N·m))
    np.testing.assert_allclose(H[..., 0, 1], H[..., 2, 0], rtol=1e-12)


def check_rigid_asymptote(drive, n_low_modes: int, first_mode_hz: float):
    """Far below the first mode, x2/T1 = i_sc / (−ω²J + iωc), J and c summed independently of
    the drive's own summaries: rotor, hubs, the (hollow) screw in torsion and every sliding mass
    through i_sc²; motor, bearing and guideway friction (a table's damper is internal).

    Elastic corrections at 1 Hz: Σ_r O((f/f_r)²) over the low modes, at most n (f/f1)²; and,
    first order in f, the guideway damping force ω c_x x_c deflects the axial supports (k_de +
    k_fe in parallel) and pitches the saddle through the nut (moment arm h_n, pitch stiffness
    k_ψ), seen at height h: ω c_x (1/k_ax + |h h_n|/k_ψ); ×2 on the first-order terms
    (estimates)."""
    s, r, c = drive.screw, drive.rotary, drive.carriage
    isc = float(s.ratio)
    d, di = float(s.diameter), float(s.bore_diameter)
    J_screw = float(s.density) * np.pi * (d**4 - di**4) / 32 * float(s.length)
    sliding = float(c.mass) + (0.0 if c.table is None else float(c.table.mass))
    J = (float(r.motor_inertia) + float(r.drive_end_inertia) + float(r.free_end_inertia)
         + J_screw + sliding * isc**2)
    cd = (float(r.motor_damping) + float(r.drive_end_damping) + float(r.free_end_damping)
          + float(c.axial_damping) * isc**2)
    # the drive's own rigid-body summaries (used by the feed-forward defaults) are these sums
    np.testing.assert_allclose(float(drive.reflected_inertia()), J, rtol=1e-14)
    np.testing.assert_allclose(float(drive.reflected_damping()), cd, rtol=1e-14)
    f = np.array([0.5, 1.0])
    w = 2 * np.pi * f
    rigid = isc / (-(w**2) * J + 1j * w * cd)
    Hf = np.asarray(drive.frf([0.4], f))[0]
    a, wc = drive.axial, 2 * np.pi * 1.0 * float(c.axial_damping)
    k_ax = float(a.drive_end_stiffness) + float(a.free_end_stiffness)

    def tol(h):
        arm = abs(h * float(c.nut_height)) / float(c.pitch_stiffness)
        return n_low_modes * (1.0 / first_mode_hz) ** 2 + 2 * wc * (1 / k_ax + arm)

    np.testing.assert_allclose(Hf[:, 1, 0], rigid, rtol=tol(float(c.scale_height)))
    np.testing.assert_allclose(Hf[:, 2, 0], rigid, rtol=tol(float(c.tool_height)))
    np.testing.assert_allclose(Hf[:, 0, 0], 1 / (-(w**2) * J + 1j * w * cd), rtol=tol(0.0))


def test_rigid_body_asymptote(drive):
    """The reference drive: three low modes (49.5, 95, 131 Hz).  Measured: 7e-4 (θ1), 8e-4
    (x2), 4.1e-3 (x3) against bounds of 1.2e-3 … 6e-3."""
    check_rigid_asymptote(drive, n_low_modes=3, first_mode_hz=49.5)


def test_rigid_body_asymptote_hollow_screw(drive):
    """A bored screw: its torsional inertia ρπ(d⁴ − d_i⁴)/32 enters J."""
    hollow = eqx.tree_at(lambda d: d.screw.bore_diameter, drive, jnp.asarray(0.03))
    assert float(hollow.reflected_inertia()) < float(drive.reflected_inertia())
    check_rigid_asymptote(hollow, n_low_modes=3, first_mode_hz=49.0)


def _peak_freqs(h, f, fmin, fmax):
    a = np.abs(h)
    k = np.flatnonzero((a[1:-1] > a[:-2]) & (a[1:-1] > a[2:])) + 1
    k = k[(f[k] > fmin) & (f[k] < fmax)]
    return f[k]


def test_modes_move_with_position(drive):
    """The calibrated drive's low modes (saddle and coupling, 49–131 Hz) hardly move; the screw's
    axial mode, whose free span and nut-point stiffness change with the nut, moves most
    (paper Sec. 3.2: higher modes vary more)."""
    m = fdjax.track_drive_modes(fdjax.drive_modes(drive, np.array([0.1, 0.7]), n_modes=6))
    f = np.asarray(m.frequency_hz)
    change = np.abs(f[1] / f[0] - 1)
    assert np.all(change[:4] < 0.03), f  # measured ≤ 2.0 % (mode 2)
    assert change[4] > 0.1, f  # the screw's axial mode: 1494 → 1320 Hz
    # the same movement in the FRF itself: the axial-mode peak of h21 between 1.2 and 1.7 kHz
    # (1492 → 1285 Hz; at 0.7 m the mode is damped, ζ ≈ 0.05, and its peak sits 2.7 % low)
    fr = np.linspace(1200.0, 1700.0, 2001)
    H = np.asarray(drive.frf([0.1, 0.7], fr))[:, :, 1, 0]
    near, far = _peak_freqs(H[0], fr, 1200, 1700), _peak_freqs(H[1], fr, 1200, 1700)
    assert abs(near[0] / f[0, 4] - 1) < 0.01 and far[0] < 0.9 * near[0], (near, far)


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
        # central differences: truncation and round-off ~ε^(2/3) ≈ 4e-11 of the scale;
        # measured 2e-10, 4e-11, 5e-11, 2e-11
        np.testing.assert_allclose(float(g), float(fd), rtol=1e-8, err_msg=name)
    h = 1e-6
    fd = (mag(drive, y + h) - mag(drive, y - h)) / (2 * h)
    # round-off ε·|f|/h of the position step: measured 1.2e-9, 1.4e-8 with the suite's flags
    np.testing.assert_allclose(float(g_y), float(fd), rtol=1e-7)


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


# ------------------------------------------------------------------ lengths in metres
@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(length=850.0, diameter=57.5, lead=10.0, bore_diameter=32.0),
         r"`Screw\(length=\.\.\.\)` must be at most 20 m \(no ball screw is longer\), got 850; "
         r"lengths are in metres: 850 mm is 0\.85 m"),
        (dict(length=0.85, diameter=57.5, lead=0.01),
         r"`Screw\(diameter=\.\.\.\)` must be at most 1 m \(no ball screw is thicker\), got "
         r"57\.5; lengths are in metres: 57\.5 mm is 0\.0575 m"),
        (dict(length=0.85, diameter=0.0575, lead=0.01, bore_diameter=32.0),
         r"`Screw\(bore_diameter=\.\.\.\)` must be at most 1 m \(no ball screw is thicker\), "
         r"got 32; lengths are in metres: 32 mm is 0\.032 m"),
        (dict(length=0.85, diameter=0.0575, lead=10.0),
         r"`Screw\(lead=\.\.\.\)` must be at most 0\.5 m \(per revolution; no ball screw has a "
         r"longer lead\), got 10; lengths are in metres: 10 mm is 0\.01 m"),
        (dict(length=3e4, diameter=0.0575, lead=0.01),
         r"`Screw\(length=\.\.\.\)` must be at most 20 m \(no ball screw is longer\), got 30000"),
    ],
)
def test_screw_lengths_are_in_metres(kwargs, match):
    """A screw given in mm used to be accepted (an 850 m screw 57.5 m thick); a concrete value
    beyond what any ball screw has is refused, with its value in metres when that fits."""
    with pytest.raises(ValueError, match="^" + match + "$"):
        fdjax.Screw(**kwargs)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: fdjax.Carriage(10.0, 1.0, 1e6, tool_height=150.0),
         r"`Carriage\(tool_height=\.\.\.\)` must be at most 5 m in magnitude \(no point of a "
         r"carriage lies farther from its pitch centre\), got 150; lengths are in metres: 150 mm "
         r"is 0\.15 m"),
        (lambda: fdjax.Carriage(10.0, 1.0, 1e6, nut_height=-120.0),
         r"`Carriage\(nut_height=\.\.\.\)` must be at most 5 m in magnitude .*got -120; lengths "
         r"are in metres: -120 mm is -0\.12 m"),
        (lambda: fdjax.Carriage(10.0, 1.0, 1e6, scale_height=5.5),
         r"`Carriage\(scale_height=\.\.\.\)` must be at most 5 m in magnitude .*got 5\.5; "
         r"lengths are in metres: 5\.5 mm is 0\.0055 m"),
        (lambda: fdjax.Table(10.0, 1e8, height=300.0),
         r"`Table\(height=\.\.\.\)` must be at most 5 m in magnitude .*got 300; lengths are in "
         r"metres: 300 mm is 0\.3 m"),
        (lambda: fdjax.Rod.axial(diameter=0.03, length=850.0),
         r"`Rod\.axial\(length=\.\.\.\)` must be at most 20 m \(no ball screw is longer\), got "
         r"850; lengths are in metres: 850 mm is 0\.85 m"),
        (lambda: fdjax.Rod(850.0, 1.0, 1.0),
         r"`Rod\(length=\.\.\.\)` must be at most 20 m \(no ball screw is longer\), got 850; "
         r"lengths are in metres: 850 mm is 0\.85 m"),
    ],
)
def test_heights_and_rod_lengths_are_in_metres(make, match):
    """A height of 150 (mm) used to give a tool point 150 m above the carriage silently (the
    x3 column 748× the reference drive's); a rod of 850 (mm), an 850 m rod."""
    with pytest.raises(ValueError, match="^" + match + "$"):
        make()


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: fdjax.Rod.axial(diameter=57.5, length=0.85),
         r"`Rod\.axial\(diameter=\.\.\.\)` must be at most 1 m \(no ball screw is thicker\), "
         r"got 57\.5; lengths are in metres: 57\.5 mm is 0\.0575 m"),
        (lambda: fdjax.Screw(length=0.85, diameter=0.0575, lead=0.01, youngs_modulus=2.06e5),
         r"`Screw\(youngs_modulus=\.\.\.\)` must be between 1e\+08 and 1e\+13 Pa, got 206000; "
         r"in Pa: 206000 N/mm² \(MPa\) is 2\.06e\+11 Pa"),
        (lambda: fdjax.Screw(length=0.85, diameter=0.0575, lead=0.01, density=7.85),
         r"`Screw\(density=\.\.\.\)` must be between 100 and 30000 kg/m³, got 7\.85; in "
         r"kg/m³: 7\.85 g/cm³ is 7850 kg/m³"),
        (lambda: fdjax.Rod.torsion(diameter=0.03, length=0.85, shear_modulus=7.93e4),
         r"`Rod\.torsion\(shear_modulus=\.\.\.\)` must be between 1e\+08 and 1e\+13 Pa, got "
         r"79300; in Pa: 79300 N/mm² \(MPa\) is 7\.93e\+10 Pa"),
        (lambda: fdjax.Rod.axial(diameter=0.03, length=0.85, density=1e6),
         r"`Rod\.axial\(density=\.\.\.\)` must be between 100 and 30000 kg/m³, got 1e\+06$"),
    ],
)
def test_rod_diameters_and_materials_in_si_units(make, match):
    """A rod 57.5 (mm) thick was accepted (EA 5.3e14 N, where the screw refuses the same
    diameter); a modulus in N/mm² or a density in g/cm³ gave a shaft 1e6 or 1e3 times too
    soft or too light.  Each is refused with the value in SI units where that fits."""
    with pytest.raises(ValueError, match="^" + match):
        make()
    # the limits themselves are materials
    fdjax.Screw(length=0.85, diameter=0.0575, lead=0.01, youngs_modulus=1e8, density=3e4)


def test_a_drive_edited_after_construction_is_checked_where_it_is_used():
    """``eqx.tree_at`` skips the constructor's checks: a negative nut stiffness gave finite
    receptances and a twin with a divergent mode reported as a rigid-body one (natural
    frequencies [0, 0, 47.4, ...]).  The functions the drive is given to run those checks
    again (eagerly: a traced parameter is left to the checks on what is computed, so a NaN
    twin under jit is refused there)."""
    drive = fdjax.reference_drive()
    bad = eqx.tree_at(lambda d: d.nut.stiffness, drive, jnp.asarray(-1e9))
    for fn, call in (("BallScrewDrive.frf", lambda: bad.frf(0.3, [100.0])),
                     ("state_space", lambda: fdjax.state_space(bad, 0.3)),
                     ("drive_modes", lambda: fdjax.drive_modes(bad, 0.3, n_modes=3))):
        with pytest.raises(ValueError, match=r"^`NutJoint\(stiffness=\.\.\.\)` must be finite "
                                             r"and positive, got -1e\+09 \(in the model given "
                                             rf"to `{fn}`\)$"):
            call()
    light = eqx.tree_at(lambda d: d.carriage.mass, drive, jnp.asarray(-1000.0))
    with pytest.raises(ValueError, match=r"`Carriage\(mass=\.\.\.\)` must be finite and "
                                         r"positive, got -1000"):
        fdjax.fe_matrices(light, 0.3)
    # under jit, a NaN parameter's twin (its Cholesky factor NaN) is refused, not returned
    twin = fdjax.TwinOptions(kept_modes=4)

    def edited(k):
        return eqx.tree_at(lambda d: d.nut.stiffness, drive, k)

    for fn, run in (("state_space", lambda k: fdjax.state_space(edited(k), 0.3, twin=twin).A),
                    ("fe_matrices", lambda k: fdjax.fe_matrices(edited(k), 0.3).stiffness)):
        with pytest.raises(Exception, match=rf"`{fn}` produced a non-finite result"):
            jax.jit(run)(jnp.nan)
    with pytest.raises(Exception, match=r"`drive_modes\(drive=\.\.\.\)` gives a non-finite "
                                        r"model"):
        jax.jit(lambda k: fdjax.drive_modes(edited(k), 0.3, n_modes=3).frequency_hz)(jnp.nan)


def test_components_of_the_wrong_kind_are_named():
    """Swapped or missing components failed later as Python errors ("not enough values to
    unpack", "'NoneType' object has no attribute 'length'"); a support given as a number as
    "'float' object has no attribute '_dynamic_stiffness'"."""
    d = fdjax.reference_drive()
    with pytest.raises(TypeError, match=r"^`BallScrewDrive\(rotary=\.\.\.\)` must be an "
                                        r"fdjax\.Rotary, got Axial$"):
        fdjax.BallScrewDrive(d.screw, d.axial, d.axial, d.carriage, d.nut, d.nut_offset)
    with pytest.raises(TypeError, match=r"`BallScrewDrive\(screw=\.\.\.\)` .* got NoneType"):
        fdjax.BallScrewDrive(None, d.rotary, d.axial, d.carriage, d.nut, d.nut_offset)
    rod = fdjax.Rod.axial(diameter=0.03, length=0.85)
    with pytest.raises(TypeError, match=r"^`rod_receptance\(left=\.\.\.\)` must be an "
                                        r"fdjax\.Support or None \(free\), got float$"):
        fdjax.rod_receptance(rod, [10.0], [0.5], left=1e8)
    with pytest.raises(TypeError, match=r"`Rod\.frf\(right=\.\.\.\)`"):
        rod.frf([10.0], [0.5], right="fixed")


def test_height_limits_and_traced_heights():
    """The limits themselves are carriages; a traced height is not refused (its plausibility
    is checked where it is given) and compiles once."""
    fdjax.Carriage(10.0, 1.0, 1e6, nut_height=-5.0, tool_height=5.0, table=fdjax.Table(
        10.0, 1e8, height=5.0))
    fdjax.Rod.axial(diameter=0.03, length=20.0)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def x3(h):
        return fdjax.Carriage(10.0, 1.0, 1e6, tool_height=h).heights[2]

    assert float(x3(jnp.asarray(0.15))) == 0.15 and float(x3(jnp.asarray(150.0))) == 150.0


def test_screw_limits_and_traced_screws():
    """The limits themselves are screws (20 m long, 1 m thick, 0.5 m lead); traced values are
    checked finite and positive only, as before, and compile once."""
    fdjax.Screw(length=20.0, diameter=1.0, lead=0.5, bore_diameter=0.5)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def ratio(lead):
        return fdjax.Screw(length=0.85, diameter=0.0575, lead=lead).ratio

    assert float(ratio(jnp.asarray(0.01))) == pytest.approx(0.01 / (2 * np.pi), rel=1e-15)
    assert float(ratio(jnp.asarray(10.0))) == pytest.approx(10.0 / (2 * np.pi), rel=1e-15)


def test_nut_offset_and_travel_in_mm_are_named():
    """``nut_offset=80.`` (mm) on the reference drive's 0.85 m screw used to be refused without
    saying why; the message now names the offset with its value in metres.  A metre value that
    is merely too large keeps the joint message.  The travel is a pair of numbers: strings are
    a TypeError, and a travel in mm below zero is caught as well as above."""
    import dataclasses

    d = fdjax.reference_drive()
    with pytest.raises(ValueError, match=r"^`BallScrewDrive\(nut_offset=\.\.\.\)` must keep the "
                                         r"nut strictly inside the screw \(0, 0\.85\) m over the "
                                         r"travel \[0\.1, 0\.7\] m, got 80 \(nut positions "
                                         r"\[80\.1, 80\.7\] m\); lengths are in metres: 80 mm is "
                                         r"0\.08 m$"):
        dataclasses.replace(d, nut_offset=80.0)
    with pytest.raises(ValueError, match=r"^`BallScrewDrive\(travel_m=\.\.\., nut_offset=\.\.\.\)` "
                                         r"must keep the nut strictly inside the screw \(0, "
                                         r"0\.85\) m, got nut positions \[1, 1\.6\] m$"):
        dataclasses.replace(d, nut_offset=0.9)
    with pytest.raises(TypeError, match=r"^`BallScrewDrive\(travel_m=\.\.\.\)` must be a \(min, "
                                        r"max\) pair of numbers in m, got \('a', 'b'\)$"):
        dataclasses.replace(d, travel_m=("a", "b"))
    with pytest.raises(ValueError, match=r"^`BallScrewDrive\(travel_m=\.\.\.\)` must be a \(min, "
                                         r"max\) pair in m, got \(-700\.0, -100\.0\); table "
                                         r"positions are in metres: -700 mm is -0\.7 m$"):
        dataclasses.replace(d, travel_m=(-700.0, -100.0))
