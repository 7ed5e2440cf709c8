"""Every check of the model side behaves under jit (and vmap, grad) as it does eagerly.

A value-range check on a traced value is an ``eqx.error_if`` whose result is the value that flows
on; a discarded one vanishes from the compiled program.  Each test here traces the guarded
argument and expects the check's own message when the program runs; the eager ValueError with
the offending value is tested alongside.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jit_errors import CHECK_FAILED

import fdjax
from fdjax._drive import ModalData, drive_modes

W = 2 * np.pi * np.array([50.0, 150.0])
FREQ = np.array([20.0, 150.0])


def _raises(match, fn, *args):
    with pytest.raises(CHECK_FAILED, match=match):
        jax.block_until_ready(fn(*args))


@pytest.fixture(scope="module")
def drive():
    return fdjax.table1_drive()


# ------------------------------------------------------------------------------------ rods
def test_rod_points_under_jit_and_vmap():
    rod = fdjax.Rod.axial(diameter=0.03, length=1.2, loss_factor=0.01)
    f = jax.jit(lambda p: rod.frf(FREQ, p))
    assert f(jnp.array([0.3, 0.9])).shape == (2, 2, 2)
    # outside [0, L]: without the check this built a negative-length segment
    _raises(r"`Rod\.frf\(points_m=\.\.\.\)` must be within \[0, L\]", f, jnp.array([0.3, 1.5]))
    _raises(r"`Rod\.frf\(points_m=\.\.\.\)` must be within \[0, L\]", f, jnp.array([-0.1, 0.3]))
    # traced points cannot be sorted or merged in Python: unsorted, repeated or end points
    # would make zero- or negative-length segments
    _raises(r"`Rod\.frf\(points_m=\.\.\.\)` must be strictly increasing", f,
            jnp.array([0.9, 0.3]))
    _raises(r"must be strictly increasing and strictly inside \(0, L\)", f, jnp.array([0.0, 0.3]))
    batch = jax.vmap(lambda p: rod.frf(FREQ, p))
    assert batch(jnp.array([[0.3], [0.6]])).shape == (2, 2, 1, 1)
    _raises(r"`Rod\.frf\(points_m=\.\.\.\)` must be within", batch, jnp.array([[0.3], [1.3]]))
    # eagerly the value and index
    with pytest.raises(ValueError, match=r"`Rod\.frf\(points_m=\.\.\.\)` must be within "
                                         r"\[0, 1\.2\] m, got 1\.5 at index 1"):
        rod.frf(FREQ, [0.3, 1.5])


def test_rod_receptance_and_wave_quantities_under_jit():
    rod = fdjax.Rod.axial(diameter=0.03, length=1.2, loss_factor=0.01)
    g = jax.jit(lambda w: fdjax.rod_receptance(rod, w, [0.3]))
    _raises(r"`rod_receptance\(omega=\.\.\.\)` must be finite", g, jnp.array([100.0, jnp.nan]))
    h = jax.jit(lambda p: fdjax.rod_receptance(rod, jnp.array([100.0]), p))
    _raises(r"`rod_receptance\(points_m=\.\.\.\)` must be within", h, jnp.array([2.0]))
    # grad w.r.t. the length: the points must stay inside the traced rod
    mag = lambda L: jnp.abs(fdjax.rod_receptance(
        fdjax.Rod.axial(diameter=0.03, length=L, loss_factor=0.01), jnp.array([700.0]), [0.3]
    )[0, 0, 0])
    fd = (float(mag(1.2 + 1e-5)) - float(mag(1.2 - 1e-5))) / 2e-5
    np.testing.assert_allclose(float(jax.grad(mag)(1.2)), fd, rtol=5e-9)  # measured 4.3e-10
    _raises(r"`rod_receptance\(points_m=\.\.\.\)` must be within", jax.grad(mag), 0.2)
    nan = jnp.asarray(jnp.nan)
    _raises(r"`Rod\.impedance\(omega=\.\.\.\)` must be finite",
            jax.jit(lambda w: rod.impedance(w)), nan)
    _raises(r"`Rod\.complex_stiffness\(omega=\.\.\.\)` must be finite",
            jax.jit(lambda w: rod.complex_stiffness(w)), nan)
    _raises(r"`Rod\.segment_stiffness\(length=\.\.\.\)` must be finite and positive",
            jax.jit(lambda a: rod.segment_stiffness(100.0, a)), -0.1)
    _raises(r"`Support\.dynamic_stiffness\(omega=\.\.\.\)` must be finite",
            jax.jit(lambda w: fdjax.Support(stiffness=1e6).dynamic_stiffness(w)), nan)
    _raises(r"`Rod\.axial\(length=\.\.\.\)` must be finite and positive",
            jax.jit(lambda L: fdjax.Rod.axial(diameter=0.03, length=L).length), -1.0)


# ------------------------------------------------------------------------------------ lumped
def test_lumped_model_under_jit():
    model = fdjax.three_mass()

    def build(k):
        return fdjax.LumpedModel(model.mass, model.stiffness.at[0, 0].set(k),
                                 model.damping).frf(FREQ)

    # the finiteness check now lives in the field converter (it was a discarded result in
    # __check_init__, so a NaN matrix passed jit unnoticed)
    _raises(r"`LumpedModel\(stiffness=\.\.\.\)` must be finite", jax.jit(build), jnp.nan)
    with pytest.raises(ValueError, match=r"`LumpedModel\(stiffness=\.\.\.\)` must be finite"):
        fdjax.LumpedModel(model.mass, model.stiffness.at[0, 0].set(np.inf), model.damping)
    _raises(r"`LumpedModel\.receptance\(omega=\.\.\.\)` must be finite",
            jax.jit(lambda w: model.receptance(w)), jnp.array([1.0, jnp.nan]))
    _raises(r"`LumpedModel\.dynamic_stiffness\(omega=\.\.\.\)` must be finite",
            jax.jit(lambda w: model.dynamic_stiffness(w)), jnp.inf)
    # a free chain at ω = 0 is singular: an error, not inf/NaN
    _raises(r"`LumpedModel\.receptance\(\.\.\.\)` produced a non-finite result",
            jax.jit(lambda w: model.receptance(w)), 0.0)
    _raises(r"`chain_model\(masses=\.\.\.\)` must be finite and positive",
            jax.jit(lambda m: fdjax.chain_model(m, [1e7], [0.0]).mass), jnp.array([1.0, -2.0]))
    batch = jax.vmap(lambda c: fdjax.chain_model([1.0, 2.0], [1e7], c).damping)
    _raises(r"`chain_model\(dampings=\.\.\.\)` must be finite and non-negative", batch,
            jnp.array([[1.0], [-1.0]]))


# ------------------------------------------------------------------------------------ coupling
def test_coupling_under_jit():
    Y = jnp.eye(2, dtype=jnp.complex128)[None] * 1e-6
    B = np.array([[-1.0, 1.0]])
    _raises(r"`couple\(receptance=\.\.\.\)` must be finite",
            jax.jit(lambda y: fdjax.couple(y, B)), Y.at[0, 0, 0].set(jnp.nan))
    _raises(r"`couple\(interface=\.\.\.\)` must be finite",
            jax.jit(lambda b: fdjax.couple(Y, b)), jnp.array([[jnp.inf, 1.0]]))
    _raises(r"`couple\(joint=\.\.\.\)` must be finite",
            jax.jit(lambda j: fdjax.couple(Y, B, j)), jnp.full((1, 1, 1), jnp.nan + 0j))
    _raises(r"`joint_receptance\(stiffness=\.\.\.\)` must be finite and positive",
            jax.jit(lambda k: fdjax.joint_receptance(k, 1e3, W)), -1.0)
    _raises(r"`joint_receptance\(damping=\.\.\.\)` must be finite and non-negative",
            jax.jit(lambda c: fdjax.joint_receptance(1e8, c, W)), -1.0)
    _raises(r"`joint_receptance\(omega=\.\.\.\)` must be finite",
            jax.jit(lambda w: fdjax.joint_receptance(1e8, 1e3, w)), jnp.nan)


# ------------------------------------------------------------------------------------ drive
RECEPTANCE_METHODS = [
    "receptance", "receptance_entries", "coupled_receptance", "receptance_direct",
    "substructure_receptances",
]


@pytest.mark.parametrize("method", RECEPTANCE_METHODS)
@pytest.mark.parametrize("y, shown", [
    (115.0, r"115; table positions are in metres: 115 mm is 0\.115 m"),  # mm typed as m
    (-3.0, "-3"), (np.nan, "nan")])
def test_drive_pointwise_methods_check_positions_eagerly(drive, method, y, shown):
    """115 (mm typed as m: the message says so), a negative position and NaN returned numbers
    or NaN before."""
    with pytest.raises(ValueError, match=rf"`BallScrewDrive\.{method}\(position_m=\.\.\.\)` "
                                         rf"must be inside the travel \[0\.1, 0\.7\] m, "
                                         rf"got {shown}$"):
        getattr(drive, method)(y, W)
    with pytest.raises(ValueError, match=rf"`BallScrewDrive\.{method}\(omega=\.\.\.\)` must be "
                                         r"finite"):
        getattr(drive, method)(0.4, np.array([1.0, np.inf]))


@pytest.mark.parametrize("method", RECEPTANCE_METHODS)
def test_drive_pointwise_methods_check_positions_under_jit(drive, method):
    f = jax.jit(lambda y: getattr(drive, method)(y, W))
    jax.block_until_ready(f(0.4))
    _raises(rf"`BallScrewDrive\.{method}\(position_m=\.\.\.\)` must be inside the travel "
            r"\[0\.1, 0\.7\] m", f, 0.9)
    _raises(rf"`BallScrewDrive\.{method}\(position_m=\.\.\.\)` must be inside the travel", f,
            jnp.nan)
    _raises(rf"`BallScrewDrive\.{method}\(omega=\.\.\.\)` must be finite",
            jax.jit(lambda w: getattr(drive, method)(0.4, w)), jnp.nan)


def test_receptance_grad_and_vmap(drive):
    """The README's example keeps working under grad; out of the travel it raises."""
    mag = lambda y: jnp.abs(drive.receptance(y, 2 * jnp.pi * 150.0)[1, 0])
    g = jax.grad(mag)(0.4)
    h = 1e-5  # measured 2.3e-9 (2.3e-8 with h = 1e-6: round-off)
    np.testing.assert_allclose(float(g), (float(mag(0.4 + h)) - float(mag(0.4 - h))) / (2 * h),
                               rtol=2e-8)
    _raises(r"`BallScrewDrive\.receptance\(position_m=\.\.\.\)` must be inside", jax.grad(mag),
            0.75)
    batch = jax.vmap(mag)
    assert batch(jnp.array([0.2, 0.5])).shape == (2,)
    _raises(r"`BallScrewDrive\.receptance\(position_m=\.\.\.\)` must be inside", batch,
            jnp.array([0.2, 0.05]))
    # ω = 0 is the rigid-body pole: an error, not inf
    with pytest.raises(ValueError, match=r"`BallScrewDrive\.receptance\(\.\.\.\)` produced a "
                                         r"non-finite result"):
        drive.receptance(0.4, 0.0)


def test_frf_and_frf_direct_under_jit(drive):
    for name in ("frf", "frf_direct"):
        f = jax.jit(lambda y, name=name: getattr(drive, name)(y, FREQ))
        _raises(rf"`BallScrewDrive\.{name}\(position_m=\.\.\.\)` must be inside the travel", f,
                jnp.array([0.3, 0.95]))
        with pytest.raises(ValueError, match=rf"`BallScrewDrive\.{name}\(position_m=\.\.\.\)` "
                                             r"must be inside the travel \[0\.1, 0\.7\] m, "
                                             r"got 0\.8 at index 1"):
            getattr(drive, name)([0.3, 0.8], FREQ)


def test_nut_offset_and_nut_inside_the_screw_under_jit(drive):
    # finite nut_offset: a field converter (the check in __check_init__ was discarded)
    def build(l0):
        d = fdjax.BallScrewDrive(drive.screw, drive.rotary, drive.axial, drive.carriage,
                                 drive.nut, nut_offset=l0, travel_m=drive.travel_m)
        return d.receptance(0.4, W)

    _raises(r"`BallScrewDrive\(nut_offset=\.\.\.\)` must be finite", jax.jit(build), jnp.nan)
    # a traced nut_offset that puts the nut past the screw's end (caught eagerly at
    # construction when concrete) is caught per position by every public method
    f = jax.jit(lambda l0: eqx.tree_at(lambda d: d.nut_offset, drive, l0).receptance(0.6, W))
    jax.block_until_ready(f(0.15))
    _raises(r"`BallScrewDrive\.receptance\(position_m=\.\.\.\)` must be such that the nut lies "
            r"inside the screw", f, 0.5)


def test_substructures_under_jit(drive):
    shaft, rod = drive.screw.torsion(), drive.screw.axial()
    nan = jnp.asarray(jnp.nan)
    _raises(r"`Rotary\.receptance\(l=\.\.\.\)` must be strictly inside \(0, L\)",
            jax.jit(lambda l: drive.rotary.receptance(shaft, l, W)), 1.2)
    _raises(r"`Rotary\.line\(omega=\.\.\.\)` must be finite",
            jax.jit(lambda w: drive.rotary.line(shaft, 0.5, w)), nan)
    _raises(r"`Axial\.receptance\(l=\.\.\.\)` must be strictly inside \(0, L\)",
            jax.jit(lambda l: drive.axial.receptance(rod, l, W)), 0.0)
    _raises(r"`Axial\.line\(l=\.\.\.\)` must be strictly inside",
            jax.jit(lambda l: drive.axial.line(rod, l, W)), -0.2)
    _raises(r"`Carriage\.receptance\(omega=\.\.\.\)` must be finite",
            jax.jit(lambda w: drive.carriage.receptance(w)), nan)
    _raises(r"`Carriage\.modal_stiffness\(omega=\.\.\.\)` must be finite",
            jax.jit(lambda w: drive.carriage.modal_stiffness(w)), nan)
    _raises(r"`NutJoint\.dynamic_stiffness\(omega=\.\.\.\)` must be finite",
            jax.jit(lambda w: drive.nut.dynamic_stiffness(w)), nan)
    with pytest.raises(ValueError, match=r"`Rotary\.receptance\(l=\.\.\.\)` must be strictly "
                                         r"inside \(0, 1\) m, got 1\.2"):
        drive.rotary.receptance(shaft, 1.2, W)


# ------------------------------------------------------------------------------------ twin
def test_state_space_under_jit_and_vmap(drive):
    f = jax.jit(lambda y: fdjax.state_space(drive, y, twin=fdjax.TwinOptions(kept_modes=4)).A)
    _raises(r"`state_space\(position_m=\.\.\.\)` must be inside the travel", f, 0.05)
    batch = jax.vmap(lambda y: fdjax.state_space(drive, y, twin=fdjax.TwinOptions(kept_modes=4)).A)
    _raises(r"`state_space\(position_m=\.\.\.\)` must be inside the travel", batch,
            jnp.array([0.3, 0.71]))
    with pytest.raises(ValueError, match=r"`state_space\(position_m=\.\.\.\)` must be inside the "
                                         r"travel \[0\.1, 0\.7\] m, got nan"):
        fdjax.state_space(drive, np.nan, twin=fdjax.TwinOptions(kept_modes=4))
    with pytest.raises(TypeError, match=r"`TwinOptions\(residual=\.\.\.\)` must be a bool"):
        fdjax.TwinOptions(kept_modes=4, residual=1)
    with pytest.raises(ValueError, match=r"`count_modes\(n_positions=\.\.\.\)` must be an integer "
                                         r"at least 1, got 0"):
        fdjax.count_modes(drive, n_positions=0)
    with pytest.raises(ValueError, match=r"`fe_matrices\(drive=\.\.\.\)` must be a BallScrewDrive"):
        fdjax.fe_matrices(fdjax.three_mass(), 0.3)


# ------------------------------------------------------------------------------------ modes
def test_drive_modes_under_jit(drive):
    f = jax.jit(lambda y: drive_modes(drive, y, n_modes=2).frequency_hz)
    _raises(r"`drive_modes\(position_m=\.\.\.\)` must be inside the travel", f, 0.8)
    _raises(r"`drive_modes\(position_m=\.\.\.\)` must be inside the travel", f,
            jnp.array([0.3, 0.8]))
    with pytest.raises(ValueError, match=r"`drive_modes\(position_m=\.\.\.\)` must be inside the "
                                         r"travel \[0\.1, 0\.7\] m, got 0\.9$"):
        drive_modes(drive, 0.9, n_modes=2)
    with pytest.raises(ValueError, match=r"`drive_modes\(n_modes=\.\.\.\)` must be an integer "
                                         r"between 1 and 28, got 0"):
        drive_modes(drive, 0.3, n_modes=0)
    with pytest.raises(ValueError, match=r"`drive_modes\(output=\.\.\.\)` must be one of"):
        drive_modes(drive, 0.3, output="x9")
    g = jax.jit(lambda tol: fdjax.track_drive_modes(
        drive_modes(drive, np.array([0.2, 0.3]), n_modes=2), freq_tol=tol).frequency_hz)
    _raises(r"`track_drive_modes\(freq_tol=\.\.\.\)` must be finite and positive", g, -0.1)


def test_modal_data_under_jit():
    f = jax.jit(lambda z: ModalData([50.0, 90.0], z, [-90.0, -120.0]).damping_ratio)
    _raises(r"`ModalData\(damping_ratio=\.\.\.\)` must be finite and positive", f,
            jnp.array([0.1, -0.05]))
    with pytest.raises(ValueError, match=r"`ModalData\(frequency_hz=\.\.\.\)` must be finite and "
                                         r"positive, got 0 at index 1"):
        ModalData([50.0, 0.0], [0.1, 0.1], [-90.0, -120.0])
    with pytest.raises(ValueError, match=r"`ModalData\(phase_deg=\.\.\.\)` must be finite"):
        ModalData([50.0], [0.1], [np.nan])


def test_update_model_bad_arguments(drive):
    data = ModalData([50.0], [0.1], [-90.0])
    bounds = {"nut.damping": (50.0, 200.0)}
    cases = [
        (dict(position_m=0.9), r"`update_model\(position_m=\.\.\.\)` must be inside the travel"),
        (dict(tolerances=(0.03, -0.25, 15.0)),
         r"`update_model\(tolerances=\.\.\.\)` must be finite and positive, got -0\.25 at index 1"),
        (dict(tolerances=(0.03, 0.25)), r"`update_model\(tolerances=\.\.\.\)` must be \(freq"),
        (dict(visibility=1.5),
         r"`update_model\(visibility=\.\.\.\)` must be in \[0, 1\), got 1\.5"),
        (dict(n_modes=0), r"`update_model\(n_modes=\.\.\.\)` must be an integer between 1 and 28"),
        (dict(max_steps=-1), r"`update_model\(max_steps=\.\.\.\)` must be an integer at least 0"),
        (dict(output="x7"), r"`update_model\(output=\.\.\.\)` must be one of"),
        (dict(parameters={"travel_m": (0.1, 1.0)}),
         r"'travel_m' must be a scalar physical parameter"),
        (dict(parameters={"screw.loss_factor": (0.0, 0.1)}), r"enters no time-domain model"),
        (dict(parameters={"nut.damping": (50.0, "x")}), r"must be a \(lo, hi\) pair of numbers"),
        (dict(target=(50.0, 0.1, -90.0)), r"`update_model\(target=\.\.\.\)` must be a ModalData"),
    ]
    for kwargs, match in cases:
        args = dict(drive=drive, target=data, parameters=bounds, position_m=0.3)
        args.update(kwargs)
        with pytest.raises(ValueError, match=match):
            fdjax.update_model(**args)


# ------------------------------------------------------------------------------------ trajectory
def test_trajectory_under_jit_and_vmap():
    traj = fdjax.reciprocating()
    f = jax.jit(lambda t: traj.evaluate(t))
    _raises(r"`Trajectory\.evaluate\(t=\.\.\.\)` must be finite", f, jnp.array([0.1, jnp.nan]))
    _raises(r"`Trajectory\.sample\(t=\.\.\.\)` must be finite",
            jax.jit(lambda t: traj.sample(t)), jnp.inf)
    build = jax.vmap(lambda r0: fdjax.Trajectory(traj.t_knots, traj.jerk, r0).position_range())
    lo, hi = build(jnp.array([0.1, 0.2]))
    np.testing.assert_allclose(np.asarray(hi) - np.asarray(lo), 5e-3, rtol=1e-12)
    _raises(r"`Trajectory\(r0=\.\.\.\)` must be finite", build, jnp.array([0.1, jnp.nan]))
    _raises(r"`Trajectory\(jerk=\.\.\.\)` must be finite",
            jax.jit(lambda j: fdjax.Trajectory(traj.t_knots, j).position_range()),
            traj.jerk.at[3].set(jnp.nan))
    with pytest.raises(ValueError, match=r"`Trajectory\.evaluate\(t=\.\.\.\)` must be finite"):
        traj.evaluate(np.nan)
