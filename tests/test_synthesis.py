"""Gradient synthesis: the growth-rate barrier's gradient, the PID parameterisation, the
interpolated and scheduled loops, the certification, and saving and loading the designs."""

import dataclasses
import math
from decimal import Decimal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fdjax
from fdjax._simulation._lifted import growth_rate

BOUNDS = fdjax.MCMBounds.for_servo(fdjax.Servo())
POSITIONS = np.linspace(0.1, 0.7, 6)


# ------------------------------------------------------------------ the growth-rate barrier
@pytest.mark.parametrize("pair", [False, True], ids=["real", "complex-pair"])
def test_growth_rate_value_and_gradient_against_eig(pair):
    """ln ρ(Φ)/h and its gradient against numpy's eigenvalues and central differences of
    them; dominant eigenvalue real or a complex pair (measured: value 5e-12, gradient 6e-9
    relative, the differences' own error)."""
    rng = np.random.default_rng(3 if pair else 4)
    A = rng.normal(size=(8, 8)) / np.sqrt(8)
    if pair:
        A[:2, :2] = 1.3 * np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    h = 1e-3
    lam = np.linalg.eigvals(A)
    assert (abs(lam[np.argmax(np.abs(lam))].imag) > 0.1) == pair

    def oracle(M):
        return np.log(np.max(np.abs(np.linalg.eigvals(M)))) / h

    P = jnp.asarray(A)
    np.testing.assert_allclose(float(growth_rate(P, h)), oracle(A), rtol=0, atol=1e-9)
    g = np.asarray(jax.grad(lambda p: growth_rate(p, h))(P))
    eps = 1e-6
    fd = np.array([[(oracle(A + eps * E) - oracle(A - eps * E)) / (2 * eps)
                    for E in np.eye(64)[8 * i:8 * i + 8].reshape(8, 8, 8)] for i in range(8)])
    np.testing.assert_allclose(g, fd, rtol=0, atol=1e-7 * np.max(np.abs(fd)))


# ------------------------------------------------------------------ PID parameterisation
def test_pid_parameterisation_round_trip_and_feedback_only():
    pid = fdjax.reference_pid(k_ffv=3.0, k_ffa=8.0)
    par = fdjax.PIDParameterisation(pid)
    theta = par.from_controller(pid)
    np.testing.assert_allclose(np.asarray(theta)[[0, 1, 2, 4, 5]], [0, 0, 0, 1, 1], atol=1e-14)
    back = par.to_controller(theta)
    for k in ("kp", "ki", "kd", "wd", "k_ffv", "k_ffa"):
        np.testing.assert_allclose(getattr(back, k), getattr(pid, k), rtol=1e-13)
    assert par.names == fdjax.PID_PARAMETERS
    # any θ: ω_d inside the default bounds, 10 Hz to 0.9 × Nyquist, reached at large |θ₃|
    top = 2 * math.pi * 0.9 * 0.5 / fdjax.Servo().period
    assert par.wd_hz == (10.0, 0.9 * 0.5 / fdjax.Servo().period)
    for th in 50 * np.random.default_rng(0).normal(size=(20, 6)):
        wd = float(par.to_controller(jnp.asarray(th)).wd)
        assert 2 * math.pi * 10.0 * (1 - 1e-12) <= wd <= top * (1 + 1e-12)
    for t3, bound in ((40.0, top), (-40.0, 2 * math.pi * 10.0)):
        th = np.zeros(6)
        th[3] = t3
        np.testing.assert_allclose(float(par.to_controller(jnp.asarray(th)).wd), bound,
                                   rtol=1e-12)
    fb = fdjax.PIDParameterisation(fdjax.reference_pid(), feedforward=False)
    c = fb.to_controller(jnp.asarray([0.1, 0.2, 0.3, 0.0, 5.0, -7.0]))
    assert float(c.k_ffv) == 0.0 and float(c.k_ffa) == 0.0
    dl = fdjax.DoubleLoopParameterisation(BOUNDS, fdjax.reference_controller(),
                                          feedforward=False)
    c = dl.to_controller(jnp.concatenate([jnp.zeros(3), jnp.array([4.0, 4.0]), jnp.zeros(7)]))
    assert float(c.k_ffv) == 0.0 and float(c.k_ffa) == 0.0
    with pytest.raises(TypeError, match=r"`PIDParameterisation\(reference=\.\.\.\)` must be an "
                                        r"fdjax.PIDLoop"):
        fdjax.PIDParameterisation(fdjax.DoubleLoop())
    with pytest.raises(ValueError, match=r"k_ffv sets the scale of its parameter"):
        fdjax.PIDParameterisation(fdjax.reference_pid())  # zero feed-forward as the scale


def test_smooth_max_lies_between_mean_and_max():
    v = jnp.array([1.0, 3.0, 2.0, 2.5])
    for beta in (0.1, 1.0, 10.0, 100.0):
        s = float(fdjax.smooth_max(v, beta))
        assert float(jnp.mean(v)) <= s <= 3.0 + 1e-12
        assert s >= 3.0 - math.log(4) / beta
    assert abs(float(fdjax.smooth_max(v, 1e-6)) - 2.125) < 1e-5
    # the closed form (1/β) ln((1/n) Σ e^{β v_i}), summed exactly in Decimal: measured 6e-16
    # relative at β = 0.1, 0 above; 4.0e-11 at β = 1e-6, where ln(1 + ~βv̄) loses ~1/β ulps
    for beta, tol in ((1e-6, 5e-11), (0.1, 1e-15), (1.0, 1e-15), (10.0, 1e-15), (100.0, 1e-15)):
        exact = (sum((Decimal(beta) * Decimal(float(x))).exp() for x in np.asarray(v)) / 4).ln()
        exact /= Decimal(beta)
        assert abs(float(fdjax.smooth_max(v, beta)) - float(exact)) <= tol * float(exact)


# ------------------------------------------------------------------ interpolation, schedule
def _designs():
    y = (POSITIONS - 0.4) / 0.3
    return np.stack([0.5 + 0.3 * y, -0.2 + 0.4 * y ** 2, 0.8 - 0.1 * y, -0.3 * y,
                     1.7 - 0.5 * y, 1.0 + 0.2 * y, -0.7 + 0.1 * y ** 3], axis=1)


def test_interpolated_loop_is_linear_in_the_normalised_parameters():
    loop = fdjax.InterpolatedLoop(fdjax.DoubleLoop(), POSITIONS, _designs(), BOUNDS)
    t = _designs()
    for i, y in enumerate(POSITIONS):
        np.testing.assert_allclose(loop.normalised(y), t[i], rtol=0, atol=1e-15)
        np.testing.assert_allclose(BOUNDS.from_mcm(loop.controller(y).mcm), t[i], atol=1e-11)
    mid = 0.5 * (POSITIONS[2] + POSITIONS[3])
    np.testing.assert_allclose(loop.normalised(mid), 0.5 * (t[2] + t[3]), atol=1e-15)
    np.testing.assert_allclose(loop.normalised(0.05), t[0], atol=1e-15)  # held outside
    with pytest.raises(ValueError, match=r"must be increasing"):
        fdjax.InterpolatedLoop(fdjax.DoubleLoop(), POSITIONS[::-1], _designs(), BOUNDS)


def test_designs_round_trip_bit_for_bit(tmp_path):
    # bounds unlike the defaults in every field, and a network unlike the default one: what
    # comes back from the JSON is compared too
    odd = fdjax.MCMBounds.for_servo(
        fdjax.Servo(period=1 / 16000), nyquist_fraction=0.8, freq_min_hz=20.0,
        peak_gain=(1e-2, 5.0), peak_damping=(0.05, 0.8), peak_phase_max=2.0,
        notch_damping=(0.02, 1.5), notch_depth_min=1e-2)
    net = fdjax.ATANetwork((0.05, 0.75), width=5, gains=True, key=jax.random.PRNGKey(2))
    mcm = fdjax.reference_mcm()
    controllers = {
        "pid": fdjax.reference_pid(k_ffv=1.5, k_ffa=2.5),
        "fixed": fdjax.DoubleLoop(123.0, 4567.0, 89.0, k_ffv=0.9, k_ffa=7.7, mcm=mcm),
        "interp": fdjax.InterpolatedLoop(fdjax.DoubleLoop(150.0, 3000.0, 40.0), POSITIONS,
                                         _designs(), odd),
        "ata": fdjax.ScheduledLoop(fdjax.DoubleLoop(111.0, 2222.0, 33.0), net, odd),
        # any MCM layout: none, two peaks alone
        "plain": fdjax.DoubleLoop(100.0, 300.0, 20.0),
        "two_peaks": fdjax.DoubleLoop(mcm=fdjax.MCM(fdjax.PeakFilter(
            np.array([0.5, 2.0]), np.array([2e3, 5e3]), np.array([0.1, 0.3]),
            np.array([0.2, -0.4])))),
    }
    fdjax.save_designs(tmp_path, controllers, metadata={"drive": "test"})
    back, meta = fdjax.load_designs(tmp_path)
    assert meta == {"drive": "test"} and list(back) == list(controllers)
    for name, c in controllers.items():
        a, b = jax.tree_util.tree_leaves(c), jax.tree_util.tree_leaves(back[name])
        assert len(a) == len(b) and type(back[name]) is type(c)
        for x, y in zip(a, b):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert back["interp"].bounds == odd and back["ata"].bounds == odd
    n = back["ata"].network
    assert (n.travel_m, n.width, n.gains) == ((0.05, 0.75), 5, True)
    with pytest.raises(TypeError, match=r"`save_designs\(controllers=\.\.\.\)` must be named "
                                        r"by strings, got the key 1 \(int\)"):
        fdjax.save_designs(tmp_path / "ints", {1: controllers["pid"]})
    # a corrupt or truncated file, malformed JSON, or the file given for its folder: named
    leaves = (tmp_path / "controllers.eqx").read_bytes()
    for name, eqx_bytes, json_text, match in (
            ("cut", leaves[:len(leaves) // 2], None, r"controllers\.eqx' does not hold the "
                                                     r"leaves of the designs"),
            ("junk", b"junk" * 8, None, r"does not hold the leaves of the designs"),
            ("bad_json", leaves, "{'x': 1", r"controllers\.json' is not the JSON file of a set "
                                            r"of fdjax designs")):
        bad = tmp_path / name
        bad.mkdir()
        (bad / "controllers.eqx").write_bytes(eqx_bytes)
        (bad / "controllers.json").write_text(
            json_text or (tmp_path / "controllers.json").read_text())
        with pytest.raises(ValueError, match=r"`load_designs\(folder=\.\.\.\)`: .*" + match):
            fdjax.load_designs(bad)
    with pytest.raises(NotADirectoryError, match=r"must be the folder that holds controllers\.eqx "
                                                 r"and controllers\.json, got the file .*did you "
                                                 r"mean"):
        fdjax.load_designs(tmp_path / "controllers.eqx")
    with pytest.raises(FileNotFoundError, match=r"`load_designs\(folder=\.\.\.\)`: no file"):
        fdjax.load_designs(tmp_path / "nothing")
    with pytest.raises(ValueError, match=r"'bare' must have an fdjax\.MCM .*got a PeakFilter"):
        fdjax.save_designs(tmp_path / "bad", {"bare": fdjax.DoubleLoop(mcm=mcm.peak)})
    assert not (tmp_path / "bad").exists()  # refused before the folder is made
    # without a folder: the designs shipped with fdjax, those the command line evaluates
    from fdjax import cli

    shipped, meta = fdjax.load_designs()
    assert list(shipped) == list(fdjax.CONTROLLERS), list(shipped)
    assert isinstance(shipped["mcm_ata_e2e"], fdjax.ScheduledLoop)
    same, _ = fdjax.load_designs(cli.SHIPPED_DESIGNS)
    assert bool(eqx.tree_equal(shipped, same))


# ------------------------------------------------------------------ certification
def test_certify_is_loop_margins_and_stability_at_each_position():
    """The certificate of a scheduled loop at each position equals the margins and the
    eigenvalues of the fixed loop it runs there (computed by the public functions)."""
    drive = fdjax.reference_drive()
    ref = fdjax.reference_controller(drive)
    theta = np.tile(np.asarray(BOUNDS.from_mcm(ref.mcm)), (6, 1))
    theta[:, 1] += np.linspace(0.0, -0.6, 6)  # the peak filter's frequency falls along the travel
    soft = eqx.tree_at(lambda c: c.log_kv, ref, ref.log_kv + math.log(0.5))
    sched = fdjax.InterpolatedLoop(soft, POSITIONS, theta, BOUNDS)
    y = np.array([0.1, 0.43, 0.7])
    f = np.geomspace(5.0, 3990.0, 300)
    cert = fdjax.certify(sched, drive, y, freq_hz=f)
    assert cert.positions_m.shape == (3,) and cert.requirements == (6.0, 30.0, 0.5)
    for k, p in enumerate(y):
        c = sched.controller(p)
        st = fdjax.check_stability(c, drive, position_m=p)
        m = fdjax.loop_margins(c, drive, f, position_m=p)
        loops = [m.plant_input, m.speed, m.position]
        assert bool(cert.stable[k]) == bool(st.stable)
        np.testing.assert_allclose(cert.growth_rate[k], st.growth_rate, rtol=1e-9)
        # the same arithmetic in another compiled program: round-off
        np.testing.assert_allclose(
            cert.modulus_margin[k], min(float(L.modulus_margin) for L in loops), rtol=1e-9)
        np.testing.assert_allclose(
            cert.gain_margin_db[k], min(abs(float(L.gain_margin_db)) for L in loops), rtol=1e-9)
        np.testing.assert_allclose(
            cert.phase_margin_deg[k], min(abs(float(L.phase_margin_deg)) for L in loops),
            rtol=1e-9)
        kept = (bool(st.stable) and min(float(L.modulus_margin) for L in loops) >= 0.5
                and min(abs(float(L.gain_margin_db)) for L in loops) >= 6.0
                and min(abs(float(L.phase_margin_deg)) for L in loops) >= 30.0)
        assert bool(cert.passed[k]) == kept, k
    assert not cert.passed.all() and cert.passed.any()  # both verdicts are exercised here
    assert ("certified at 3 positions" in cert.message) == cert.ok
    y_gm, v_gm = cert.worst("gain_margin_db")
    assert f"least gain margin {v_gm:.3g} dB at {y_gm * 1e3:.0f} mm (required 6 dB)" in cert.message
    # the requirements are the caller's: relaxed, every stable position passes (the same
    # compiled checks; the verdicts are drawn from them)
    easy = fdjax.certify(sched, drive, y, freq_hz=f, gain_margin_db=0.0, phase_margin_deg=0.0,
                         modulus_margin=1e-3)
    assert easy.requirements == (0.0, 0.0, 1e-3)
    np.testing.assert_array_equal(easy.modulus_margin, cert.modulus_margin)
    assert np.all(easy.stable) and np.all(easy.passed) and easy.ok
    assert "certified at 3 positions" in easy.message and "(required 0 dB)" in easy.message
    # a position gain so low (e⁻⁴ k_p, 3.7 1/s) that the position loop crosses unit gain
    # below the grid's 5 Hz: its phase margin cannot be read there, so no position passes
    # (|L| at 5 Hz measured 0.119); a grid from 0.05 Hz reads it and certifies the design
    # (|L| 11.7 there; least phase margin 67°, the speed loop's)
    weak = eqx.tree_at(lambda c: c.log_kp, soft, soft.log_kp - 4.0)
    blind = fdjax.certify(weak, drive, y, freq_hz=f)
    assert np.all(blind.stable) and not np.any(blind.passed)
    assert np.all(blind.low_gain < 1) and "a gain crossover below the grid" in blind.message
    seen = fdjax.certify(weak, drive, y, freq_hz=np.geomspace(0.05, 3990.0, 300))
    assert seen.ok and np.all(seen.low_gain > 1), seen.message
    assert blind.rows()["loop_gain_at_lowest_freq"] == blind.low_gain.tolist()
    # arguments that are not a twin's options or a grid below Nyquist are named
    with pytest.raises(TypeError, match=r"`certify\(twin=\.\.\.\)` must be an "
                                        r"fdjax\.TwinOptions, got str"):
        fdjax.certify(ref, drive, y, twin="full")
    for grid, expected in ((np.geomspace(5.0, 5000.0, 50), r"below the servo's Nyquist "
                                                             r"frequency 4000 Hz"),
                           ([3.0, 2.0], "strictly increasing")):
        with pytest.raises(ValueError, match=r"`certify\(freq_hz=\.\.\.\)` must be " + expected):
            fdjax.certify(ref, drive, y, freq_hz=grid)
    # the reference controller held fixed fails toward the screw end (unstable from 0.5 m)
    bad = fdjax.certify(ref, drive, y, freq_hz=f)
    assert not bad.ok and not bool(bad.stable[-1])
    assert "NOT certified" in bad.message and "unstable at" in bad.message
    # the message's span and the unstable stretch are the positions' range, in any order
    backwards = jax.tree_util.tree_map(lambda a: a[::-1], bad)
    for c in (bad, backwards):
        span = f"({y.min() * 1e3:.0f}–{y.max() * 1e3:.0f} mm)"
        assert span in c.message, c.message
    unstable = np.sort(bad.positions_m[~bad.stable]) * 1e3
    assert (f"unstable at {unstable.size} positions, from {unstable[0]:.0f} mm to "
            f"{unstable[-1]:.0f} mm") in backwards.message
    assert bad.worst("modulus_margin")[0] == 0.7
    # with several unstable positions the worst is the most unstable, in any order (the first
    # unstable one in the positions' order had been named: growth 1 of [1, 60, 5] 1/s)
    n = bad.positions_m.size
    growth = np.linspace(1.0, 5.0, n)
    growth[n // 2] = 60.0
    many = eqx.tree_at(lambda c: (c.stable, c.growth_rate), bad, (np.zeros(n, bool), growth))
    for many in (many, jax.tree_util.tree_map(lambda a: a[::-1], many)):
        assert many.worst("gain_margin_db")[0] == bad.positions_m[n // 2]
        assert (f"most at {bad.positions_m[n // 2] * 1e3:.0f} mm (growing at 60 1/s)"
                in many.message), many.message
    # the message's least margins are those of the stable positions (an unstable loop's
    # margins mean nothing)
    y_s, v_s = bad.worst("modulus_margin", stable_only=True)
    assert bool(bad.stable[list(bad.positions_m).index(y_s)])
    assert f"least modulus margin where stable {v_s:.3g} at {y_s * 1e3:.0f} mm" in bad.message
    with pytest.raises(ValueError, match=r"`certify\(positions_m=\.\.\.\)` must be inside the "
                                         r"travel"):
        fdjax.certify(ref, drive, [115.0])
    with pytest.raises(TypeError, match=r"`certify\(positions_m=\.\.\.\)` must be a number or an "
                                        r"array of numbers, got \['a'\]"):
        fdjax.certify(ref, drive, ["a"])
    # a grid on which a crossing can hide: a few points (the PID tuned at 115 mm was
    # certified at 0.4 and 0.7 m on 3 of them), or a filter sharper than its steps
    with pytest.raises(ValueError, match=r"`certify\(freq_hz=\.\.\.\)` must have neighbouring "
                                         r"frequencies within 5 % of each other .* got "
                                         r"8\.73e\+03 % between 44\.1588 and 3900 Hz"):
        fdjax.certify(ref, drive, y, freq_hz=np.geomspace(0.5, 3900.0, 3))
    sharp = eqx.tree_at(lambda c: c.mcm.peak.log_xi, ref, jnp.full_like(ref.mcm.peak.log_xi,
                                                                           np.log(1e-4)))
    with pytest.raises(ValueError, match=r"`certify\(freq_hz=\.\.\.\)` must resolve the "
                                         r"controller's peak filter at 174 Hz \(relative "
                                         r"half-width 0\.0001\), got a step of 0\.3\d+ % there: "
                                         r"give a grid with points closer than 0\.0174 Hz"):
        fdjax.certify(sharp, drive, y)
    # a requirement that no margin can meet (NaN failed every position without a word)
    for kw, msg in (({"gain_margin_db": np.nan}, r"gain_margin_db=\.\.\.\)` must be finite"),
                    ({"modulus_margin": 2.0}, r"modulus_margin=\.\.\.\)` must be in \(0, 1\]"),
                    ({"phase_margin_deg": 200.0}, r"phase_margin_deg=\.\.\.\)` must be in")):
        with pytest.raises(ValueError, match=r"`certify\(" + msg):
            fdjax.certify(ref, drive, y, **kw)


# ------------------------------------------------------------------ export
def test_python_control_export_names_its_arguments():
    # checked before python-control is imported: named without it too
    ref = fdjax.reference_controller()
    # a schedule's position: required, inside its network's travel
    sched = fdjax.ScheduledLoop(ref, fdjax.ATANetwork((0.1, 0.7), width=3), BOUNDS)
    with pytest.raises(ValueError, match=r"`to_python_control\(position_m=\.\.\.\)` is required"):
        fdjax.to_python_control(sched)
    with pytest.raises(ValueError, match=r"`to_python_control\(position_m=\.\.\.\)` must be "
                                         r"inside the network's travel \[0\.1, 0\.7\] m, got 0\.9"):
        fdjax.to_python_control(sched, 0.9)
    for kw, msg in (({"position_m": 115.0}, r"position_m=\.\.\.\)` must be a finite table position "
                                            r"in metres .*115 mm is 0\.115 m"),
                    ({"position_m": np.nan}, r"position_m=\.\.\.\)` must be a finite"),
                    ({"position_m": [0.2, 0.3]}, r"position_m=\.\.\.\)` must be a scalar"),
                    ({"filter_method": "bogus"}, r"filter_method=\.\.\.\)` must be one of"),
                    ({"form": "zpk"}, r"form=\.\.\.\)` must be 'ss' or 'tf', got 'zpk'")):
        with pytest.raises(ValueError, match=r"`to_python_control\(" + msg):
            fdjax.to_python_control(ref, **kw)


def test_python_control_export_is_the_law_the_loop_runs():
    control = pytest.importorskip("control")
    net = fdjax.ATANetwork((0.1, 0.7), width=4, key=jax.random.PRNGKey(1))
    sched = fdjax.ScheduledLoop(fdjax.reference_controller(), net, BOUNDS)
    servo = fdjax.Servo()
    T = servo.period
    f = np.array([3.0, 50.0, 170.0, 1260.0, 3000.0])
    z = np.exp(2j * np.pi * f * T)
    law = sched.law(0.4)
    want = np.asarray(law.discrete_transfer(jnp.asarray(z), T, "fitted"))  # (freq, 5)
    sys = fdjax.to_python_control(sched, 0.4, servo=servo)
    assert sys.dt == T and sys.ninputs == 5 and sys.noutputs == 1
    got = np.stack([sys(zk)[0] for zk in z])
    # the same state space evaluated by python-control: round-off (measured 4e-15)
    np.testing.assert_allclose(got, want, rtol=1e-10)
    cont = fdjax.to_python_control(fdjax.reference_pid(), discrete=False, form="tf")
    assert isinstance(cont, control.TransferFunction) and cont.dt == 0
    s = 2j * np.pi * f
    want_c = np.asarray(fdjax.reference_pid().law(None).transfer(jnp.asarray(s)))
    # ss → tf (polynomials) loses ~1e-7 near the integrator's pole at 3 Hz (measured 1.9e-7)
    np.testing.assert_allclose(np.stack([cont(sk)[0] for sk in s]), want_c, rtol=1e-6)
    # another servo period and the other discretisation: the export follows both (measured
    # 1.1e-14; the two discretisations differ by 1.2e-3 there)
    T16 = 1 / 16000
    z16 = np.exp(2j * np.pi * f * T16)
    sys16 = fdjax.to_python_control(sched, 0.4, servo=fdjax.Servo(period=T16),
                                    filter_method="tustin")
    assert sys16.dt == T16 and sys16.input_labels == list(fdjax.LAW_SIGNALS)
    assert sys16.output_labels == ["u"]
    want16 = np.asarray(law.discrete_transfer(jnp.asarray(z16), T16, "tustin"))
    np.testing.assert_allclose(np.stack([sys16(zk)[0] for zk in z16]), want16, rtol=1e-10)
    # and differs from the default's law there (what a dropped argument would give)
    assert not np.allclose(want16, law.discrete_transfer(jnp.asarray(z16), T16, "fitted"),
                           rtol=1e-6)


def test_synthesise_names_its_arguments():
    with pytest.raises(ValueError, match=r"`synthesise\(margin_width=\.\.\.\)` must be a "
                                         r"finite positive number, got 0"):
        fdjax.synthesise(margin_width=0, progress=False)
    with pytest.raises(TypeError, match=r"`synthesise\(drive=\.\.\.\)` must be an fdjax"):
        fdjax.synthesise("drive.json", progress=False)
    with pytest.raises(TypeError, match=r"`synthesise\(servo=\.\.\.\)` must be an fdjax"):
        fdjax.synthesise(servo=8000, progress=False)
    # the paper's positions must lie in the drive's travel (checked before any stage runs)
    short = dataclasses.replace(fdjax.reference_drive(), travel_m=(0.2, 0.6))
    with pytest.raises(ValueError, match=r"`synthesise\(drive=\.\.\.\)` must have a travel that "
                                         r"holds the paper's design positions 0\.1–0\.7 m"):
        fdjax.synthesise(short, progress=False)
    # the counts of every stage before the first one runs (the robust MCM's is the last)
    for kwargs, match in (({"robust_steps": -1}, r"robust_steps=\.\.\.\)` must be an integer at "
                                                 r"least 1, got -1"),
                          ({"e2e_positions": 1},
                           r"e2e_positions=\.\.\.\)` must be an integer at least 2"),
                          ({"local_steps": 2.5},
                           r"local_steps=\.\.\.\)` must be an integer at least 1"),
                          ({"simplex_evaluations": 13},
                           r"simplex_evaluations=\.\.\.\)` must be an integer at least 14, "
                           r"got 13")):
        with pytest.raises(ValueError, match=r"`synthesise\(" + match):
            fdjax.synthesise(progress=False, **kwargs)
