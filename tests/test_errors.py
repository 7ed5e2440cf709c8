"""Bad input: a clear ValueError naming the argument, its value and what was expected."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jit_errors import CHECK_FAILED

import fdjax

FREQ = np.linspace(10.0, 100.0, 5)


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: fdjax.chain_model([100.0, -1.0], [1e7], [0.0]),
         r"chain_model\(masses=\.\.\.\)` must be finite and positive, got -1"),
        (lambda: fdjax.chain_model([100.0, 0.0], [1e7], [0.0]),
         r"chain_model\(masses=\.\.\.\)` must be finite and positive, got 0"),
        (lambda: fdjax.chain_model([100.0, 1.0], [-5.0], [0.0]),
         r"chain_model\(stiffnesses=\.\.\.\)` must be finite and positive, got -5"),
        (lambda: fdjax.chain_model([100.0, 1.0], [1e7, 1e7], [0.0]),
         r"`chain_model\(stiffnesses=\.\.\., dampings=\.\.\.\)` must have 1 entries for 2 masses, "
         r"got 2 and 1"),
        (lambda: fdjax.LumpedModel([[1.0, 0], [0, -1.0]], np.eye(2), np.eye(2)),
         r"LumpedModel\(mass=\.\.\.\)` must be positive definite, got eigenvalues \[-1\.,  1\.\]"),
        (lambda: fdjax.Rod.axial(diameter=0.03, length=0.0),
         r"`Rod\.axial\(length=\.\.\.\)` must be finite and positive, got 0"),
        (lambda: fdjax.Rod.axial(diameter=-0.03, length=1.0),
         r"Rod.axial\(diameter=\.\.\.\)` must be finite and positive, got -0.03"),
        (lambda: fdjax.Screw(length=1.0, diameter=0.03, lead=-0.02),
         r"Screw\(lead=\.\.\.\)` must be finite and positive, got -0.02"),
        (lambda: fdjax.Screw(length=1.0, diameter=0.03, lead=0.0),
         r"Screw\(lead=\.\.\.\)` must be finite and positive, got 0"),
        (lambda: fdjax.Screw(length=np.nan, diameter=0.03, lead=0.01),
         r"Screw\(length=\.\.\.\)` must be finite and positive, got nan"),
        (lambda: fdjax.Screw(length=1.0, diameter=0.03, lead=0.01, bore_diameter=0.03),
         r"Screw\(bore_diameter=\.\.\.\)` must be smaller than the diameter 0.03 m, got 0.03"),
        (lambda: fdjax.Screw(length=1.0, diameter=0.03, lead=0.01, bore_diameter=-0.01),
         r"Screw\(bore_diameter=\.\.\.\)` must be finite and non-negative, got -0.01"),
        (lambda: fdjax.Carriage(mass=250.0, pitch_inertia=9.0, pitch_stiffness=2e8,
                                tool_height=np.nan),
         r"Carriage\(tool_height=\.\.\.\)` must be finite"),
        (lambda: fdjax.NutJoint(stiffness=-1e8),
         r"NutJoint\(stiffness=\.\.\.\)` must be finite and positive, got -1e\+08"),
        (lambda: fdjax.Rotary(motor_inertia=0.0, coupling_stiffness=1e4),
         r"Rotary\(motor_inertia=\.\.\.\)` must be finite and positive, got 0"),
        (lambda: fdjax.Axial(drive_end_stiffness=7e8, free_end_damping=-1.0),
         r"Axial\(free_end_damping=\.\.\.\)` must be finite and non-negative, got -1"),
    ],
)
def test_bad_parameters(build, match):
    with pytest.raises(ValueError, match=match):
        build()


def test_position_outside_travel():
    drive = fdjax.reference_drive()
    with pytest.raises(ValueError, match=r"frf\(position_m=\.\.\.\)` must be inside the travel "
                                         r"\[0.1, 0.7\] m, got 0.8 at index 1"):
        drive.frf([0.3, 0.8], FREQ)


def test_travel_beyond_screw():
    d = fdjax.reference_drive()
    with pytest.raises(ValueError, match=r"must keep the nut strictly inside the screw"):
        fdjax.BallScrewDrive(d.screw, d.rotary, d.axial, d.carriage, d.nut, nut_offset=0.15,
                             travel_m=(0.1, 0.9))


@pytest.mark.parametrize(
    "freq, match",
    [
        ([10.0, 5.0, 20.0], r"must be strictly increasing, got \[10\., +5\., 20\.\]"),
        ([10.0, 10.0], r"must be strictly increasing, got \[10\., 10\.\]"),
        ([0.0, 5.0], r"must be finite and positive, got 0 at index 0"),
        ([-1.0, 5.0], r"must be finite and positive, got -1 at index 0"),
        ([1.0, np.nan], r"must be finite and positive, got nan at index 1"),
        (np.ones((2, 2)), r"must be a 1-D grid of at least one frequency, got shape \(2, 2\)"),
    ],
)
def test_bad_frequency_grids(freq, match):
    """Named with the method the user called, the drive's or the lumped model's."""
    with pytest.raises(ValueError, match=r"^`BallScrewDrive\.frf\(freq_hz=\.\.\.\)` " + match):
        fdjax.reference_drive().frf([0.3], freq)
    with pytest.raises(ValueError, match=r"^`LumpedModel\.frf\(freq_hz=\.\.\.\)` " + match):
        fdjax.three_mass().frf(freq)


def test_errors_under_jit():
    drive = fdjax.reference_drive()

    @jax.jit
    def f(y):
        return drive.frf(y, FREQ)

    assert f(jnp.array([0.3])).shape == (1, 5, 3, 2)
    with pytest.raises(CHECK_FAILED, match=r"`BallScrewDrive\.frf\(position_m=\.\.\.\)` must be "
                                           r"inside the travel"):
        jax.block_until_ready(f(jnp.array([0.9])))

    @jax.jit
    def g(lead):
        return fdjax.Screw(length=1.0, diameter=0.03, lead=lead).ratio

    with pytest.raises(CHECK_FAILED, match=r"Screw\(lead=\.\.\.\)` must be finite and positive"):
        jax.block_until_ready(g(jnp.asarray(-0.01)))


def test_nan_parameter_inside_jit_is_not_silent():
    drive = fdjax.reference_drive()

    @eqx.filter_jit
    def f(k):
        d = eqx.tree_at(lambda d: d.nut.stiffness, drive, k)
        return d.frf(jnp.array([0.3]), FREQ)

    # tree_at bypasses the constructor's checks; the non-finite result is caught instead
    with pytest.raises(CHECK_FAILED, match=r"non-finite result; check the parameters for NaN"):
        jax.block_until_ready(f(jnp.asarray(jnp.nan)))

    @jax.jit
    def g(k):
        return fdjax.NutJoint(stiffness=k).dynamic_stiffness(1.0)

    with pytest.raises(CHECK_FAILED, match=r"NutJoint\(stiffness=\.\.\.\)` must be finite"):
        jax.block_until_ready(g(jnp.asarray(jnp.nan)))


def test_position_in_millimetres_says_so():
    """A position typed in mm (inside the travel once divided by 1000) gets the value in metres
    in the message, from the drive, the loop's functions and the tuners; one outside in both
    units does not."""
    drive = fdjax.reference_drive()
    hint = r"; table positions are in metres: 250 mm is 0\.25 m$"
    with pytest.raises(ValueError, match=r"`BallScrewDrive\.frf\(position_m=\.\.\.\)` must be "
                                         r"inside the travel \[0\.1, 0\.7\] m, got 250 at "
                                         r"index 1" + hint):
        drive.frf([0.3, 250.0], FREQ)
    with pytest.raises(ValueError, match=r"`state_space\(position_m=\.\.\.\)` .* got 250" + hint):
        fdjax.state_space(drive, 250.0)
    ref = fdjax.reference_controller(drive)
    par = fdjax.DoubleLoopParameterisation(fdjax.MCMBounds.for_servo(fdjax.Servo()), ref)
    obj = fdjax.tuning_objective()
    with pytest.raises(ValueError, match=r"`tune_local\(positions_m=\.\.\.\)` .* got 250 at "
                                         r"index 0 and 1 more" + hint):
        fdjax.tune_local(par, obj, drive, [250.0, 400.0], ref)
    # 0.9 m: outside in m and in mm
    with pytest.raises(ValueError, match=r"^`BallScrewDrive\.frf\(position_m=\.\.\.\)` must be "
                                         r"inside the travel \[0\.1, 0\.7\] m, got 900 at "
                                         r"index 0$"):
        drive.frf([900.0], FREQ)


def test_a_position_that_is_not_a_number_is_named():
    drive = fdjax.reference_drive()
    for bad in ("0.4", ["a", "b"], None):
        with pytest.raises(TypeError, match=r"`BallScrewDrive\.frf\(position_m=\.\.\.\)` must be a "
                                            r"number or an array of numbers, got"):
            drive.frf(bad, np.array([10.0, 20.0]))
    with pytest.raises(TypeError, match=r"`check_stability\(position_m=\.\.\.\)` must be a number"):
        fdjax.check_stability(fdjax.DoubleLoop(), drive, position_m="0.4")


def test_public_docstrings_carry_their_module_notes():
    """Every public name has a docstring; one that refers to its module's docstring (the
    equations its module's names share) shows that text in help() too."""
    import sys

    for name in fdjax.__all__:
        value = getattr(fdjax, name)
        if not callable(value):
            continue
        doc = " ".join((value.__doc__ or "").split())   # a phrase broken over lines too
        assert doc, name
        assert "module docstring" not in doc and "module docs" not in doc, name
        if "notes below" in doc:
            first = sys.modules[value.__module__].__doc__.strip().splitlines()[0]
            assert first.strip() in doc, name
    assert "J(controller, Y) = e_rms / e_ref" in fdjax.Objective.__doc__


def test_more_inputs_are_named_before_any_work():
    """Each of these used to reach JAX, NumPy or diffrax and fail there (or run on)."""
    import dataclasses

    drive = fdjax.reference_drive()
    loop = fdjax.DoubleLoop()
    ref = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    n = int(round(ref.duration / 1.25e-4)) + 1
    cases = [
        (lambda: dataclasses.replace(drive, travel_m=(0.1, 0.7, 0.9)),
         r"`BallScrewDrive\(travel_m=\.\.\.\)` must be a \(min, max\) pair of numbers in m"),
        (lambda: dataclasses.replace(drive, travel_m=(100.0, 700.0)),
         r"`BallScrewDrive\(travel_m=\.\.\.\)` must be a \(min, max\) pair in m, got \(100\.0, "
         r"700\.0\); table positions are in metres: 700 mm is 0\.7 m"),
        (lambda: fdjax.simulate(loop, drive, ref, position_m=0.3, moving="no"),
         r"`simulate\(moving=\.\.\.\)` must be a bool", TypeError),
        (lambda: fdjax.simulate(loop, drive, ref, position_m=0.3, disturbance=np.full(n, np.nan)),
         r"`simulate\(disturbance=\.\.\.\)` must be finite"),
        (lambda: fdjax.simulate(loop, drive, ref, fdjax.PadeODE(), position_m=0.3,
                                duration=1e-6),
         r"`simulate\(duration=\.\.\.\)` must span at least one output period of PadeODE "
         r"\(0\.000125 s\), got 1e-06 s"),
        # an exponential solver of another step: an error deep inside diffrax at run time
        (lambda: fdjax.simulate(loop, drive, ref, fdjax.PadeODE(
            dt=1e-4, solver=fdjax.ExponentialFOH(1.25e-4)), position_m=0.3),
         r"`PadeODE\(solver=\.\.\.\)` is an ExponentialFOH stepping 0\.000125 s, which must be "
         r"the output period 0\.0001 s"),
        # a run of one sample gave an RMS error of 0; 0.6 periods of PadeODE ran one period
        (lambda: fdjax.simulate(loop, drive, ref, position_m=0.3, duration=1e-5),
         r"`simulate\(duration=\.\.\.\)` must span at least one output period of SampledData "
         r"\(0\.000125 s\), got 1e-05 s"),
        (lambda: fdjax.simulate(loop, drive, ref, fdjax.PadeODE(dt=1e-3), position_m=0.3,
                                duration=6e-4),
         r"must span at least one output period of PadeODE \(0\.001 s\), got 0\.0006 s"),
        (lambda: fdjax.simulate(loop, drive, ref, position_m=0.3, duration=1e6),
         r"`simulate\(duration=\.\.\.\)`: 1e\+06 s is 8000000001 output samples .* GiB, more "
         r"than the .* GiB of memory available"),
        (lambda: fdjax.gain_headroom(loop, drive),
         r"`gain_headroom\(position_m=\.\.\.\)` is required"),
        (lambda: fdjax.DiscreteFilter([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0]], np.zeros((0, 6)), 1e-4),
         r"`DiscreteFilter\(parallel_sos=\.\.\.\)` must hold finite rows .* a0 ≠ 0"),
        (lambda: fdjax.LTI(np.eye(2), np.ones((3, 1)), np.ones((1, 2)), np.zeros((1, 1))),
         r"`LTI\(A=\.\.\., B=\.\.\., C=\.\.\., D=\.\.\.\)` must have shapes"),
        (lambda: drive.frf(0.3, []), r"`BallScrewDrive\.frf\(freq_hz=\.\.\.\)` must be a 1-D "
         r"grid of at least one frequency, got shape \(0,\)"),
        (lambda: fdjax.jerk_limited("0.3", 0.1, 1.0, 100.0),
         r"`jerk_limited\(distance=\.\.\.\)` must be a number or an array of numbers, got '0\.3'",
         TypeError),
    ]
    for call, match, *kind in cases:
        with pytest.raises(kind[0] if kind else ValueError, match=match):
            call()
    with pytest.raises(TypeError, match=r"`gain_headroom\(controller=\.\.\.\)` must be"):
        fdjax.gain_headroom("x", drive, position_m=0.3)
    # travel given as an array is kept as the pair of floats a static field needs
    again = dataclasses.replace(drive, travel_m=np.array([0.1, 0.7]))
    assert again.travel_m == (0.1, 0.7) and type(again.travel_m[0]) is float
    # a channel of zeros has nothing to fit
    f = np.geomspace(20.0, 3000.0, 200)
    H = np.array(drive.frf(0.3, f))[0]
    H[:, 2, 1] = 0.0
    with pytest.raises(ValueError, match=r"`identify_modes\(frf=\.\.\.\)` must not have a channel "
                                         r"that is zero at every frequency, got one at channel 5"):
        fdjax.identify_modes(f, H, n_modes=4)


def test_figures_take_one_position_and_missing_values():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fdjax import plots

    drive = fdjax.reference_drive()
    f = np.geomspace(20.0, 3000.0, 100)
    H = np.asarray(drive.frf(0.4, f))
    fig = plots.plot_frf_family(0.4, f, H[0])
    assert [len(a.lines) for a in fig.axes] == [1] * 6          # the six entries at one position
    h = H[:, :, 1, 0].copy()
    h[0, 3] = np.nan
    fig = plots.plot_frf_cloud(0.4, f, h)
    assert len(fig.axes) == 2 and all(a.collections for a in fig.axes)
    # a mode missing at 200 mm is a gap in its curves, the other points drawn
    fig = plots.plot_resonant_phase([0.1, 0.2, 0.3],
                                    np.array([[50, 100], [51, np.nan], [52, 101.0]]),
                                    np.array([[-100, -200], [-110, np.nan], [-120, -190.0]]))
    phase, freq = fig.axes
    np.testing.assert_array_equal(phase.lines[1].get_xdata(), [100.0, 200.0, 300.0])   # in mm
    np.testing.assert_array_equal(phase.lines[1].get_ydata(), [-200.0, np.nan, -190.0])
    np.testing.assert_array_equal(freq.lines[1].get_ydata(), [100.0, np.nan, 101.0])
    np.testing.assert_array_equal(freq.lines[0].get_ydata(), [50.0, 51.0, 52.0])
    # a controller unstable everywhere: no error drawn, a marker at each position
    fig = plots.plot_rms_over_travel([100, 200], {"a": {"rms_error_um": [None, None],
                                                        "stable": [False, False],
                                                        "modulus_margin": [0.1, 0.2]}})
    rms, margin = fig.axes
    assert np.all(np.isnan(rms.lines[0].get_ydata())) and len(rms.lines[1].get_ydata()) == 2
    np.testing.assert_array_equal(margin.lines[0].get_ydata(), [0.1, 0.2])
    with pytest.raises(ValueError, match=r"`plot_tracking\(runs=\.\.\.\)` must hold at least one"):
        plots.plot_tracking({}, title="none")
    plt.close("all")


def test_figures_name_their_bad_arguments():
    """Positions in mm where metres are expected (and the reverse), transposed or short data,
    non-finite positions, an empty input: refused before anything is drawn, in the house
    style, instead of a scrambled figure or an error from inside NumPy or matplotlib."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fdjax import plots

    f = np.geomspace(10.0, 3000.0, 4)
    pos = [0.1, 0.2, 0.3]
    h = (100.0 * np.arange(3)[:, None] + np.arange(4)[None] + 1).astype(complex)
    L = np.full((3, 4), -0.5 + 0.1j)
    res = {"a": {"rms_error_um": [1.0, 2.0, 3.0], "stable": [True] * 3,
                 "modulus_margin": [0.6] * 3}}
    cases = [
        (lambda: plots.plot_frf_family([115, 400, 700], f, np.zeros((3, 4, 3, 2))),
         r"`plot_frf_family\(position_m=\.\.\.\)` must be at most 20 m .*115 mm is 0.115 m"),
        (lambda: plots.plot_frf_cloud([115, 400, 700], f, h),
         r"`plot_frf_cloud\(position_m=\.\.\.\)` must be at most 20 m"),
        (lambda: plots.plot_frf_cloud(pos, f, h.T),
         r"`plot_frf_cloud\(h=\.\.\.\)` must have shape \(n_pos, n_freq\) = \(3, 4\), "
         r"got \(4, 3\)"),
        (lambda: plots.plot_frf_cloud([np.nan, 0.2, 0.3], f, h),
         r"`plot_frf_cloud\(position_m=\.\.\.\)` must be table positions in m, finite, got "
         r"nan at index 0"),
        (lambda: plots.plot_resonant_phase(pos, np.ones((2, 3)), np.ones((2, 3))),
         r"`plot_resonant_phase\(frequency_hz=\.\.\.\)` must have shape \(n_pos, n_modes\)"),
        (lambda: plots.plot_resonant_phase(pos, np.ones((3, 2)), np.ones((3, 3))),
         r"`plot_resonant_phase\(phase_deg=\.\.\.\)` must have shape"),
        (lambda: plots.plot_peak_filter_effect(f, pos, L[:2], L),
         r"`plot_peak_filter_effect\(L_without=\.\.\.\)` must have shape \(n_pos, n_freq\)"),
        (lambda: plots.plot_peak_filter_effect(f, [], L, L),
         r"`plot_peak_filter_effect\(position_m=\.\.\.\)` must be table positions in m: "
         r"a 1-D array of at least one value, got shape \(0,\)"),
        (lambda: plots.plot_peak_filter_effect(f, pos, L, L, filter_label=""),
         r"`plot_peak_filter_effect\(filter_label=\.\.\.\)` must be a non-empty string"),
        (lambda: plots.plot_rms_over_travel([0.1, 0.4, 0.7], res),
         r"`plot_rms_over_travel\(positions_mm=\.\.\.\)` must be table positions in mm, "
         r"got values from 0.1 to 0.7: positions in metres\? 0.7 m is 700 mm"),
        (lambda: plots.plot_rms_over_travel([100, 200], res),
         r"`plot_rms_over_travel\(results=\.\.\.\)` must give one 'rms_error_um' per "
         r"position \(2\), got 3 for 'a'"),
        (lambda: plots.plot_rms_over_travel([100, 200, 300], {"a": {"rms_error_um": [1] * 3,
                                                                    "stable": [True] * 3}}),
         r"must give 'modulus_margin' for every controller, got none for 'a'"),
        (lambda: plots.plot_convergence({}),
         r"`plot_convergence\(curves=\.\.\.\)` must hold at least one tuning"),
        (lambda: plots.plot_convergence({"t": (np.ones((5, 2)), ["one"])}),
         r"must give one line label per column of the history \(2\), got 1 for 't'"),
        (lambda: plots.plot_three_mass_frf(f, np.zeros((3, 3, 3))),
         r"`plot_three_mass_frf\(H=\.\.\.\)` must have shape \(n_freq, 3, 3\) = \(4, 3, 3\)"),
        (lambda: plots.plot_deflection_shapes(np.eye(3), ["a"]),
         r"`plot_deflection_shapes\(labels=\.\.\.\)` must hold one title per shape \(3\), "
         r"got 1"),
        (lambda: plots.plot_deflection_shapes(np.array([[1.0, 2.0], [0.0, 0.0]]), ["a", "b"]),
         r"must have a non-zero entry in every shape, got an all-zero row 1"),
        (lambda: plots.plot_velocity_nyquist(f, h[0], h[0, :3]),
         r"`plot_velocity_nyquist\(h_noncollocated=\.\.\.\)` must have shape \(n_freq,\)"),
        (lambda: plots.plot_velocity_nyquist([], [], []),
         r"`plot_velocity_nyquist\(freq_hz=\.\.\.\)` must be frequencies in Hz: a 1-D array"),
    ]
    for call, match in cases:
        with pytest.raises(ValueError, match=match):
            call()
    # the receptance's own label when the accelerance is off, and one mode's phase per position
    fig = plots.plot_frf_cloud(pos, f, h, accelerance=False)
    assert fig.axes[1].get_ylabel() == "|h21| = |x2/T1| (m/(N·m))"
    plots.plot_resonant_phase(pos, [50.0, 51.0, 52.0], [-90.0, -100.0, -110.0])
    plt.close("all")


def test_reference_pid_names_its_feedforward_gains():
    """Its own name, not the PIDLoop it builds."""
    with pytest.raises(ValueError, match=r"`reference_pid\(k_ffv=\.\.\.\)` must be finite"):
        fdjax.reference_pid(k_ffv=np.nan)
    with pytest.raises(TypeError, match=r"`reference_pid\(k_ffa=\.\.\.\)` must be a number"):
        fdjax.reference_pid(k_ffa="x")


def test_reference_controller_names_its_arguments():
    """Its own name, not rigid_feedforward, which it calls."""
    with pytest.raises(TypeError, match=r"^`reference_controller\(drive=\.\.\.\)` must be an "
                                        r"fdjax\.BallScrewDrive, got str$"):
        fdjax.reference_controller("x")
    with pytest.raises(TypeError, match=r"^`reference_controller\(servo=\.\.\.\)` must be an "
                                        r"fdjax\.Servo, got float$"):
        fdjax.reference_controller(fdjax.reference_drive(), 1.2)


def test_first_use_inside_a_users_jit_leaks_no_tracer():
    """fdjax loads its modules on first use; when that use is inside a jitted function, the
    module's constants (the default Servo()) were built as tracers of that trace, and the
    next trace failed with an UnexpectedTracerError.  A fresh process, as a user's (an open
    loop: the cheapest program of the module that first raised it)."""
    import subprocess
    import sys

    script = (
        "import numpy as np, equinox as eqx, jax.numpy as jnp, fdjax\n"
        "f = np.geomspace(5, 3900, 64)\n"
        "@eqx.filter_jit\n"
        "def gm(c, d, p):\n"
        "    return jnp.abs(fdjax.open_loop(c, d, f, position_m=p,\n"
        "        twin=fdjax.TwinOptions(kept_modes=7)).speed[..., 10])\n"
        "d, c = fdjax.reference_drive(), fdjax.DoubleLoop()\n"
        "a = gm(c, d, 0.3)\n"
        "v = gm(c, d, jnp.array([0.2, 0.3]))  # a second trace: it failed here\n"
        "print(float(a), *(float(x) for x in v))\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    a, *v = (float(x) for x in out.stdout.split())
    assert len(v) == 2 and abs(v[1] - a) <= 1e-12 * abs(a), (a, v)


def test_a_controller_with_nan_parameters_is_named():
    """A NaN gain in a user's controller reached the law inside fdjax's compiled programs,
    where no check sees it: margins came back inf and the stability verdict "pole at nan Hz".
    Every entry point now names the leaf; under jit, simulate's check is an eqx.error_if."""
    drive = fdjax.reference_drive()
    bad = eqx.tree_at(lambda c: c.log_kv, fdjax.DoubleLoop(), jnp.asarray(jnp.nan))
    f = np.geomspace(1.0, 3900.0, 50)
    ref = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    calls = {
        "loop_margins": lambda: fdjax.loop_margins(bad, drive, f, position_m=0.3),
        "open_loop": lambda: fdjax.open_loop(bad, drive, f, position_m=0.3),
        "check_stability": lambda: fdjax.check_stability(bad, drive, position_m=0.3),
        "gain_headroom": lambda: fdjax.gain_headroom(bad, drive, position_m=0.3),
        "simulate": lambda: fdjax.simulate(bad, drive, ref, position_m=0.3),
    }
    for fn, call in calls.items():
        with pytest.raises(ValueError, match=rf"`{fn}\(controller=\.\.\.\)` must have finite "
                                             r"parameters, got nan in \.log_kv"):
            call()
    run = eqx.filter_jit(lambda c: fdjax.simulate(c, drive, ref, position_m=0.3).x2)
    with pytest.raises(eqx.EquinoxRuntimeError,  # what eqx.filter_jit raises
                       match=r"`simulate\(controller=\.\.\.\)` must have finite parameters"):
        jax.block_until_ready(run(bad))
    # the margins, the open loops and the stability verdict check it under jit too (they read
    # a NaN gain as infinite margins, all-NaN loops, and "unstable, growing at nan 1/s")
    twin = fdjax.state_space(drive, 0.3, twin=fdjax.TwinOptions(kept_modes=4))
    jitted = {"loop_margins": lambda c: fdjax.loop_margins(c, twin, f),
              "open_loop": lambda c: fdjax.open_loop(c, twin, f).speed,
              "check_stability": lambda c: fdjax.check_stability(c, twin)}
    for fn, body in jitted.items():
        call = eqx.filter_jit(body)
        with pytest.raises(eqx.EquinoxRuntimeError,
                           match=rf"`{fn}\(controller=\.\.\.\)` must have finite parameters"):
            jax.block_until_ready(call(bad))
    # a leaf set to a Python float is a parameter too
    floating = eqx.tree_at(lambda c: c.log_kv, fdjax.DoubleLoop(), float("nan"))
    with pytest.raises(ValueError, match=r"`check_stability\(controller=\.\.\.\)` must have "
                                         r"finite parameters, got nan in \.log_kv"):
        fdjax.check_stability(floating, drive, position_m=0.3)
    # the certificate of no position certifies nothing
    with pytest.raises(ValueError, match=r"`certify\(positions_m=\.\.\.\)` must be a 1-D array "
                                         r"of at least one position, got shape \(0,\)"):
        fdjax.certify(fdjax.DoubleLoop(), drive, [])


def test_a_scheduled_controller_on_measured_frfs():
    """An FRF plant: each FRF's loop runs the schedule's controller at its own position, as
    the fixed controller there does (the law of a schedule takes one position; it used to get
    the batch's positions and fail)."""
    drive = fdjax.reference_drive()
    designs, _ = fdjax.load_designs()
    f = np.geomspace(1.0, 3000.0, 200)
    y = np.array([0.2, 0.45])
    H = drive.frf(y, f)
    kw = dict(screw_ratio=drive.screw.ratio, method=fdjax.Continuous())
    for name in ("mcm_ata_e2e", "mcm_interp"):
        sched = designs[name]
        both = fdjax.loop_margins(sched, H, f, position_m=y, **kw)
        for i, p in enumerate(y):
            one = fdjax.loop_margins(sched.controller(p), H[i], f, position_m=p, **kw)
            # the same arithmetic in another compiled program: round-off
            np.testing.assert_allclose(both.speed.phase_margin_deg[i],
                                       one.speed.phase_margin_deg, rtol=1e-10)
            np.testing.assert_allclose(both.position.modulus_margin[i],
                                       one.position.modulus_margin, rtol=1e-10)


def test_a_twin_of_a_non_physical_drive_is_refused():
    """A negative saddle mass (set past the constructor's check) gave a twin of NaN matrices
    without a word; the eager call now names the value, by the constructor's own check."""
    drive = eqx.tree_at(lambda d: d.carriage.mass, fdjax.reference_drive(),
                        jnp.asarray(-1000.0))
    with pytest.raises(ValueError, match=r"^`Carriage\(mass=\.\.\.\)` must be finite and "
                                         r"positive, got -1000 \(in the model given to "
                                         r"`state_space`\)$"):
        fdjax.state_space(drive, 0.3)


def test_a_bore_as_wide_as_the_screw_is_refused_under_vmap_and_tree_at():
    """A traced bore skips the constructor's check; the twin of a bore at least as wide as the
    screw was NaN matrices without a word (under vmap) and the FRF's error named a Rod.  The
    twin and the screw's rods now check it, under vmap and jit and after eqx.tree_at (eagerly,
    with the values, where the screw is concrete)."""
    drive = fdjax.reference_drive()
    opts = fdjax.TwinOptions(kept_modes=6)
    d = float(drive.screw.diameter)

    def bored(b):
        return eqx.tree_at(lambda dr: dr.screw.bore_diameter, drive, b)

    match = r"`Screw\(bore_diameter=\.\.\.\)` must be smaller than the diameter"
    ok = jax.vmap(lambda b: fdjax.state_space(bored(b), 0.3, twin=opts).A)(jnp.array([0.03]))
    assert np.all(np.isfinite(ok))
    for b in (d, 1.2 * d):
        with pytest.raises(eqx.EquinoxRuntimeError, match=match):
            jax.block_until_ready(jax.vmap(lambda b: fdjax.state_space(
                bored(b), 0.3, twin=opts).A)(jnp.array([0.03, b])))
        with pytest.raises(eqx.EquinoxRuntimeError, match=match):
            jax.block_until_ready(eqx.filter_jit(lambda b: bored(b).frf(
                0.3, FREQ))(jnp.asarray(b)))
        # eager, with the values: by the screw's own check, and where the drive is used
        with pytest.raises(ValueError, match=match + rf" {d:g} m, got {b:g}"):
            bored(jnp.asarray(b)).screw.torsion()
        with pytest.raises(ValueError, match=match + rf" {d:g} m, got {b:g} \(in the model "
                                                     r"given to `BallScrewDrive\.frf`\)"):
            bored(jnp.asarray(b)).frf(0.3, FREQ)
    # a concrete drive's modes are counted eagerly inside a trace: no check is staged there
    assert fdjax.count_modes(bored(jnp.asarray(0.03))) >= 1


def test_identify_modes_without_an_order_inside_jit_says_what_to_give():
    """The order is chosen eagerly (the stabilisation diagram); traced data used to fail with
    JAX's TracerArrayConversionError."""
    f = np.geomspace(20.0, 3000.0, 300)
    h = jnp.asarray(np.asarray(fdjax.reference_drive().frf(0.3, f))[..., 1, 0].ravel())
    with pytest.raises(ValueError, match=r"`identify_modes\(n_modes=\.\.\.\)` is required inside "
                                         r"jit, vmap or grad"):
        eqx.filter_jit(lambda h: fdjax.identify_modes(f, h).frequency_hz)(h)


def test_a_schedule_names_the_callers_position():
    """A schedule built for 200–600 mm, asked at 650 mm (inside the drive's travel): each
    entry point refuses it eagerly with its own argument and the value (the network's check
    inside the compiled program named only ScheduledLoop.controller); an FRF plant needs the
    position, one per FRF."""
    drive = fdjax.reference_drive()
    base = fdjax.load_designs()[0]["mcm_ata_e2e"]
    narrow = fdjax.ScheduledLoop(base.loop, fdjax.ATANetwork((0.2, 0.6), width=4), base.bounds)
    ref = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    f = np.geomspace(1.0, 3000.0, 50)
    travel = r"must be inside the network's travel \[0\.2, 0\.6\] m, got 0\.65"
    for fn, call in (
            ("check_stability", lambda: fdjax.check_stability(narrow, drive, position_m=0.65)),
            ("loop_margins", lambda: fdjax.loop_margins(narrow, drive, f, position_m=0.65)),
            ("simulate", lambda: fdjax.simulate(narrow, drive, ref, position_m=0.65))):
        with pytest.raises(ValueError, match=rf"`{fn}\(position_m=\.\.\.\)` {travel}"):
            call()
    with pytest.raises(ValueError, match=rf"`certify\(positions_m=\.\.\.\)` {travel}"):
        fdjax.certify(narrow, drive, [0.3, 0.65])
    H = drive.frf(np.array([0.3]), f)
    kw = dict(screw_ratio=drive.screw.ratio, method=fdjax.Continuous())
    with pytest.raises(ValueError, match=r"`loop_margins\(position_m=\.\.\.\)` is required: the "
                                         r"schedule's law depends on the table position"):
        fdjax.loop_margins(narrow, H, f, **kw)
    with pytest.raises(ValueError, match=r"`loop_margins\(position_m=\.\.\.\)` must be one "
                                         r"position per FRF, shape \(1,\) .* got shape \(2,\)"):
        fdjax.loop_margins(narrow, H, f, position_m=[0.3, 0.4], **kw)
    with pytest.raises(ValueError, match=r"`loop_margins\(position_m=\.\.\.\)` must be inside "
                                         r"the network's travel .* 300 mm is 0\.3 m"):
        fdjax.loop_margins(narrow, H, f, position_m=300.0, **kw)
    # a twin built at 650 mm: the schedule is checked at the twin's position (the error came
    # from inside the compiled program, without the value)
    twin = fdjax.state_space(drive, 0.65, twin=fdjax.TwinOptions(kept_modes=4))
    with pytest.raises(ValueError, match=r"`check_stability\(plant=\.\.\.\)\.position_m` "
                                         + travel):
        fdjax.check_stability(narrow, twin)
    # a 1 mm grid built by np.arange ends at 0.7000000000000005: the end of the travel
    grid = np.arange(0.1, 0.7 + 1e-3, 1e-3)
    assert grid[-1] > 0.7
    np.testing.assert_array_equal(drive._check_travel(grid[-2:], "certify", "positions_m"),
                                  grid[-2:])
    with pytest.raises(ValueError, match=r"got 0\.700001 at index 0"):
        drive._check_travel([0.700001], "certify", "positions_m")


def test_a_filter_above_nyquist_is_named_by_the_function_called():
    """A notch at 4.5 kHz on an 8 kHz servo: the discretisation raised inside the compiled
    program ("MCM.discretize(dt=...)", without the values); each entry point now names its
    controller argument, the filter and the Nyquist frequency, before any work."""
    drive = fdjax.reference_drive()
    c = fdjax.reference_controller(drive)
    bad = eqx.tree_at(lambda x: x.mcm, c, fdjax.MCM(c.mcm.peak, fdjax.NotchFilter(
        2 * np.pi * 4500.0, 0.01, 0.3)))
    f = np.geomspace(5.0, 3900.0, 50)
    msg = (r"`{}\(controller=\.\.\.\)` has a filter at 4500 Hz, not below the Nyquist frequency "
           r"4000 Hz of the servo that samples it \(period 0\.000125 s\)")
    for fn, call in (("loop_margins", lambda: fdjax.loop_margins(bad, drive, f, position_m=0.3)),
                     ("check_stability", lambda: fdjax.check_stability(bad, drive,
                                                                       position_m=0.3)),
                     ("simulate", lambda: fdjax.simulate(bad, drive, fdjax.reciprocating(),
                                                         position_m=0.3))):
        with pytest.raises(ValueError, match=msg.format(fn)):
            call()
    # a faster servo (Nyquist 5 kHz) samples it: the check runs, with a finite growth rate
    fast = fdjax.Servo(period=1e-4)
    assert np.isfinite(float(fdjax.check_stability(bad, drive, position_m=0.3,
                                                   servo=fast).growth_rate))


def test_controllers_checked_where_their_values_are_traced():
    """Checks a constructor makes eagerly, made again where the values are traced: a PID's
    derivative corner inside a user's law (margins came out for an unstable filter), an
    interpolated schedule's position in mm under jit (the end design ran); a servo's period
    given as a NumPy or JAX scalar is a number (it was refused as not a number)."""
    drive = fdjax.reference_drive()
    twin = fdjax.state_space(drive, 0.3, twin=fdjax.TwinOptions(kept_modes=4))

    class MyPID(fdjax.AbstractController):
        wd: jax.Array

        def law(self, position_m):
            return fdjax.Law((fdjax.Path({"r": 1.0, "x2": -1.0},
                                         (fdjax.PID(1.5e3, 5e3, 100.0, self.wd),)),))

    f = np.geomspace(1.0, 3000.0, 200)
    fdjax.loop_margins(MyPID(jnp.asarray(2 * np.pi * 150.0)), twin, f)
    with pytest.raises(CHECK_FAILED, match=r"`PID\(wd=\.\.\.\)` must be positive"):
        jax.block_until_ready(fdjax.loop_margins(MyPID(jnp.asarray(-2 * np.pi * 150.0)), twin,
                                                 f).plant_input.gain_margin_db)
    designs = fdjax.load_designs()[0]
    interp = designs["mcm_interp"]
    with pytest.raises(CHECK_FAILED, match=r"`InterpolatedLoop\.controller\(position_m=\.\.\.\)` "
                                           r"must be a table position in metres .* given in mm"):
        jax.block_until_ready(jax.jit(lambda y: interp.controller(y).mcm.peak.omega)(300.0))
    np.testing.assert_array_equal(jax.jit(lambda y: interp.controller(y).mcm.peak.omega)(0.3),
                                  interp.controller(0.3).mcm.peak.omega)
    for period in (np.float32(1e-4), jnp.float64(1.25e-4), np.float64(2e-4)):
        servo = fdjax.Servo(period=period)
        assert type(servo.period) is float and servo.period == float(period)


def test_a_position_in_mm_under_jit_says_so():
    """Traced, the value cannot be printed, but the mm hint can still be given: the check
    picks the sentence by whether the value lies inside once divided by 1000."""
    drive = fdjax.reference_drive()
    frf = eqx.filter_jit(lambda y: drive.frf(y, jnp.geomspace(10.0, 100.0, 3)))
    with pytest.raises(CHECK_FAILED, match=r"`BallScrewDrive\.frf\(position_m=\.\.\.\)` must be "
                                           r"inside the travel \[0\.1, 0\.7\] m; table "
                                           r"positions are in metres \(the value lies inside "
                                           r"once divided by 1000: it was given in mm\)"):
        jax.block_until_ready(frf(jnp.asarray([300.0])))
    with pytest.raises(CHECK_FAILED, match=r"`BallScrewDrive\.frf\(position_m=\.\.\.\)` must be "
                                           r"inside the travel \[0\.1, 0\.7\] m") as info:
        jax.block_until_ready(frf(jnp.asarray([0.9])))
    assert "given in mm" not in str(info.value)
    # under vmap each position picks its sentence: a position inside (which would lie outside
    # once divided by 1000) no longer gives the hint to another that is merely outside
    batched = jax.vmap(lambda y: drive.frf(y, jnp.geomspace(10.0, 100.0, 3)))
    with pytest.raises(CHECK_FAILED, match=r"must be inside the travel") as info:
        jax.block_until_ready(batched(jnp.asarray([0.2, 0.8])))
    assert "given in mm" not in str(info.value)
    with pytest.raises(CHECK_FAILED, match=r"it was given in mm"):
        jax.block_until_ready(batched(jnp.asarray([0.2, 300.0])))


def test_tuners_name_a_bad_optimiser_and_pid_corner():
    """An optimiser given by name, not as an optax transformation, is named by the tuner
    (it failed on an attribute inside optax); a PID's derivative corner must be positive (a
    negative one puts the filter's pole in the right half-plane); smooth_max and descend
    refuse what they cannot reduce."""
    drive = fdjax.reference_drive()
    start = fdjax.reference_controller(drive)
    par = fdjax.DoubleLoopParameterisation(fdjax.MCMBounds.for_servo(fdjax.Servo()), start)
    obj = fdjax.tuning_objective()
    with pytest.raises(TypeError, match=r"`tune_local\(optimiser=\.\.\.\)` must be an optax "
                                        r"GradientTransformation \(e\.g\. optax\.adam\(0\.02\)\), "
                                        r"got 'adam'"):
        fdjax.tune_local(par, obj, drive, [0.3], start, optimiser="adam")
    with pytest.raises(ValueError, match=r"`PID\(wd=\.\.\.\)` must be positive \(the derivative "
                                         r"filter's corner, rad/s\), got -10"):
        fdjax.PID(1.0, 1.0, 1.0, -10.0)
    with pytest.raises(ValueError, match=r"`smooth_max\(values=\.\.\.\)` must be a non-empty 1-D "
                                         r"array, got shape \(0,\)"):
        fdjax.smooth_max(jnp.zeros(0), 10.0)
    with pytest.raises(ValueError, match=r"`descend\(steps=\.\.\.\)` must be an integer at least "
                                         r"1, got 0"):
        fdjax.descend(lambda p: (p**2, p), jnp.ones(()), None, 0)


def test_a_motion_out_of_the_travel_is_refused_before_the_run():
    """The trajectory's exact extremes are checked against the travel before anything is
    compiled; a stroke typed in mm (5 for 5 mm) says so, a real overrun does not."""
    drive = fdjax.reference_drive()
    loop = fdjax.DoubleLoop()
    mm = fdjax.reciprocating(stroke=5.0, v_max=10.0, a_max=100.0, j_max=1e4)
    with pytest.raises(ValueError, match=r"`simulate\(reference=\.\.\., position_m=\.\.\.\)`: the "
                                         r"reference motion from table position 0\.115 m reaches "
                                         r"5\.115 m, outside the travel \[0\.1, 0\.7\] m; motions "
                                         r"are in metres: a move of 5 mm is 0\.005 m"):
        fdjax.simulate(loop, drive, mm, position_m=0.115)
    with pytest.raises(ValueError, match=r"reaches 0\.815 m, outside the travel \[0\.1, 0\.7\] "
                                         r"m$"):
        fdjax.simulate(loop, drive, fdjax.reciprocating(stroke=0.7), position_m=0.115)
    # a run of part of the motion is judged by the positions it runs through, eagerly as under
    # jit (eagerly the whole motion's reach refused it): 10 ms of a 5 mm stroke from 0.698 m
    move = fdjax.reciprocating(stroke=5e-3, v_max=0.1, a_max=2.0, j_max=200.0)
    run = lambda p: fdjax.simulate(loop, drive, move, position_m=p, duration=0.01)  # noqa: E731
    eager, jitted = run(0.698), eqx.filter_jit(run)(0.698)
    assert eager.message == jitted.message == "simulation ok at table position 0.698 m"
    np.testing.assert_allclose(float(eager.rms_error()), float(jitted.rms_error()), rtol=1e-12)
    assert float(np.max(eager.position_m)) < 0.7
    with pytest.raises(ValueError, match=r"reaches 0\.703 m, outside the travel"):
        fdjax.simulate(loop, drive, move, position_m=0.698)


def test_a_motion_built_inside_jit_says_what_to_give():
    """A motion built inside the user's jitted function has a traced duration, which cannot
    set the run's number of samples: the error names the reference and what to give (the
    motion built outside, or the duration), not an argument the user never passed."""
    drive = fdjax.reference_drive()
    loop = fdjax.reference_controller(drive)
    run = eqx.filter_jit(lambda p: fdjax.simulate(loop, drive, fdjax.reciprocating(),
                                                  position_m=p).rms_error())
    with pytest.raises(ValueError, match=r"`simulate\(reference=\.\.\.\)` was built inside, or "
                                         r"passed into, a traced function .* build the motion "
                                         r"outside and close over it, or give "
                                         r"`simulate\(duration=\.\.\.\)` as a number"):
        run(0.3)
    # passed in as an argument: the same sentence
    move = fdjax.reciprocating()
    with pytest.raises(ValueError, match=r"`simulate\(reference=\.\.\.\)` was built inside, or "
                                         r"passed into, a traced function"):
        eqx.filter_jit(lambda m: fdjax.simulate(loop, drive, m, position_m=0.3).rms_error())(move)


def test_batches_of_twins_and_frf_arrays_where_a_model_is_needed():
    """simulate takes one twin (a batch is named, with what to do); gain_headroom gives g per
    twin of a batch, as per position of a drive, and names its own arguments; the closed
    loop's poles refuse an FRF array as such."""
    drive = fdjax.reference_drive()
    loop = fdjax.reference_controller(drive)
    opts = fdjax.TwinOptions(kept_modes=4)
    twins = jax.vmap(lambda p: fdjax.state_space(drive, p, twin=opts))(jnp.array([0.2, 0.6]))
    with pytest.raises(ValueError, match=r"`simulate\(plant=\.\.\.\)` must be the twin at one "
                                         r"position .*got a batch of twins \(A of shape "
                                         r"\(2, 8, 8\)\): jax\.vmap"):
        fdjax.simulate(loop, twins, fdjax.reciprocating())
    g_batch = fdjax.gain_headroom(loop, twins, rtol=0.05)
    g_drive = fdjax.gain_headroom(loop, drive, position_m=[0.2, 0.6], twin=opts, rtol=0.05)
    assert g_batch.shape == (2,) and g_batch[0] > 1 and g_batch[1] == 0.0  # unstable at 0.6 m
    np.testing.assert_array_equal(g_batch, g_drive)
    with pytest.raises(ValueError, match=r"`gain_headroom\(position_m=\.\.\.\)` is only for a "
                                         r"BallScrewDrive"):
        fdjax.gain_headroom(loop, twins, position_m=0.2)
    frf = np.ones((16, 3, 2), complex)
    for fn in (fdjax.check_stability, fdjax.closed_loop):
        with pytest.raises(TypeError, match=rf"`{fn.__name__}\(plant=\.\.\.\)` must be a drive "
                                            r"or a StateSpace, not an FRF array \(shape "
                                            r"\(16, 3, 2\)\)"):
            fn(loop, frf)


def test_a_shared_discretisation_serves_its_own_design_only():
    """SampledData.sharing holds one design's discretisation around one twin: the closed loop,
    the margins and the run of that design use it; another plant kind, twin or controller is
    refused (it used to run the shared law with the other's plant, e.g. a stable verdict at
    0.6 m that was 0.115 m's)."""
    drive = fdjax.reference_drive()
    ref = fdjax.reference_controller(drive)
    opts = fdjax.TwinOptions(kept_modes=4)
    twin = fdjax.state_space(drive, 0.115, twin=opts)
    shared = fdjax.SampledData().sharing(ref, twin, fdjax.Servo())
    own = fdjax.check_stability(ref, twin, method=shared)
    plain = fdjax.check_stability(ref, twin)
    np.testing.assert_allclose(own.growth_rate, plain.growth_rate, rtol=1e-12)
    with pytest.raises(ValueError, match=r"`check_stability\(method=\.\.\.\)` holds the "
                                         r"discretisation of one design around one twin"):
        fdjax.check_stability(ref, drive, position_m=[0.115, 0.6], method=shared, twin=opts)
    other = r"holds the discretisation of another design, twin or servo"
    with pytest.raises(ValueError, match=r"`check_stability\(method=\.\.\.\)` " + other):
        fdjax.check_stability(fdjax.DoubleLoop(), twin, method=shared)
    with pytest.raises(ValueError, match=r"`simulate\(method=\.\.\.\)` " + other):
        fdjax.simulate(ref, fdjax.state_space(drive, 0.6, twin=opts), fdjax.reciprocating(),
                       shared)
    # traced arguments cannot be compared with it: under jit another twin ran the shared
    # one's, under grad the gradient through it was zero; refused when it is traced
    motion = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    traced = r"`simulate\(method=\.\.\.\)` holds a discretisation built outside this traced "
    with pytest.raises(ValueError, match=traced):
        eqx.filter_jit(lambda p: fdjax.simulate(ref, p, motion, shared).rms_error())(
            fdjax.state_space(drive, 0.6, twin=opts))
    with pytest.raises(ValueError, match=traced + r".*gradient through it would be zero"):
        eqx.filter_grad(lambda c: fdjax.simulate(c, twin, motion, shared).rms_error())(ref)
    # built inside the traced function it follows the design: its gradient against central
    # differences of the plain run (measured 1.4e-9 relative at h = 1e-4)
    g_shared = eqx.filter_grad(lambda c: fdjax.simulate(
        c, twin, motion, fdjax.SampledData().sharing(c, twin, fdjax.Servo())).rms_error())(ref)
    rms = lambda d: float(fdjax.simulate(  # noqa: E731
        eqx.tree_at(lambda c: c.log_kv, ref, ref.log_kv + d), twin, motion).rms_error())
    fd = (rms(1e-4) - rms(-1e-4)) / 2e-4
    np.testing.assert_allclose(float(g_shared.log_kv), fd, rtol=1e-8)
    assert fd != 0.0


def test_a_dead_channel_is_refused_under_vmap_too():
    """The check a concrete FRF gets, made again where it is traced: a channel that is zero
    at every frequency (NaN frequencies, or a solver's unnamed error)."""
    drive = fdjax.reference_drive()
    f = np.geomspace(20.0, 3000.0, 400)
    H = np.array(drive.frf(np.array([0.3, 0.4]), f))[:, :, :, 0]
    H[1, :, 2] = 0.0  # the tool point's channel dead at the second position
    fit = fdjax.identify_modes(f, H[0], 4)
    with pytest.raises(eqx.EquinoxRuntimeError, match=r"`identify_modes\(frf=\.\.\.\)` must not "
                                                      r"have a channel that is zero"):
        jax.block_until_ready(jax.vmap(lambda h: fdjax.identify_modes(
            f, h, 4, initial=fit, throw=False).frequency_hz)(jnp.asarray(H)))
