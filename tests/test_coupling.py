"""LM-FBS coupling: Y_c = Y − Y Bᵀ (B Y Bᵀ + Y_j)⁻¹ B Y."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fdjax

FREQ = np.linspace(20.0, 6000.0, 1500)


def _rod(L):
    return fdjax.Rod.axial(diameter=0.03, length=L, retardation=2e-6)


def _two_rods_uncoupled(L1, L2):
    Y1 = np.asarray(_rod(L1).frf(FREQ, [0.0, L1]))
    Y2 = np.asarray(_rod(L2).frf(FREQ, [0.0, L2]))
    Y = np.zeros((FREQ.size, 4, 4), complex)
    Y[:, :2, :2], Y[:, 2:, 2:] = Y1, Y2
    return Y


def test_two_free_free_rods_rigidly_coupled_equal_one_rod():
    L1, L2 = 0.45, 0.8
    Y = _two_rods_uncoupled(L1, L2)
    B = np.array([[0.0, 1.0, -1.0, 0.0]])  # joint: end of rod 1 meets start of rod 2
    Yc = np.asarray(fdjax.couple(jnp.asarray(Y), B))
    ref = np.asarray(_rod(L1 + L2).frf(FREQ, [0.0, L1, L1 + L2]))
    sel = [0, 1, 3]  # (start, joint (rod-1 side), far end)
    # round-off of the coupling's solve near the rods' resonances: measured 7.2e-13
    np.testing.assert_allclose(Yc[:, sel][:, :, sel], ref, rtol=1e-11, atol=0)
    # both sides of a rigid joint move together (measured 2.3e-14)
    np.testing.assert_allclose(Yc[:, 1], Yc[:, 2], rtol=1e-12)


def test_stiff_joint_approaches_rigid_at_first_order():
    L1, L2 = 0.45, 0.8
    Y = jnp.asarray(_two_rods_uncoupled(L1, L2))
    B = np.array([[0.0, 1.0, -1.0, 0.0]])
    rigid = np.asarray(fdjax.couple(Y, B))
    errs = []
    stiffness = np.array([1e10, 1e11, 1e12])
    for k in stiffness:
        Yj = jnp.full((FREQ.size, 1, 1), 1.0 / k, jnp.complex128)
        Yc = np.asarray(fdjax.couple(Y, B, Yj))
        errs.append(np.median(np.abs(Yc[:, 0, 3] - rigid[:, 0, 3]) / np.abs(rigid[:, 0, 3])))
    order = -np.polyfit(np.log(stiffness), np.log(errs), 1)[0]
    assert abs(order - 1.0) < 0.05  # error ∝ joint compliance 1/k


def test_coupled_receptance_is_reciprocal_and_matches_numpy():
    rng = np.random.default_rng(0)
    n, m = 5, 2
    A = rng.normal(size=(7, n, n)) + 1j * rng.normal(size=(7, n, n))
    Y = A + np.swapaxes(A, -1, -2)  # reciprocal (symmetric) substructure receptances
    B = rng.normal(size=(m, n))
    J = np.eye(m) * (0.3 + 0.1j)
    Yc = np.asarray(fdjax.couple(jnp.asarray(Y), B, jnp.asarray(J)))
    ref = Y - Y @ B.T @ np.linalg.inv(B @ Y @ B.T + J) @ B @ Y
    # entries of order one: measured 5e-15 and 1.3e-14
    np.testing.assert_allclose(Yc, ref, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(Yc, np.swapaxes(Yc, -1, -2), rtol=1e-12, atol=1e-13)


def test_three_mass_by_coupling_two_substructures():
    # m1 alone and the (m2, m3) chain joined by the compliant joint k1, c1 reproduce the 3M2S
    w = 2 * np.pi * np.linspace(5.0, 300.0, 400)
    m1 = fdjax.LumpedModel([[100.0]], [[0.0]], [[0.0]])
    rest = fdjax.chain_model([150.0, 50.0], [2e7], [4e2])
    Y = np.zeros((w.size, 3, 3), complex)
    Y[:, :1, :1] = np.asarray(m1.receptance(w))
    Y[:, 1:, 1:] = np.asarray(rest.receptance(w))
    joint = np.asarray(fdjax.joint_receptance(5e7, 1e3, w))[:, None, None]
    Yc = np.asarray(fdjax.couple(jnp.asarray(Y), np.array([[-1.0, 1.0, 0.0]]), jnp.asarray(joint)))
    ref = np.asarray(fdjax.three_mass().receptance(w))
    np.testing.assert_allclose(Yc, ref, rtol=1e-12)  # measured 3.4e-14


def test_an_interface_with_a_zero_or_repeated_row_is_named():
    """Each row of B is one compatibility constraint: a zero row or a repeated one leaves
    B Y Bᵀ singular (a bare ZeroDivisionError, or "non-finite result, check the parameters")."""
    import pytest

    Y = np.eye(3)[None] * (1e-6 + 0j)
    for B in (np.array([[1.0, -1.0, 0.0], [0.0, 0.0, 0.0]]),
              np.array([[1.0, -1.0, 0.0], [1.0, -1.0, 0.0]])):
        with pytest.raises(ValueError, match=r"`couple\(interface=\.\.\.\)` must have "
                                             r"independent rows .* got rank 1 for 2 rows"):
            fdjax.couple(Y, B)
    assert fdjax.couple(Y, np.array([[1.0, -1.0, 0.0]])).shape == (1, 3, 3)


def test_compliant_joints_in_parallel_are_one_joint_of_their_summed_stiffness():
    """With joint receptances a repeated row of B is a joint in parallel, not a repeated
    constraint: two springs k1, k2 between the same DOFs couple as one spring k1 + k2 (the
    rank check is for rigid joints only; it refused this).  Measured 0 relative difference
    (the same numbers to the last digit), asserted to 1e-12."""
    Y = np.diag([1e-6, 2e-6, 3e-6]).astype(complex)[None]
    k1, k2 = 2e6, 3e6
    B = np.array([[1.0, -1.0, 0.0], [1.0, -1.0, 0.0]])
    two = np.asarray(fdjax.couple(Y, B, np.diag([1 / k1, 1 / k2]).astype(complex)[None]))
    one = np.asarray(fdjax.couple(Y, B[:1], np.array([[[1 / (k1 + k2)]]], complex)))
    np.testing.assert_allclose(two, one, rtol=1e-12)
    # against the LM-FBS formula in NumPy
    J = np.diag([1 / k1, 1 / k2]).astype(complex)
    ref = Y[0] - Y[0] @ B.T @ np.linalg.solve(B @ Y[0] @ B.T + J, B @ Y[0])
    np.testing.assert_allclose(two[0], ref, rtol=1e-12)
    # joints given as zero are rigid: repeated (or scaled) rows are refused as without joints
    # (finite and 29 % off the one-row result had come back)
    for rows in (B, np.array([[1.0, -1.0, 0.0], [3.0, -3.0, 0.0]])):
        with pytest.raises(ValueError, match=r"independent rows for its rigid joints .* got "
                                             r"rank 1 for 2 rows"):
            fdjax.couple(Y, rows, np.zeros((1, 2, 2), complex))
    # one rigid, one compliant joint on the same row: the compliant one keeps it invertible
    mixed = np.asarray(fdjax.couple(Y, B, np.diag([0.0, 1 / k2]).astype(complex)[None]))
    J = np.diag([0.0, 1 / k2]).astype(complex)
    ref = Y[0] - Y[0] @ B.T @ np.linalg.solve(B @ Y[0] @ B.T + J, B @ Y[0])
    np.testing.assert_allclose(mixed[0], ref, rtol=1e-12)


def test_inputs_that_are_not_numbers_or_do_not_broadcast_are_named():
    """Raised by the function the user called, with the parameter, instead of JAX's errors."""
    from fdjax._coupling import couple, joint_receptance

    rng = np.random.default_rng(0)
    Y, Yj = rng.normal(size=(5, 3, 3)) + 0j, rng.normal(size=(4, 1, 1)) + 0j
    with pytest.raises(TypeError, match=r"`couple\(receptance=\.\.\.\)` must be a number or an "
                                        r"array of numbers, got 'a'"):
        couple("a", np.eye(3))
    with pytest.raises(ValueError, match=r"`couple\(joint=\.\.\.\)` must broadcast against the "
                                         r"receptance's batch \(5,\), got batch \(4,\)"):
        couple(Y, np.eye(3)[:1], Yj)
    with pytest.raises(TypeError, match=r"`joint_receptance\(omega=\.\.\.\)` must be a number"):
        joint_receptance(1.0, 1.0, "1")
    with pytest.raises(ValueError, match=r"`joint_receptance\(stiffness=\.\.\., damping=\.\.\., "
                                         r"omega=\.\.\.\)` must broadcast against each other, got "
                                         r"shapes \(2,\), \(3,\) and \(\)"):
        joint_receptance([1.0, 2.0], [1.0, 2.0, 3.0], 1.0)
    with pytest.raises(TypeError, match=r"`LumpedModel\.receptance\(omega=\.\.\.\)` must be a "
                                        r"number or an array of numbers, got '1'"):
        fdjax.three_mass().receptance("1")


def test_couple_under_jit_vmap_and_grad():
    """A traced interface (under jit) takes couple's general path (no structural zeros skipped,
    no rank check): it equals the eager result; vmap over joint stiffnesses equals a loop; the
    gradient in the joint's stiffness matches central differences."""
    Y = jnp.asarray(_two_rods_uncoupled(0.45, 0.8)[::50])  # 30 frequencies
    B = jnp.array([[0.0, 1.0, -1.0, 0.0]])
    eager = np.asarray(fdjax.couple(Y, B))
    # measured: equal (the skipped blocks are exact zeros either way)
    np.testing.assert_allclose(np.asarray(jax.jit(fdjax.couple)(Y, B)), eager, rtol=1e-13)

    def tip(k):  # |far end / start| of the rods joined by a spring of stiffness k (N/m)
        Yj = jnp.broadcast_to((1.0 / k).astype(jnp.complex128), (Y.shape[0], 1, 1))
        return jnp.abs(fdjax.couple(Y, B, Yj)[:, 0, 3]) * 1e9

    ks = jnp.array([1e8, 1e9, 1e10])
    np.testing.assert_allclose(np.asarray(jax.jit(jax.vmap(tip))(ks)),
                               np.stack([np.asarray(tip(k)) for k in ks]), rtol=1e-13)
    f = lambda lk: jnp.sum(tip(jnp.exp(lk)))  # noqa: E731
    x, h = jnp.log(1e9), 1e-5
    fd = (float(f(x + h)) - float(f(x - h))) / (2 * h)
    np.testing.assert_allclose(float(jax.grad(f)(x)), fd, rtol=2e-8)  # measured 2.3e-9


def test_rigid_rows_are_checked_under_jit_and_at_each_batch_index():
    """Repeated or scaled rigid rows are refused under jit as eagerly, whether B or the joints
    are traced (a single frequency came back finite and 69 % off the one-row coupling); a joint
    that is zero at one batch index only is rigid there, and that index is named; an interface
    without rows and a singular bracket are named as such."""
    import equinox as eqx
    from jit_errors import CHECK_FAILED

    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3)) + 1j * rng.normal(size=(3, 3))
    Y = (1e-6 * (A + A.T))[None]  # one frequency: nothing else in the batch makes it inf
    B = np.array([[1.0, -1.0, 0.0], [3.0, -3.0, 0.0]])
    pattern = r"`couple\(interface=\.\.\.\)` must have independent rows for its rigid joints"
    with pytest.raises(CHECK_FAILED, match=pattern):
        jax.block_until_ready(eqx.filter_jit(fdjax.couple)(Y, B))
    with pytest.raises(CHECK_FAILED, match=pattern):
        jax.block_until_ready(eqx.filter_jit(lambda J: fdjax.couple(Y, B, J))(
            np.zeros((1, 2, 2), complex)))
    # compliant joints on the same rows pass under jit, equal to the eager result
    J = np.diag([1e-7, 2e-7]).astype(complex)[None]
    np.testing.assert_array_equal(np.asarray(eqx.filter_jit(fdjax.couple)(Y, B, J)),
                                  np.asarray(fdjax.couple(Y, B, J)))
    # both joints rigid at batch index 1 only (one rigid joint there would be accepted)
    Js = np.stack([np.diag([1e-7, 2e-7]), np.zeros((2, 2)), np.diag([1e-7, 0.0])])
    Js = Js.astype(complex)
    Y3 = np.repeat(Y, 3, axis=0)
    fdjax.couple(Y3, B, Js[[0, 2, 2]])
    with pytest.raises(ValueError, match=pattern + r" .*got rank 1 for 2 rows at batch index 1"):
        fdjax.couple(Y3, B, Js)
    with pytest.raises(ValueError, match=r"`couple\(interface=\.\.\.\)` must have at least one "
                                         r"row \(a joint\), got shape \(0, 3\)"):
        fdjax.couple(Y, np.zeros((0, 3)))
    # two grounded DOFs: B Y Bᵀ = 0, inputs all finite
    with pytest.raises(ValueError, match=r"`couple\(receptance=\.\.\., interface=\.\.\., "
                                         r"joint=\.\.\.\)` must be such that the interface "
                                         r"bracket B·Y·Bᵀ \+ Y_j is invertible"):
        fdjax.couple(np.diag([0.0, 0.0, 1e-6])[None] + 0j, np.array([[1.0, -1.0, 0.0]]))
