"""The ATA scheduling network, the scheduled loop, and saving and loading a schedule."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jit_errors import CHECK_FAILED

import fdjax

BOUNDS = fdjax.MCMBounds.for_servo(fdjax.Servo())
POSITIONS = np.linspace(0.1, 0.7, 6)


def _local_designs():
    """Six smooth, distinct local designs (normalised parameters) over the travel."""
    y = (POSITIONS - 0.4) / 0.3
    return np.stack([0.5 + 0.3 * y, -0.2 + 0.4 * y ** 2, 0.8 - 0.1 * y, -0.3 * y,
                     1.7 - 0.5 * y, 1.0 + 0.2 * y, -0.7 + 0.1 * y ** 3], axis=1)


def _numpy_forward(net, positions):
    """The network's outputs at ``positions`` (m), computed in NumPy from its weights."""
    lo, hi = net.travel_m
    h = (2.0 * (np.asarray(positions) - lo) / (hi - lo) - 1.0)[:, None]
    layers = net.mlp.layers
    for k, layer in enumerate(layers):
        h = h @ np.asarray(layer.weight).T + np.asarray(layer.bias)
        if k < len(layers) - 1:
            h = 1.0 / (1.0 + np.exp(-h))
    return h


def test_network_shape():
    net = fdjax.ATANetwork((0.1, 0.7), width=8)
    assert net.width == 8 and net.mlp.depth == 2 and net.mlp.activation is jax.nn.sigmoid
    assert net.mlp.in_size == 1 and net.mlp.out_size == 7
    assert net(0.3).shape == (7,) and net(0.3).dtype == jnp.float64
    out = jax.vmap(net)(jnp.asarray(POSITIONS))
    np.testing.assert_allclose(out[2], net(POSITIONS[2]), rtol=1e-15)
    # the forward pass in NumPy: ŷ = 2(Y − Y_min)/(Y_max − Y_min) − 1, two sigmoid layers,
    # a linear output
    np.testing.assert_allclose(out, _numpy_forward(net, POSITIONS), rtol=1e-13, atol=1e-15)
    with pytest.raises(ValueError, match=r"in m, got \(100\.0, 700\.0\); table positions are "
                                         r"in metres: 700 mm is 0\.7 m"):
        fdjax.ATANetwork((100.0, 700.0))
    with pytest.raises(ValueError, match=r"`ATANetwork\(travel_m=\.\.\.\)` must be an increasing"):
        fdjax.ATANetwork((0.7, 0.1))


def test_backpropagation_fits_the_local_designs():
    targets = _local_designs()
    net0 = fdjax.ATANetwork((0.1, 0.7), width=8, key=jax.random.PRNGKey(3))
    net, history = fdjax.fit_network(net0, POSITIONS, targets, steps=4000)
    history = np.asarray(history)
    assert history.shape == (4000,) and np.all(np.isfinite(history))
    # the first loss is the start's: (1/n) Σ_i ‖θ(Y_i) − θ_i‖² of the untrained network
    start = np.mean(np.sum((_numpy_forward(net0, POSITIONS) - targets) ** 2, axis=1))
    np.testing.assert_allclose(history[0], start, rtol=1e-13)
    assert history[-1] < 1e-5 * history[0]       # measured 2.2e-6
    fitted = np.asarray(jax.vmap(net)(jnp.asarray(POSITIONS)))
    # 7 smooth targets at 6 points with 8+8 sigmoid neurons: measured max error 3.6e-3
    np.testing.assert_allclose(fitted, targets, atol=5e-3)
    with pytest.raises(ValueError, match=r"must have shapes \(n,\) and \(n, 7\)"):
        fdjax.fit_network(net0, POSITIONS, targets[:, :6])


def test_scheduled_loop_is_the_fixed_loop_at_each_position():
    net = fdjax.ATANetwork((0.1, 0.7), width=4, key=jax.random.PRNGKey(1))
    sched = fdjax.ScheduledLoop(fdjax.DoubleLoop(mcm=fdjax.reference_mcm()), net, BOUNDS)
    assert sched.loop.mcm.peak is None  # the loop carries the gains only
    y = 0.37
    fixed = sched.controller(y)
    theta = np.asarray(BOUNDS.from_mcm(fixed.mcm))
    np.testing.assert_allclose(theta, np.asarray(net(y)), rtol=1e-10, atol=1e-12)
    drive = fdjax.reference_drive()
    f = np.geomspace(10.0, 3000.0, 64)
    twin = fdjax.TwinOptions(kept_modes=6)

    # the open loop and its gradient in one compiled program (the loss, with the open loop as
    # its aux), reused below for the central differences: one program instead of three
    def loss(c):
        ol = fdjax.open_loop(c, drive, f, position_m=y, twin=twin)
        return jnp.sum(jnp.abs(ol.speed)), ol

    value_and_grad = eqx.filter_jit(eqx.filter_value_and_grad(loss, has_aux=True))
    (_, a), g = value_and_grad(sched)
    b = fdjax.open_loop(fixed, drive, f, position_m=y, twin=twin)
    # the same arithmetic in two compiled programs: measured 1.3e-15
    for k in ("plant_input", "speed", "position"):
        np.testing.assert_allclose(getattr(a, k), getattr(b, k), rtol=1e-13)
    # gradients reach the network's weights and the gains, not the hardware
    leaves = jax.tree_util.tree_leaves(g.network)
    assert leaves and all(np.all(np.isfinite(np.asarray(v))) for v in leaves)
    assert any(np.any(np.asarray(v) != 0) for v in leaves)
    # the gain's against central differences
    speed = lambda d: float(value_and_grad(  # noqa: E731
        eqx.tree_at(lambda c: c.loop.log_kv, sched, sched.loop.log_kv + d))[0][0])
    h = 1e-5
    fd = (speed(h) - speed(-h)) / (2 * h)
    np.testing.assert_allclose(float(g.loop.log_kv), fd, rtol=1e-10)   # measured 2.4e-11


# bounds unlike the defaults in every field: a loader that dropped one would not give them back
ODD_BOUNDS = fdjax.MCMBounds.for_servo(
    fdjax.Servo(period=1 / 16000), nyquist_fraction=0.8, freq_min_hz=20.0,
    peak_gain=(1e-2, 5.0), peak_damping=(0.05, 0.8), peak_phase_max=2.0,
    notch_damping=(0.02, 1.5), notch_depth_min=1e-2)


def test_save_and_load_are_bit_exact(tmp_path):
    net = fdjax.ATANetwork((0.05, 0.75), width=5, gains=True, key=jax.random.PRNGKey(2))
    sched = fdjax.ScheduledLoop(fdjax.DoubleLoop(kp=55.0, kv=2e3), net, ODD_BOUNDS)
    path = tmp_path / "schedule.eqx"
    fdjax.save_schedule(path, sched, metadata={"drive": "reference_drive()"})
    meta = json.loads((tmp_path / "schedule.json").read_text())
    assert meta["network"]["width"] == 5 and meta["units"]["kv"] == "A·s/m"
    assert meta["metadata"]["drive"] == "reference_drive()"
    back = fdjax.load_schedule(path)
    la, lb = jax.tree_util.tree_leaves(sched), jax.tree_util.tree_leaves(back)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        assert np.array_equal(np.asarray(x), np.asarray(y))
    assert back.bounds == ODD_BOUNDS and back.network.travel_m == (0.05, 0.75)
    assert back.network.width == 5 and back.network.gains is True
    with pytest.raises(FileNotFoundError, match=r"`load_schedule\(path=\.\.\.\)`: no file"):
        fdjax.load_schedule(tmp_path / "missing.eqx")
    # leaves cut short, or a JSON that is not one: named, with the file
    (tmp_path / "cut.eqx").write_bytes(path.read_bytes()[:100])
    (tmp_path / "cut.json").write_text((tmp_path / "schedule.json").read_text())
    with pytest.raises(ValueError, match=r"`load_schedule\(path=\.\.\.\)`: .*cut\.eqx' does not "
                                         r"hold the leaves of a schedule"):
        fdjax.load_schedule(tmp_path / "cut.eqx")
    (tmp_path / "cut.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"cut\.json' is not the JSON file of an fdjax schedule "
                                         r"\(it holds a list"):
        fdjax.load_schedule(tmp_path / "cut.eqx")
    for f in ("cut.eqx", "cut.json"):
        (tmp_path / f).unlink()
    # the leaves without their JSON; the JSON given for the leaves; a folder that is not there
    (tmp_path / "lone.eqx").write_bytes(b"")
    with pytest.raises(FileNotFoundError, match=r"no file .*lone\.json' \(the hyperparameters "
                                                r"that save_schedule writes beside"):
        fdjax.load_schedule(tmp_path / "lone.eqx")
    for fn in (fdjax.load_schedule, lambda p: fdjax.save_schedule(p, sched)):
        with pytest.raises(ValueError, match=r"_schedule\(path=\.\.\.\)` must be the schedule's "
                                             r"leaves \(e\.g\. 'schedule\.eqx'\), not the JSON"):
            fn(tmp_path / "s.json")
    with pytest.raises(FileNotFoundError, match=r"`save_schedule\(path=\.\.\.\)`: no folder"):
        fdjax.save_schedule(tmp_path / "no" / "s.eqx", sched)
    # a folder for the file: the one fdjax tune writes is named
    with pytest.raises(IsADirectoryError, match=r"must be a schedule's file .*got the folder .*"
                                                r"did you mean .*schedule\.eqx'\?"):
        fdjax.load_schedule(tmp_path)
    # metadata JSON cannot hold is refused before anything is written: the schedule saved
    # before is still there and loads
    other = eqx.tree_at(lambda s: s.loop.log_kv, sched, sched.loop.log_kv + 1.0)
    with pytest.raises(ValueError, match=r"`save_schedule\(metadata=\.\.\.\)` must hold only "
                                         r"what JSON can .*ArrayImpl"):
        fdjax.save_schedule(path, other, metadata={"lead": jnp.asarray(0.01)})
    assert bool(eqx.tree_equal(fdjax.load_schedule(path), back))
    assert sorted(f.name for f in tmp_path.iterdir()) == ["lone.eqx", "schedule.eqx",
                                                          "schedule.json"]
    # a NaN leaf is refused before anything is written, and one in a file is named on loading
    nan = eqx.tree_at(lambda s: s.loop.log_kv, sched, jnp.asarray(np.nan))
    with pytest.raises(ValueError, match=r"`save_schedule\(\.\.\.\)`: the leaf \.loop\.log_kv "
                                         r"holds NaN or ∞, cannot be saved"):
        fdjax.save_schedule(path, nan)
    assert bool(eqx.tree_equal(fdjax.load_schedule(path), back))
    with open(path, "wb") as fh:
        eqx.tree_serialise_leaves(fh, nan)
    with pytest.raises(ValueError, match=r"`load_schedule\(path=\.\.\.\)`: the leaf "
                                         r"\.loop\.log_kv holds NaN or ∞, in .*schedule\.eqx"):
        fdjax.load_schedule(path)


def test_a_file_must_be_the_schedule_its_json_describes_for_the_drive_given(tmp_path):
    """Leaves of another schedule, or of a larger tree (the designs file), with trailing bytes,
    or gains the JSON does not hold, had loaded as the JSON's schedule (kp 328.9 where the JSON
    said 337.4); a drive recorded on saving is checked on loading; bounds given as NumPy
    scalars are stored as Python floats (saving had blamed them on `metadata`)."""
    drive = fdjax.reference_drive()
    net = fdjax.ATANetwork((0.1, 0.7), width=3, key=jax.random.PRNGKey(5))
    bounds = fdjax.MCMBounds(period=np.float32(1.25e-4), freq_hz=(np.float64(20.0), 3000.0))
    sched = fdjax.ScheduledLoop(fdjax.DoubleLoop(), net, bounds)
    one, two = tmp_path / "one.eqx", tmp_path / "two.eqx"
    fdjax.save_schedule(one, sched, drive=drive)
    meta = json.loads((tmp_path / "one.json").read_text())
    assert meta["drive"]["type"] == "BallScrewDrive" and len(meta["drive"]["sha256"]) == 64
    assert meta["bounds"]["period_s"] == float(np.float32(1.25e-4))
    assert type(bounds.period) is float and type(bounds.freq_hz[0]) is float
    as_array = fdjax.MCMBounds(period=1.25e-4, freq_hz=jnp.array([20.0, 3000.0]))
    assert as_array.freq_hz == (20.0, 3000.0) and hash(as_array) == hash(
        fdjax.MCMBounds(period=1.25e-4, freq_hz=(20.0, 3000.0)))
    assert bool(eqx.tree_equal(fdjax.load_schedule(one, drive=drive), sched))
    stiffer = eqx.tree_at(lambda d: d.nut.stiffness, drive, drive.nut.stiffness * 1.01)
    with pytest.raises(ValueError, match=r"`load_schedule\(drive=\.\.\.\)`: .*one\.json' was "
                                         r"tuned for another drive \(BallScrewDrive, travel"):
        fdjax.load_schedule(one, drive=stiffer)
    fdjax.save_schedule(two, eqx.tree_at(lambda s: s.loop.log_kp, sched,
                                         sched.loop.log_kp + 0.1))
    with pytest.raises(ValueError, match=r"records no drive to compare with"):
        fdjax.load_schedule(two, drive=drive)
    # the leaves of the other schedule under this one's JSON
    (tmp_path / "mixed.eqx").write_bytes(two.read_bytes())
    (tmp_path / "mixed.json").write_text((tmp_path / "one.json").read_text())
    with pytest.raises(ValueError, match=r"mixed\.eqx' does not hold the leaves its JSON "
                                         r"describes: gains .* \(the leaves of another schedule"):
        fdjax.load_schedule(tmp_path / "mixed.eqx")
    # trailing bytes: the leaves of something larger
    (tmp_path / "mixed.eqx").write_bytes(one.read_bytes() + bytes(64))
    with pytest.raises(ValueError, match=r"written for something else: 64 bytes left over"):
        fdjax.load_schedule(tmp_path / "mixed.eqx")
    # the JSON's gains as another backend's exp rounds them (XLA's and libm's differ by up to
    # 2 ulp) load; a network entry that is not an object is named
    kp = float(sched.loop.kp)
    meta["gains"]["kp"] = float(np.nextafter(np.nextafter(kp, np.inf), np.inf))
    (tmp_path / "mixed.eqx").write_bytes(one.read_bytes())
    (tmp_path / "mixed.json").write_text(json.dumps(meta))
    assert bool(eqx.tree_equal(fdjax.load_schedule(tmp_path / "mixed.eqx"), sched))
    (tmp_path / "mixed.json").write_text(json.dumps({**meta, "network": [4, 2]}))
    with pytest.raises(ValueError, match=r"does not describe an fdjax schedule "
                                         r"\(AttributeError"):
        fdjax.load_schedule(tmp_path / "mixed.eqx")
    # a network the JSON says fdjax does not build
    meta["network"]["depth"] = 3
    (tmp_path / "mixed.eqx").write_bytes(one.read_bytes())
    (tmp_path / "mixed.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"does not describe an fdjax schedule \(ValueError: a "
                                         r"network of depth 3"):
        fdjax.load_schedule(tmp_path / "mixed.eqx")
    # positions of the wrong shape are named
    with pytest.raises(ValueError, match=r"`ScheduledLoop\.controller\(position_m=\.\.\.\)` must "
                                         r"be one table position \(a scalar"):
        sched.controller(jnp.array([0.2, 0.3]))
    with pytest.raises(ValueError, match=r"`ScheduledLoop\.fixed_at\(positions_m=\.\.\.\)` must "
                                         r"be a 1-D array of at least one position, got shape "
                                         r"\(\)"):
        sched.fixed_at(0.2)
    with pytest.raises(ValueError, match=r"`ScheduledLoop\.filter_table\(positions_m=\.\.\.\)` "
                                         r"must be 1-D with at least one position"):
        sched.filter_table([])


def test_filter_table_is_the_schedule_in_drive_units():
    net = fdjax.ATANetwork((0.1, 0.7), width=4, key=jax.random.PRNGKey(4))
    sched = fdjax.ScheduledLoop(fdjax.DoubleLoop(), net, BOUNDS)
    table = sched.filter_table(POSITIONS)
    assert list(table) == ["position_mm", "peak_K", "peak_freq_hz", "peak_xi", "peak_phi_deg",
                           "notch_freq_hz", "notch_zeta_n", "notch_zeta_d", "kp", "kv", "ki"]
    # the gains are the loop's, the same in every row, unless the network schedules them
    assert table["kv"] == [float(sched.loop.kv)] * 6
    assert all(len(v) == 6 for v in table.values())
    np.testing.assert_allclose(table["position_mm"], POSITIONS * 1e3, rtol=1e-15)
    # every column of every row: the controller at that position, one at a time, converted
    # here (Hz from rad/s, degrees from radians)
    for i, y in enumerate(POSITIONS):
        c = sched.controller(y)
        pk, nt = c.mcm.peak, c.mcm.notch
        want = {"peak_K": pk.K[0], "peak_freq_hz": pk.omega[0] / (2 * np.pi),
                "peak_xi": pk.xi[0], "peak_phi_deg": float(pk.phi[0]) * 180 / np.pi,
                "notch_freq_hz": nt.omega[0] / (2 * np.pi), "notch_zeta_n": nt.zeta_n[0],
                "notch_zeta_d": nt.zeta_d[0], "kp": c.kp, "kv": c.kv, "ki": c.ki}
        for k, v in want.items():
            np.testing.assert_allclose(table[k][i], float(v), rtol=1e-13, err_msg=(k, y))
    assert all(z_n < z_d for z_n, z_d in zip(table["notch_zeta_n"], table["notch_zeta_d"]))
    json.dumps(table)  # plain floats
    # a position in mm is refused, eagerly and under jit (a network does not extrapolate)
    msg = (r"`ScheduledLoop.controller\(position_m=\.\.\.\)` must be inside the network's "
           r"travel \[0.1, 0.7\] m")
    with pytest.raises(ValueError, match=msg + ", got 400; table positions are in metres: "
                                             r"400 mm is 0\.4 m$"):
        sched.controller(400.0)
    with pytest.raises(CHECK_FAILED, match=msg):
        eqx.filter_jit(lambda c, y: c.controller(y).mcm.peak.omega)(sched, jnp.asarray(400.0))
    with pytest.raises(ValueError, match=r"`ScheduledLoop.filter_table\(positions_m=\.\.\.\)` "
                                         r"must be inside the network's travel"):
        sched.filter_table([0.1, 400.0])


def test_a_network_with_gains_schedules_the_feedback_gains(tmp_path):
    """``with_gains`` adds three zero outputs: the same controller at every position until the
    gain outputs move; then k(Y) = k e^{δ(Y)} for k_p, k_v, k_i, with the filters unchanged.
    The gain schedule goes through the table, gradients, fitting and saving."""
    net = fdjax.ATANetwork((0.1, 0.7), width=4, key=jax.random.PRNGKey(6))
    loop = fdjax.DoubleLoop(kp=60.0, kv=900.0, ki=120.0)
    sched = fdjax.ScheduledLoop(loop, net, BOUNDS)
    wide = eqx.tree_at(lambda s: s.network, sched, net.with_gains())
    assert wide.network.gains and wide.network(0.3).shape == (10,)
    assert wide.network.outputs[7:] == ("log_kp", "log_kv", "log_ki")
    assert wide.network.with_gains() is wide.network
    for y in (0.1, 0.37, 0.7):
        a, b = sched.controller(y), wide.controller(y)
        for x, z in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            assert np.array_equal(np.asarray(x), np.asarray(z))
    # δ = (ln 2, 0, −ln 4) everywhere: a bias on the three gain outputs
    delta = jnp.array([np.log(2.0), 0.0, -np.log(4.0)])
    moved = eqx.tree_at(lambda s: s.network.mlp.layers[-1].bias, wide,
                        wide.network.mlp.layers[-1].bias.at[7:].add(delta))
    c = moved.controller(0.45)
    np.testing.assert_allclose([c.kp, c.kv, c.ki], [120.0, 900.0, 30.0], rtol=1e-14)
    theta = np.asarray(BOUNDS.from_mcm(c.mcm))
    np.testing.assert_allclose(theta, np.asarray(net(0.45)), rtol=1e-10, atol=1e-12)
    table = moved.filter_table(POSITIONS)
    np.testing.assert_allclose(table["ki"], [30.0] * 6, rtol=1e-14)
    # a factor beyond e^±30 is held there: k e^{clip(δ, −30, 30)}
    far = eqx.tree_at(lambda s: s.network.mlp.layers[-1].bias, wide,
                      wide.network.mlp.layers[-1].bias.at[7:].add(jnp.array([100., -100., 31.])))
    c = far.controller(0.45)
    np.testing.assert_allclose([c.kp, c.kv, c.ki], [60.0 * np.exp(30.0), 900.0 * np.exp(-30.0),
                                                    120.0 * np.exp(30.0)], rtol=1e-14)
    # gradients reach the gain outputs' weights
    drive = fdjax.reference_drive()
    f = np.geomspace(10.0, 3000.0, 32)
    # (one compiled program: the gradient under jit)
    g = eqx.filter_jit(eqx.filter_grad(lambda s: jnp.sum(jnp.abs(
        fdjax.open_loop(s, drive, f, position_m=0.45).position))))(moved)
    last = np.asarray(g.network.mlp.layers[-1].bias)
    assert np.all(np.isfinite(last)) and np.all(last[7:] != 0)
    # fitted to filters and gain factors of local designs
    targets = np.concatenate([_local_designs(), 0.1 * np.stack([POSITIONS] * 3, 1)], axis=1)
    fitted, hist = fdjax.fit_network(net.with_gains(), POSITIONS, targets, steps=200)
    assert float(hist[-1]) < 0.1 * float(hist[0])  # measured 7.83 → 0.23 (0.029×)
    with pytest.raises(ValueError, match=r"must have shapes \(n,\) and \(n, 10\)"):
        fdjax.fit_network(fitted, POSITIONS, targets[:, :7])
    # saved and loaded bit for bit, alone and among designs
    fdjax.save_schedule(tmp_path / "s.eqx", moved)
    meta = json.loads((tmp_path / "s.json").read_text())
    assert meta["network"]["gains"] is True and meta["network"]["outputs"][-1] == "log_ki"
    fdjax.save_designs(tmp_path / "d", {"gs": moved})
    for back in (fdjax.load_schedule(tmp_path / "s.eqx"),
                 fdjax.load_designs(tmp_path / "d")[0]["gs"]):
        assert back.network.gains
        for x, z in zip(jax.tree_util.tree_leaves(moved), jax.tree_util.tree_leaves(back)):
            assert np.array_equal(np.asarray(x), np.asarray(z))


@pytest.fixture(scope="module")
def e2e():
    """What both end-to-end tests train and check, built once for the file: the reference
    drive, a schedule fitted to the reference MCM everywhere (its k_v halved, stable over the
    travel, no feed-forward), one objective (1 mm stroke, 64 frequencies, 4 kept modes) and
    J at a batch of positions in one compiled program (shared by both tests: every schedule
    they check has the same tree)."""
    drive = fdjax.reference_drive()
    ref = fdjax.reference_controller(drive)
    soft = eqx.tree_at(lambda c: (c.log_kv, c.k_ffv, c.k_ffa), ref,
                       (ref.log_kv + np.log(0.5), jnp.asarray(0.0), jnp.asarray(0.0)))
    target = np.tile(np.asarray(BOUNDS.from_mcm(ref.mcm)), (6, 1))
    net, _ = fdjax.fit_network(fdjax.ATANetwork((0.1, 0.7), width=4, key=jax.random.PRNGKey(5)),
                               POSITIONS, target, steps=1500)
    motion = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    obj = fdjax.Objective(motion, np.geomspace(5.0, 3900.0, 64),
                          twin=fdjax.TwinOptions(kept_modes=4), error_scale_m=1e-4)
    J = eqx.filter_jit(jax.vmap(lambda s, p: obj(s, drive, p).total, in_axes=(None, 0)))
    return drive, fdjax.ScheduledLoop(soft, net, BOUNDS), obj, J


def test_end_to_end_training_lowers_the_objective_and_keeps_feedback_only(e2e):
    """A schedule fitted to the reference MCM everywhere, trained end to end 8 steps with its
    feedback gains: the objective falls at every position checked, the gains and the network
    move, the feed-forward gains stay zero (a feedback schedule is compared with feedback
    designs) and the result is stable at the positions checked."""
    drive, start, obj, J = e2e
    trained, rec = fdjax.train_schedule(start, obj, drive, steps=8, batch=2, chunk=8,
                                        train_gains=True, optimiser=optax.adam(0.03))
    h = np.asarray(rec.history)
    assert h.shape == (8,) and np.all(np.isfinite(h))
    assert float(trained.loop.k_ffv) == 0.0 and float(trained.loop.k_ffa) == 0.0
    assert float(trained.loop.log_kv) != float(start.loop.log_kv)
    assert any(np.any(np.asarray(a) != np.asarray(b)) for a, b in
               zip(jax.tree_util.tree_leaves(trained.network),
                   jax.tree_util.tree_leaves(start.network)))
    y = jnp.asarray([0.1, 0.4, 0.7])
    before, after = np.asarray(J(start, y)), np.asarray(J(trained, y))
    # measured J 4.2, 33, 255 → 1.4, 1.6, 8.9 at 100, 400, 700 mm (the same with 4 kept modes
    # as with the 6 this test used to keep)
    assert np.all(after < 0.8 * before), (before, after)
    for p in np.asarray(y):
        assert bool(fdjax.check_stability(trained.controller(p), drive, position_m=p).stable)


def test_end_to_end_on_fixed_positions_by_lbfgs(e2e):
    """On fixed positions the objective is deterministic and L-BFGS trains the schedule: the
    first value of the history is ½(mean + smax) of J at those positions, computed here
    independently, and the best value is lower and is the schedule returned; positions outside
    the travel are refused.  With ``train_feedforward`` the feed-forward gains, zero at the
    start, are trained too."""
    drive, start, obj, J = e2e
    y = np.array([0.1, 0.4, 0.7])
    with pytest.raises(ValueError, match=r"`train_schedule\(positions_m=\.\.\.\)` must be inside "
                                         r"the travel \[0.1, 0.7\] m, got 400 at index 1; table "
                                         r"positions are in metres: 400 mm is 0.4 m"):
        fdjax.train_schedule(start, obj, drive, positions_m=[0.1, 400.0])
    with pytest.raises(ValueError, match=r"`train_schedule\(positions_m=\.\.\.\)` must be a "
                                         r"non-empty 1-D array, got shape \(0,\)"):
        fdjax.train_schedule(start, obj, drive, positions_m=[])
    trained, rec = fdjax.train_schedule(start, obj, drive, steps=3, chunk=3, positions_m=y,
                                        optimiser=optax.lbfgs(), train_feedforward=True)
    assert float(start.loop.k_ffv) == 0.0 and float(start.loop.k_ffa) == 0.0
    assert float(trained.loop.k_ffv) != 0.0 and float(trained.loop.k_ffa) != 0.0
    assert float(trained.loop.log_kv) == float(start.loop.log_kv)  # feedback gains held
    # one program for the start and the result (the same kind of schedule), the other test's
    j = np.asarray(J(start, jnp.asarray(y)))
    expected = 0.5 * (j.mean() + float(fdjax.smooth_max(jnp.asarray(j), 2.0)))
    h = np.asarray(rec.history)
    # the same J in two compiled programs: equal to round-off (measured 1.7e-11 and 3.2e-11
    # relative)
    np.testing.assert_allclose(h[0], expected, rtol=1e-10)
    assert h.min() < 0.9 * h[0], h
    # the schedule returned is the best of the history, computed here again (two programs:
    # measured 3.8e-11 relative)
    jt = np.asarray(J(trained, jnp.asarray(y)))
    np.testing.assert_allclose(0.5 * (jt.mean() + float(fdjax.smooth_max(jnp.asarray(jt), 2.0))),
                               h.min(), rtol=1e-10)


def test_batch_covers_the_ends_and_one_position_per_stratum():
    from fdjax._tune._end_to_end import batch_positions

    for k in range(20):
        y = np.asarray(batch_positions(jax.random.PRNGKey(k), (0.1, 0.7), 8))
        assert y.shape == (8,) and y[0] == 0.1 and y[-1] == 0.7
        strata = np.floor((y[1:-1] - 0.1) / 0.1).astype(int)   # 6 strata of 0.1 m
        np.testing.assert_array_equal(strata, np.arange(6))
    np.testing.assert_array_equal(batch_positions(jax.random.PRNGKey(0), (0.1, 0.7), 2),
                                  [0.1, 0.7])


def test_trained_gains_stay_finite_after_a_step_of_any_length():
    """The gains ``train_schedule(train_gains=True)`` trains are held within e^±30 of their
    start: a step of 1e3 in ln k leaves k_ref e^30, finite and positive, and the loss the
    optimiser sees is finite; inside the limit the gains are the trained ones bit for bit."""
    from fdjax._tune._end_to_end import _EndToEndLoss, held_gains
    from fdjax._tune._parameterisation import LOG_GAIN_LIMIT

    drive = fdjax.reference_drive()
    ref = fdjax.reference_controller(drive)
    net = fdjax.ATANetwork((0.1, 0.7), width=4, key=jax.random.PRNGKey(5))
    start = fdjax.ScheduledLoop(ref, net, BOUNDS)
    gains = lambda s: (s.loop.log_kp, s.loop.log_kv, s.loop.log_ki)  # noqa: E731
    reference = jnp.stack(gains(start))
    step = jnp.array([1e3, -1e3, 0.25])
    moved = eqx.tree_at(gains, start, tuple(reference + step))
    held = held_gains(moved, reference)
    np.testing.assert_array_equal(np.asarray(jnp.stack(gains(held))),
                                  np.asarray(reference) + [LOG_GAIN_LIMIT, -LOG_GAIN_LIMIT, 0.25])
    assert float(held.loop.log_ki) == float(moved.loop.log_ki)   # inside: untouched
    k = np.array([float(held.loop.kp), float(held.loop.kv), float(held.loop.ki)])
    assert np.all(np.isfinite(k)) and np.all(k > 0)
    assert not np.isfinite(float(moved.loop.kp))                 # what the hold prevents

    class GainSum(eqx.Module):     # a stand-in objective: J = (k_p + k_v + k_i) / 1000 at Y
        def __call__(self, controller, drive, position):
            c = controller.controller(position)

            class R(eqx.Module):
                total: jax.Array
            return R(c.kp * 1e-3 + c.kv * 1e-3 + c.ki * 1e-3)

    spec = jax.tree_util.tree_map(lambda _: False, moved)
    spec = eqx.tree_at(gains, spec, (True,) * 3)
    params, static = eqx.partition(moved, spec)
    loss = _EndToEndLoss(static, GainSum(), drive, jnp.array([0.1, 0.7]), reference,
                         (0.1, 0.7), 2, 2.0)
    # the same J at both positions: the loss is J of the held gains, k_ref e^{(30, −30, 0.25)}
    value, worst = loss(params)
    k0 = np.exp(np.asarray(reference))
    j = 1e-3 * (k0[0] * np.exp(30.0) + k0[1] * np.exp(-30.0) + k0[2] * np.exp(0.25))
    np.testing.assert_allclose([float(value), float(worst)], [j, j], rtol=1e-14)  # 2.6e-15
    # its gradient: zero where the hold is active, ∂J/∂ln k_i = k_i/1000 inside it
    g = jax.grad(lambda p: loss(p)[0])(params)
    np.testing.assert_allclose(np.asarray(jnp.stack(gains(g))),
                               [0.0, 0.0, 1e-3 * k0[2] * np.exp(0.25)], rtol=1e-14, atol=0)


# ------------------------------------------------------------------ input checks (audit fixes)
def test_loaders_refuse_the_files_of_another_format(tmp_path):
    """A set of designs given for a schedule, or a JSON of an unknown format or controller
    kind, is named with its file, never read as if it were the other."""
    import shutil

    designs, _ = fdjax.load_designs()
    fdjax.save_designs(tmp_path / "d", designs)
    shutil.copy(tmp_path / "d" / "controllers.eqx", tmp_path / "s.eqx")
    shutil.copy(tmp_path / "d" / "controllers.json", tmp_path / "s.json")
    with pytest.raises(ValueError, match=r"`load_schedule\(path=\.\.\.\)`: .*s\.json' is not an "
                                         r"fdjax schedule \(format 'fdjax-designs/1', expected "
                                         r"'fdjax-schedule/1'\)"):
        fdjax.load_schedule(tmp_path / "s.eqx")
    meta_path = tmp_path / "d" / "controllers.json"
    meta = json.loads(meta_path.read_text())
    meta_path.write_text(json.dumps(dict(meta, format="x")))
    with pytest.raises(ValueError, match=r"`load_designs\(folder=\.\.\.\)`: .*controllers\.json' "
                                         r"is not a set of fdjax designs \(format 'x'"):
        fdjax.load_designs(tmp_path / "d")
    meta["controllers"][meta["names"][0]]["kind"] = "Lead"
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"does not describe a set of fdjax designs .*unknown "
                                         r"controller kind 'Lead'"):
        fdjax.load_designs(tmp_path / "d")


def test_save_and_load_a_path_without_suffix(tmp_path):
    """A path without a suffix takes .eqx on both sides, as equinox's serialisation does (the
    schedule used to be written to ``s1`` and looked for in ``s1.eqx``); the JSON follows.
    Leaves written without a suffix by the earlier fdjax still load."""
    sched = fdjax.load_designs()[0]["mcm_ata_e2e"]
    fdjax.save_schedule(tmp_path / "s1", sched)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["s1.eqx", "s1.json"]
    for path in (tmp_path / "s1", str(tmp_path / "s1"), tmp_path / "s1.eqx"):
        assert bool(eqx.tree_equal(fdjax.load_schedule(path), sched))
    # what the earlier save_schedule("old", ...) wrote: leaves at "old", JSON at "old.json"
    with open(tmp_path / "old", "wb") as f:
        eqx.tree_serialise_leaves(f, sched)
    (tmp_path / "old.json").write_text((tmp_path / "s1.json").read_text())
    assert bool(eqx.tree_equal(fdjax.load_schedule(tmp_path / "old"), sched))
    missing = str(tmp_path / "nope.eqx")
    with pytest.raises(FileNotFoundError,
                       match=rf"^`load_schedule\(path=\.\.\.\)`: no file '{missing}'$"):
        fdjax.load_schedule(tmp_path / "nope")


def test_network_checks_its_position():
    """``ATANetwork(Y)`` takes a real scalar inside its travel (it does not extrapolate): a
    position in mm, NaN or a string used to be computed on.  Traced positions are checked by
    ``eqx.error_if`` and compile once; the scheduled loop's own path is unchanged."""
    net = fdjax.ATANetwork((0.1, 0.7), width=4, key=jax.random.PRNGKey(7))
    msg = r"^`ATANetwork\(position_m=\.\.\.\)` must be inside the network's travel \[0\.1, 0\.7\] m"
    with pytest.raises(ValueError, match=msg + r", got 300; table positions are in metres: "
                                         r"300 mm is 0\.3 m$"):
        net(300.0)
    with pytest.raises(ValueError, match=msg + r", got nan$"):
        net(jnp.nan)
    with pytest.raises(TypeError, match=r"^`ATANetwork\(position_m=\.\.\.\)` must be a number or "
                                        r"an array of numbers, got '0\.3'$"):
        net("0.3")
    with pytest.raises(ValueError, match=r"^`ATANetwork\(position_m=\.\.\.\)` must be a real "
                                         r"scalar, got float64 of shape \(2,\)$"):
        net([0.3, 0.4])

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def outputs(n, y):
        return n(y)

    np.testing.assert_array_equal(outputs(net, jnp.asarray(0.3)), net(0.3))
    outputs(net, jnp.asarray(0.6))
    with pytest.raises(CHECK_FAILED, match=msg[1:]):
        jax.block_until_ready(outputs(net, jnp.asarray(300.0)))
    np.testing.assert_allclose(jax.vmap(net)(jnp.asarray([0.1, 0.7]))[1], net(0.7), rtol=1e-14)
    # the scheduled loop checks its position once (its message) and calls the network unchecked
    sched = fdjax.ScheduledLoop(fdjax.DoubleLoop(), net, BOUNDS)
    np.testing.assert_allclose(BOUNDS.from_mcm(sched.controller(0.45).mcm), net(0.45),
                               rtol=1e-10, atol=1e-12)


def test_fit_network_checks_its_designs():
    """Positions in mm (inside the travel once read in metres), non-finite targets and no
    designs at all used to train on (NaN weights, NaN loss); each is refused, naming
    ``fit_network``, eagerly and under jit."""
    net = fdjax.ATANetwork((0.1, 0.7), width=4, key=jax.random.PRNGKey(8))
    y = np.array([0.2, 0.4, 0.6])
    t = np.asarray(jax.vmap(net)(jnp.asarray(y)))
    with pytest.raises(ValueError, match=r"^`fit_network\(positions_m=\.\.\.\)` must be inside "
                                         r"the network's travel \[0\.1, 0\.7\] m, got 200 at "
                                         r"index 0 and 2 more; table positions are in metres: "
                                         r"200 mm is 0\.2 m$"):
        fdjax.fit_network(net, y * 1000, t, steps=5)
    bad = t.copy()
    bad[1, 3] = np.nan
    with pytest.raises(ValueError, match=r"^`fit_network\(targets=\.\.\.\)` must be finite \(no "
                                         r"NaN or inf\), got nan at index \(1, 3\)$"):
        fdjax.fit_network(net, y, bad, steps=5)
    with pytest.raises(ValueError, match=r"^`fit_network\(positions_m=\.\.\., targets=\.\.\.\)` "
                                         r"must have shapes \(n,\) and \(n, 7\) \(n ≥ 1 designs; 7 "
                                         r"the network's outputs\), got \(0,\) and \(0, 7\)$"):
        fdjax.fit_network(net, [], np.zeros((0, 7)), steps=5)
    with pytest.raises(ValueError, match=r"^`fit_network\(steps=\.\.\.\)` must be an integer at "
                                         r"least 1, got True$"):
        fdjax.fit_network(net, y, t, steps=True)
    fitted = eqx.filter_jit(lambda p: fdjax.fit_network(net, p, t, steps=1)[1])
    assert np.isfinite(float(fitted(jnp.asarray(y))[0]))
    with pytest.raises(CHECK_FAILED, match=r"`fit_network\(positions_m=\.\.\.\)` must be "
                                              r"inside the network's travel \[0\.1, 0\.7\] m"):
        jax.block_until_ready(fitted(jnp.asarray(y * 1000)))


def test_network_travel_is_a_pair_of_numbers_in_metres():
    """The network's travel goes through the drive's travel check (``travel_pair``): strings are
    a TypeError, one number a ValueError, both naming ``ATANetwork(travel_m=...)`` (they used to
    fail in float() or in unpacking); a travel in mm below zero is caught as well as above."""
    with pytest.raises(TypeError, match=r"^`ATANetwork\(travel_m=\.\.\.\)` must be a \(min, max\) "
                                        r"pair of numbers in m, got \('a', 'b'\)$"):
        fdjax.ATANetwork(("a", "b"))
    for travel, shown in (((0.1,), r"\(0\.1,\)"), (0.7, r"0\.7"),
                          ((0.1, 0.4, 0.7), r"\(0\.1, 0\.4, 0\.7\)")):
        with pytest.raises(ValueError, match=r"^`ATANetwork\(travel_m=\.\.\.\)` must be a "
                                             rf"\(min, max\) pair of numbers in m, got {shown}$"):
            fdjax.ATANetwork(travel)
    with pytest.raises(ValueError, match=r"^`ATANetwork\(travel_m=\.\.\.\)` must be an increasing "
                                         r"\(min, max\) pair in m, got \(nan, 0\.7\)$"):
        fdjax.ATANetwork((np.nan, 0.7))
    with pytest.raises(ValueError, match=r"^`ATANetwork\(travel_m=\.\.\.\)` must be a \(min, max\) "
                                         r"pair in m, got \(-700\.0, -100\.0\); table positions "
                                         r"are in metres: -700 mm is -0\.7 m$"):
        fdjax.ATANetwork((-700.0, -100.0))
    assert fdjax.ATANetwork(np.array([0.1, 0.7])).travel_m == (0.1, 0.7)


def test_interpolated_loop_refuses_the_last_design_position_in_mm():
    """700 (mm) for designs up to 0.7 m: 700 × 1e-3 rounds to 0.7000000000000001, past the last
    design, so it used to be held at the end design; 700 / 1000 is 0.7 and it is refused."""
    loop = fdjax.InterpolatedLoop(fdjax.DoubleLoop(), POSITIONS, _local_designs(), BOUNDS)
    with pytest.raises(ValueError, match=r"^`InterpolatedLoop\.controller\(position_m=\.\.\.\)` "
                                         r"must be a table position in metres \(the designs lie "
                                         r"at 0\.1 … 0\.7 m\), got 700; 700 mm is 0\.7 m$"):
        loop.controller(700.0)


def test_tuning_objective_checks_its_arguments():
    """(tuning_objective lives in fdjax._tune._synthesis; its checks are tested here.)  Each
    argument is checked before the objective is built, naming ``tuning_objective``: a zero
    width used to divide by zero, a string to fail in the division, a float servo in an
    attribute lookup, and a negative width was reported as ``Objective(margin_width=...)``."""
    cases = [
        (dict(margin_width=0), ValueError,
         r"`tuning_objective\(margin_width=\.\.\.\)` must be finite and positive, got 0"),
        (dict(margin_width=-0.05), ValueError,
         r"`tuning_objective\(margin_width=\.\.\.\)` must be finite and positive, got -0\.05"),
        (dict(margin_width=np.nan), ValueError,
         r"`tuning_objective\(margin_width=\.\.\.\)` must be finite and positive, got nan"),
        (dict(margin_width="0.05"), TypeError,
         r"`tuning_objective\(margin_width=\.\.\.\)` must be a number or an array of numbers, "
         r"got '0\.05'"),
        (dict(margin_width=[0.01, 0.05]), ValueError,
         r"`tuning_objective\(margin_width=\.\.\.\)` must be a real scalar, got float64 of "
         r"shape \(2,\)"),
        (dict(servo=1.0), TypeError,
         r"`tuning_objective\(servo=\.\.\.\)` must be an fdjax\.Servo, got float"),
        (dict(feedforward="yes"), TypeError,
         r"`tuning_objective\(feedforward=\.\.\.\)` must be a bool, got 'yes'"),
        (dict(kept_modes=0), ValueError,
         r"`tuning_objective\(kept_modes=\.\.\.\)` must be an integer between 1 and 29, got 0"),
        (dict(kept_modes=6.0), ValueError,
         r"`tuning_objective\(kept_modes=\.\.\.\)` must be an integer between 1 and 29, got 6\.0"),
    ]
    for kwargs, kind, match in cases:
        with pytest.raises(kind, match="^" + match + "$"):
            fdjax.tuning_objective(**kwargs)
    assert float(fdjax.tuning_objective(margin_width=np.float32(0.01)).margin_sharpness) == \
        pytest.approx(1000.0, rel=1e-6)
    # the margins' grid follows the servo: 5 Hz to 0.975 of its Nyquist frequency, 3.9 kHz
    # at the reference's 8 kHz, 2.925 kHz at 6 kHz (a fixed 3.9 kHz grid was refused there)
    np.testing.assert_array_equal(fdjax.tuning_objective().freq_hz,
                                  np.geomspace(5.0, 3900.0, 400))
    slow = fdjax.tuning_objective(fdjax.Servo(period=1 / 6000))
    np.testing.assert_allclose([slow.freq_hz[0], slow.freq_hz[-1]], [5.0, 2925.0], rtol=1e-14)


def test_scheduled_loop_runs_the_continuous_simulation_and_the_moving_table():
    """A schedule through the Padé loop's run and the moving table (its law taken at the
    table's position at every sample).  With a network whose output does not depend on the
    position (last layer's weights zero) the runs are the fixed controller's; with the
    network's weights the moving run follows the schedule away from the start's design."""
    drive = fdjax.reference_drive()
    net = fdjax.ATANetwork((0.1, 0.7), width=4, key=jax.random.PRNGKey(1))
    last = lambda n: n.mlp.layers[-1].weight  # noqa: E731
    flat = eqx.tree_at(last, net, jnp.zeros_like(last(net)))
    base = fdjax.DoubleLoop(mcm=fdjax.reference_mcm())
    sched_flat, sched = (fdjax.ScheduledLoop(base, n, BOUNDS) for n in (flat, net))
    y0 = 0.3
    fast = fdjax.jerk_limited(0.02, 1.0, 20.0, 2.0e4)  # the table moves ~1 mm in 10 ms
    kw = dict(position_m=y0, duration=0.01, twin=fdjax.TwinOptions(kept_modes=6))

    def rel(a, b):
        return float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b)))

    for method, moving in ((fdjax.PadeODE(), False), (fdjax.SampledData(), True)):
        a = fdjax.simulate(sched_flat, drive, fast, method, moving=moving, **kw)
        b = fdjax.simulate(sched_flat.controller(y0), drive, fast, method, moving=moving, **kw)
        assert a.result == fdjax.RESULTS.successful
        # the same arithmetic on the same values: bit-identical with XLA's default flags; with
        # the tests' (conftest.py) the Padé run's two programs fuse the solver step's hold of
        # a diverging state apart: measured 1.2e-14
        assert rel(a.error_scale, b.error_scale) < 5e-14
    # frozen at y0, the schedule's own network is its controller at y0 (the same programs)
    a = fdjax.simulate(sched, drive, fast, fdjax.PadeODE(), **kw)
    b = fdjax.simulate(sched.controller(y0), drive, fast, fdjax.PadeODE(), **kw)
    assert rel(a.error_scale, b.error_scale) < 1e-14
    c = fdjax.simulate(sched, drive, fast, moving=True, **kw)
    d = fdjax.simulate(sched.controller(y0), drive, fast, moving=True, **kw)
    assert float(c.position_m[-1]) > y0 + 5e-4  # it moved
    # the filters change with the position, a little over 1 mm: measured 1.13e-7 of the error
    # (the flat network's runs above agree to round-off, so this is no round-off)
    assert 5e-8 < rel(c.error_scale, d.error_scale) < 2e-7
