"""The ATA scheduling network, the scheduled loop, and saving and loading a schedule."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import fdjax

BOUNDS = fdjax.MCMBounds.for_servo(fdjax.Servo())
POSITIONS = np.linspace(0.1, 0.7, 6)


def _local_designs():
    """Six smooth, distinct local designs (normalised parameters) over the travel."""
    y = (POSITIONS - 0.4) / 0.3
    return np.stack([0.5 + 0.3 * y, -0.2 + 0.4 * y ** 2, 0.8 - 0.1 * y, -0.3 * y,
                     1.7 - 0.5 * y, 1.0 + 0.2 * y, -0.7 + 0.1 * y ** 3], axis=1)


def test_network_shape():
    net = fdjax.ATANetwork((0.1, 0.7), width=8)
    assert net.width == 8 and net.mlp.depth == 2 and net.mlp.activation is jax.nn.sigmoid
    assert net.mlp.in_size == 1 and net.mlp.out_size == 7
    assert net(0.3).shape == (7,) and net(0.3).dtype == jnp.float64
    out = jax.vmap(net)(jnp.asarray(POSITIONS))
    np.testing.assert_allclose(out[2], net(POSITIONS[2]), rtol=1e-15)
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
    assert history[-1] < 1e-3 * history[0]
    fitted = np.asarray(jax.vmap(net)(jnp.asarray(POSITIONS)))
    # 7 smooth targets at 6 points with 8+8 sigmoid neurons: measured max error 6e-3
    np.testing.assert_allclose(fitted, targets, atol=2e-2)
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
    a = fdjax.open_loop(sched, drive, f, position_m=y, twin=twin)
    b = fdjax.open_loop(fixed, drive, f, position_m=y, twin=twin)
    for k in ("plant_input", "speed", "position"):
        np.testing.assert_allclose(getattr(a, k), getattr(b, k), rtol=1e-13)
    # gradients reach the network's weights and the gains, not the hardware
    g = eqx.filter_grad(
        lambda c: jnp.sum(jnp.abs(fdjax.open_loop(c, drive, f, position_m=y, twin=twin).speed))
    )(sched)
    leaves = jax.tree_util.tree_leaves(g.network)
    assert leaves and all(np.all(np.isfinite(np.asarray(v))) for v in leaves)
    assert any(np.any(np.asarray(v) != 0) for v in leaves)


def test_save_and_load_are_bit_exact(tmp_path):
    net = fdjax.ATANetwork((0.1, 0.7), width=5, key=jax.random.PRNGKey(2))
    sched = fdjax.ScheduledLoop(fdjax.DoubleLoop(kp=55.0, kv=2e3), net, BOUNDS)
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
    assert back.bounds == sched.bounds and back.network.travel_m == (0.1, 0.7)
    with pytest.raises(FileNotFoundError, match=r"`load_schedule\(path=\.\.\.\)`: no file"):
        fdjax.load_schedule(tmp_path / "missing.eqx")
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
    with pytest.raises(ValueError, match=r"`save_schedule\(metadata=\.\.\.\)` must hold only "
                                         r"what JSON can .*ArrayImpl"):
        fdjax.save_schedule(path, sched, metadata={"lead": jnp.asarray(0.01)})
    assert bool(eqx.tree_equal(fdjax.load_schedule(path), back))
    assert sorted(f.name for f in tmp_path.iterdir()) == ["lone.eqx", "schedule.eqx",
                                                          "schedule.json"]


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
    m = sched.controller(POSITIONS[3]).mcm
    np.testing.assert_allclose(table["peak_freq_hz"][3], float(m.peak.omega[0]) / (2 * np.pi),
                               rtol=1e-13)
    np.testing.assert_allclose(table["notch_zeta_n"][3], float(m.notch.zeta_n[0]), rtol=1e-13)
    assert all(z_n < z_d for z_n, z_d in zip(table["notch_zeta_n"], table["notch_zeta_d"]))
    json.dumps(table)  # plain floats
    # a position in mm is refused, eagerly and under jit (a network does not extrapolate)
    msg = (r"`ScheduledLoop.controller\(position_m=\.\.\.\)` must be inside the network's "
           r"travel \[0.1, 0.7\] m")
    with pytest.raises(ValueError, match=msg + ", got 400; table positions are in metres: "
                                             r"400 mm is 0\.4 m$"):
        sched.controller(400.0)
    with pytest.raises(Exception, match=msg):
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
    # gradients reach the gain outputs' weights
    drive = fdjax.reference_drive()
    f = np.geomspace(10.0, 3000.0, 32)
    g = eqx.filter_grad(lambda s: jnp.sum(jnp.abs(
        fdjax.open_loop(s, drive, f, position_m=0.45).position)))(moved)
    last = np.asarray(g.network.mlp.layers[-1].bias)
    assert np.all(np.isfinite(last)) and np.all(last[7:] != 0)
    # fitted to filters and gain factors of local designs
    targets = np.concatenate([_local_designs(), 0.1 * np.stack([POSITIONS] * 3, 1)], axis=1)
    fitted, hist = fdjax.fit_network(net.with_gains(), POSITIONS, targets, steps=200)
    assert float(hist[-1]) < float(hist[0])
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


def _feedback_schedule():
    """The reference drive and a schedule fitted to the reference MCM everywhere, its k_v
    halved (stable over the travel) and no feed-forward."""
    drive = fdjax.reference_drive()
    ref = fdjax.reference_controller(drive)
    soft = eqx.tree_at(lambda c: (c.log_kv, c.k_ffv, c.k_ffa), ref,
                       (ref.log_kv + np.log(0.5), jnp.asarray(0.0), jnp.asarray(0.0)))
    target = np.tile(np.asarray(BOUNDS.from_mcm(ref.mcm)), (6, 1))
    net, _ = fdjax.fit_network(fdjax.ATANetwork((0.1, 0.7), width=4, key=jax.random.PRNGKey(5)),
                               POSITIONS, target, steps=1500)
    return drive, fdjax.ScheduledLoop(soft, net, BOUNDS)


def test_end_to_end_training_lowers_the_objective_and_keeps_feedback_only():
    """A schedule fitted to the reference MCM everywhere, trained end to end 8 steps with its
    feedback gains: the objective falls at every position checked, the gains and the network
    move, the feed-forward gains stay zero (a feedback schedule is compared with feedback
    designs) and the result is stable at the positions checked."""
    drive, start = _feedback_schedule()
    motion = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    obj = fdjax.Objective(motion, np.geomspace(5.0, 3900.0, 64),
                          twin=fdjax.TwinOptions(kept_modes=6), error_scale_m=1e-4)
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
    J = eqx.filter_jit(jax.vmap(lambda c, p: obj(c, drive, p).total, in_axes=(None, 0)))
    before, after = np.asarray(J(start, y)), np.asarray(J(trained, y))
    # measured J 4.2, 33, 255 → 1.4, 1.6, 8.9 at 100, 400, 700 mm
    assert np.all(after < 0.8 * before), (before, after)
    for p in np.asarray(y):
        assert bool(fdjax.check_stability(trained.controller(p), drive, position_m=p).stable)


def test_end_to_end_on_fixed_positions_by_lbfgs():
    """On fixed positions the objective is deterministic and L-BFGS trains the schedule: the
    first value of the history is ½(mean + smax) of J at those positions, computed here
    independently, and the best value is lower; positions outside the travel are refused."""
    drive, start = _feedback_schedule()
    motion = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    obj = fdjax.Objective(motion, np.geomspace(5.0, 3900.0, 64),
                          twin=fdjax.TwinOptions(kept_modes=4), error_scale_m=1e-4)
    y = np.array([0.1, 0.4, 0.7])
    with pytest.raises(ValueError, match=r"`train_schedule\(positions_m=\.\.\.\)` must be inside "
                                         r"the travel \[0.1, 0.7\] m, got 400 at index 1; table "
                                         r"positions are in metres: 400 mm is 0.4 m"):
        fdjax.train_schedule(start, obj, drive, positions_m=[0.1, 400.0])
    with pytest.raises(ValueError, match=r"`train_schedule\(positions_m=\.\.\.\)` must be a "
                                         r"non-empty 1-D array, got shape \(0,\)"):
        fdjax.train_schedule(start, obj, drive, positions_m=[])
    trained, rec = fdjax.train_schedule(start, obj, drive, steps=3, chunk=3, positions_m=y,
                                        optimiser=optax.lbfgs())
    j = np.asarray(eqx.filter_jit(jax.vmap(lambda p: obj(start, drive, p).total))(
        jnp.asarray(y)))
    expected = 0.5 * (j.mean() + float(fdjax.smooth_max(jnp.asarray(j), 2.0)))
    h = np.asarray(rec.history)
    # the same J in two compiled programs: equal to round-off (measured 1.7e-11 relative)
    np.testing.assert_allclose(h[0], expected, rtol=1e-10)
    assert h.min() < 0.9 * h[0], h


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
    value, worst = loss(params)
    assert np.isfinite(float(value)) and np.isfinite(float(worst))
    g = jax.grad(lambda p: loss(p)[0])(params)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(g))
