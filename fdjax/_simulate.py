r"""Time simulation of the closed feed-drive loop (paper Sec. 4.3, Figs. 16–17).

Two ways to run the same loop (the controllers of :mod:`fdjax._loop` around the state-space
twin of :mod:`fdjax._statespace`), both pure functions of pytrees, differentiable with respect
to every controller and plant parameter and batched with ``jax.vmap``:

**Sampled data** (:class:`SampledData`): what a servo drive does.  At the servo period T the
controller reads the scale x2 and the encoder angle θ1, computes the current command u_k, and
the command reaches the motor d = τ/T samples later (an integer-sample delay, a shift
register); between samples the torque is held (zero-order hold, ZOH).  The plant's exact ZOH
discretisation over one period,

    x_{k+1} = Φ x_k + Γ (T1_k, F3_k),     [[Φ, Γ], [0, I]] = exp([[A, B], [0, 0]] T),

the controller in discrete time — the motor speed by the backward difference
v_m,k = i_sc (θ1_k − θ1_{k−1})/T, the PI (PID) blocks by Tustin's rule, the MCM as its
second-order sections (:meth:`fdjax.MCM.discretize`: pole-matched and fitted by default,
prewarped Tustin with ``SampledData(filter_method="tustin")``) — and the delay as d states
make one discrete LTI system :math:`s_{k+1} = A_d s_k + B_d w_k`, :math:`y_k = C_d s_k + D_d
w_k` (:func:`sampled_closed_loop`), run by a ``lax.scan`` of matrix–vector products.  It is
exact for the sampled loop: nothing is approximated but the plant's modal truncation.

**ODE** (:class:`PadeODE`): the continuous loop of :func:`fdjax.closed_loop` with the delay as
its [n/n] Padé approximant, solved by ``diffrax.diffeqsolve``.  The inputs w = (r, ṙ, r̈, F3)
are sampled on the output grid and interpolated linearly in between (a first-order hold, as
``scipy.signal.lsim`` does).  The default solver :class:`ExponentialFOH` integrates that ODE exactly
(matrix exponential of the step); any diffrax solver can be passed instead.  With
``moving=True`` the plant's matrices follow the table, Y(t) = Y₀ + r(t): the finite-element
matrices are rebuilt at Y(t) on every evaluation and projected on a fixed modal basis (a Ritz
basis, the modes at Y₀), so the nut's stiffness moves along the screw during the motion (the
paper froze the position).  The sampled path does the same sample by sample
(:func:`_sampled_moving`: the sampled loop rebuilt at each step's midpoint position).  The
sampled loop adds the half-sample lags of the ZOH and of the backward difference, which the
continuous loop lumps into τ: the two paths agree to O(T) (tested: first-order convergence as
T → 0).

**Outputs** (:class:`Simulation`): θ1, x2, x3, the motor torque T1 and current T1/k_m, the
tracking errors e2 = r − x2 (scale) and e3 = r − x3 (tool point).  A run that diverges — a
state turns non-finite, or the scale error exceeds ``error_bound`` — stops there: the states
are frozen at their last finite values (no NaN reaches the outputs) and the result code says
"diverged at t = … s, table position … m".  ``throw=True`` (default) raises it.
"""

from __future__ import annotations

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float, Int

from . import _checks
from ._drive import BallScrewDrive
from ._loop import (
    DEFAULT_PADE_ORDER,
    AbstractLoop,
    DoubleLoop,
    PIDLoop,
    _closed_loop_impl,
    _Layout,
    _pade_ss,
)
from ._statespace import (
    DEFAULT_ELEMENTS,
    StateSpace,
    _assemble,
    _generalised_eigh,
    _rigid_mode,
    count_modes,
    state_space,
)

__all__ = [
    "SampledData",
    "PadeODE",
    "ExponentialFOH",
    "SampledLoop",
    "Simulation",
    "SimulationResult",
    "sampled_closed_loop",
    "simulate",
    "SIMULATION_OUTPUTS",
]

SIMULATION_OUTPUTS = ("theta1", "x2", "x3", "T1")
"""Rows of :attr:`SampledLoop.C`: motor angle (rad), scale and tool positions (m), torque (N·m)."""


class SimulationResult(eqx.Enumeration):
    """Result code of a :class:`Simulation`."""

    successful = "the simulation ran to the end"
    diverged = "the closed loop diverged (a state turned non-finite or the error bound was hit)"
    solver_failed = "the ODE solver failed (step size or step count; see diffrax)"
    unstable = "the closed loop is unstable"


# ------------------------------------------------------------------------------------ methods
class SampledData(eqx.Module):
    r"""Sampled-data simulation at the servo period: ZOH plant, discrete controller, delay of
    ``d = τ/T`` whole samples, outputs at every sample.

    Attributes:
        period: the servo period T (s), static; outputs come at this period.
        delay_samples: the delay d in samples (static).  Default: τ/T of the loop, which must
            be a whole number ≥ 1 of periods.  Required when the loop is built inside
            jit/grad (its τ is then traced); τ = d·T is still checked (``eqx.error_if``).
        filter_method: how the MCM is discretised, ``"fitted"`` (default, within 1 % of the
            continuous filter below Nyquist/4) or ``"tustin"`` (prewarped bilinear, what most
            drives run); see :meth:`fdjax.MCM.discretize`.
    """

    period: float = eqx.field(static=True, default=5.0e-5)
    delay_samples: int | None = eqx.field(static=True, default=None)
    filter_method: str = eqx.field(static=True, default="fitted")

    def __check_init__(self):
        p = float(self.period)
        if not (math.isfinite(p) and p > 0):
            raise ValueError(f"`SampledData(period=...)` must be positive, got {p:.6g}")
        d = self.delay_samples
        if d is not None and (isinstance(d, bool) or not isinstance(d, int | np.integer) or d < 1):
            raise ValueError(f"`SampledData(delay_samples=...)` must be an int ≥ 1, got {d!r}")
        if self.filter_method not in ("fitted", "tustin"):
            raise ValueError(
                "`SampledData(filter_method=...)` must be 'fitted' or 'tustin', "
                f"got {self.filter_method!r}"
            )


class ExponentialFOH(diffrax.AbstractSolver):
    r"""Exponential solver for the linear loop ẋ = A x + B w(t) with the input linear over each
    step (a first-order hold), the method of ``scipy.signal.lsim``:

        x_{k+1} = Φ x_k + (Γ₀ − Γ₁) w_k + Γ₁ w_{k+1},
        exp([[A h, B h, 0], [0, 0, I], [0, 0, 0]]) = [[Φ, Γ₀, Γ₁], [0, I, I], [0, 0, I]].

    For a frozen plant (A, B constant) this is exact, whatever the stiffness of the Padé delay
    and the high modes; the exponential is computed once, at ``init``, for the step ``dt``, and
    every step must be dt (``diffrax.StepTo`` on the output grid, as :func:`simulate` does;
    another step length is an error).  For
    the moving table A(Y(t)), B(Y(t)) are taken at the step's midpoint (the exponential
    midpoint rule, second order in the variation of the plant over a step — the table moves
    micrometres per step) and the exponential is computed every step.  No error estimate, so
    no adaptive stepping.  Works with the loop terms of :func:`simulate` only.
    """

    dt: float = eqx.field(static=True)

    term_structure = diffrax.AbstractTerm
    interpolation_cls = diffrax.LocalLinearInterpolation

    def order(self, terms):
        return 2

    def init(self, terms, t0, t1, y0, args):
        terms = _unwrap(terms)
        if isinstance(terms, _LTITerm):
            return _foh_matrices(terms.A, terms.B, jnp.asarray(self.dt, jnp.float64))
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del made_jump
        terms = _unwrap(terms)
        h = t1 - t0
        if isinstance(terms, _LTITerm):
            # Steps of exactly dt (a branch computing exp(A h) for another h would cost the
            # reverse pass both branches' residuals at every step: 3× the gradient's time).
            Phi, G0, G1 = solver_state
            y0 = eqx.error_if(
                y0,
                jnp.abs(h - self.dt) > 1e-9 * self.dt,
                "ExponentialFOH(dt) takes steps of exactly dt on a frozen plant: use "
                "diffrax.StepTo on a grid of spacing dt (the default of fdjax.simulate)",
            )
        else:
            A, B = terms.system(0.5 * (t0 + t1))[:2]
            Phi, G0, G1 = _foh_matrices(A, B, h)
        w0, w1 = terms.inputs(t0), terms.inputs(t1)
        y1 = Phi @ y0 + G0 @ w0 + G1 @ (w1 - w0)
        return y1, None, dict(y0=y0, y1=y1), solver_state, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


class PadeODE(eqx.Module):
    r"""The continuous loop (delay as its [n/n] Padé approximant) solved by ``diffrax``.

    Attributes:
        dt: output period (s), static; also the step of the default :class:`ExponentialFOH` solver
            and the spacing of the input samples.
        pade_order: order n of the delay's Padé approximant (static).
        solver: a diffrax solver; default :class:`ExponentialFOH` (exact for the frozen plant,
            exponential midpoint for the moving table).  General solvers (``diffrax.Tsit5()``,
            ``diffrax.Kvaerno5()``) work too, but the loop is stiff (the Padé delay's poles
            reach ~7e4 1/s), so they need many small steps.
        stepsize_controller: default ``StepTo(ts=output grid)`` for ExponentialFOH, else
            ``PIDController(rtol=1e-8, atol=1e-12)`` clipped to end steps on the output grid
            (where the first-order-hold input has its kinks).
        adjoint: diffrax adjoint; default ``RecursiveCheckpointAdjoint()``: reverse-mode through
            the solver's own steps with diffrax's online (treeverse) checkpointing — exact
            gradients of the discrete solution in little memory (measured: 7.3 MiB of temporaries
            for the gradient at six positions over 10,000 steps; ``benchmarks/closed_loop.py``).
            Backsolve adjoints would integrate the damped loop backwards, which is unstable,
            and :class:`ExponentialFOH` does not support them.
        max_steps: diffrax's step budget (static); default: the number of output steps for
            :class:`ExponentialFOH` (a tight budget keeps diffrax's buffers and checkpoints small),
            100 000 for other solvers.
    """

    dt: float = eqx.field(static=True, default=5.0e-5)
    pade_order: int = eqx.field(static=True, default=DEFAULT_PADE_ORDER)
    solver: diffrax.AbstractSolver | None = None
    stepsize_controller: diffrax.AbstractStepSizeController | None = None
    adjoint: diffrax.AbstractAdjoint | None = None
    max_steps: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        p = float(self.dt)
        if not (math.isfinite(p) and p > 0):
            raise ValueError(f"`PadeODE(dt=...)` must be positive, got {p:.6g}")
        n = self.pade_order
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or not 1 <= n <= 16:
            raise ValueError(f"`PadeODE(pade_order=...)` must be an int in [1, 16], got {n!r}")


def _unwrap(terms):
    # diffeqsolve wraps the user's term (direction of integration); the solver needs ours.
    while not isinstance(terms, _LTITerm | _MovingTerm):
        if not hasattr(terms, "term"):
            raise TypeError(
                f"ExponentialFOH solves only the loop terms of fdjax.simulate, got a "
                f"{type(terms).__name__}; pass a general solver (e.g. diffrax.Tsit5())"
            )
        terms = terms.term
    return terms


def _expm(M):
    r"""exp(M) after a diagonal balancing M → D⁻¹MD (Osborne's iteration, powers of two, so
    exact): the Padé delay's realisation is badly scaled (‖M‖₁ ~ 1e7 for a loop step), which
    costs exp and its derivative accuracy; balancing brings the norm down by orders of
    magnitude.  exp(D⁻¹MD) = D⁻¹ exp(M) D; D is held constant under differentiation."""
    Ma = jnp.abs(jax.lax.stop_gradient(M))
    off = Ma * (1.0 - jnp.eye(M.shape[0]))
    log_d = jnp.zeros(M.shape[0])
    for _ in range(12):
        d = jnp.exp2(log_d)
        B = off * d[None, :] / d[:, None]
        r, c = jnp.sum(B, 1), jnp.sum(B, 0)
        ok = (r > 0) & (c > 0)
        step = jnp.where(ok, 0.5 * jnp.log2(jnp.where(ok, r / jnp.where(ok, c, 1.0), 1.0)), 0.0)
        log_d = log_d + jnp.round(step)
    d = jnp.exp2(log_d)
    E = jsl.expm(M * d[None, :] / d[:, None], max_squarings=64)
    return E * d[:, None] / d[None, :]


def _foh_matrices(A, B, h):
    n, m = A.shape[0], B.shape[1]
    M = jnp.zeros((n + 2 * m, n + 2 * m), A.dtype)
    M = M.at[:n, :n].set(A * h).at[:n, n : n + m].set(B * h)
    M = M.at[n : n + m, n + m :].set(jnp.eye(m, dtype=A.dtype))
    E = _expm(M)
    return E[:n, :n], E[:n, n : n + m], E[:n, n + m :]


# ------------------------------------------------------------------------------------ results
class SampledLoop(eqx.Module):
    r"""The sampled-data closed loop as one discrete LTI system (see the module docstring):
    ``s_{k+1} = A s_k + B w_k``, ``y_k = C s_k + D w_k``, ``w = (r, ṙ, r̈, F3)``,
    ``y = (θ1, x2, x3, T1)``.  ``control.ss(A, B, C, D, dt)`` accepts it as it is.

    State: the plant's, the previous encoder angle, the controller's (Tustin PI or PID, then
    the MCM's sections), the d delayed commands.
    """

    A: Float[Array, "n n"]
    B: Float[Array, "n 4"]
    C: Float[Array, "4 n"]
    D: Float[Array, "4 4"]
    dt: Float[Array, ""]
    position_m: Float[Array, ""]
    delay_samples: int = eqx.field(static=True)


class Simulation(eqx.Module):
    r"""A simulated run of the closed loop.

    Attributes:
        t: output times (s), (n,).
        reference: r, ṙ, r̈ (m, m/s, m/s²), (n, 3).
        theta1: motor angle (rad).  x2: scale position (m).  x3: tool-point position (m).
        torque: motor torque T1 (N·m).  current: T1/k_motor (A).
        error_scale: e2 = r − x2 (m).  error_tool: e3 = r − x3 (m).
        position_m: table position Y (m) at each output time (constant unless moving).
        result: :class:`SimulationResult`.
        failed_at: index of the first output sample after which the run was stopped (n when
            it ran to the end).
        growth_rate: max Re s over the closed loop's poles (1/s) for a frozen plant, from the
            spectral radius of the one-step transition matrix (works under jit and vmap);
            ≥ 0 makes ``result`` ``unstable`` even before the run has grown past
            ``error_bound``.  None for the moving table.
        least_stable_pole: the closed loop's pole with the largest real part, as a continuous
            pole s (1/s; for the sampled loop s = ln z / T), when it was computed (a frozen
            plant and a call outside jit/vmap); else None.
    """

    t: Float[Array, "*batch n"]
    reference: Float[Array, "*batch n 3"]
    theta1: Float[Array, "*batch n"]
    x2: Float[Array, "*batch n"]
    x3: Float[Array, "*batch n"]
    torque: Float[Array, "*batch n"]
    current: Float[Array, "*batch n"]
    error_scale: Float[Array, "*batch n"]
    error_tool: Float[Array, "*batch n"]
    position_m: Float[Array, "*batch n"]
    result: SimulationResult
    failed_at: Int[Array, "*batch"]
    growth_rate: Float[Array, "*batch"] | None = None
    least_stable_pole: Complex[Array, "*batch"] | None = None

    def rms_error(self, which: str = "scale") -> Float[Array, "*batch"]:
        """RMS tracking error (m) over the run: ``"scale"`` (r − x2) or ``"tool"`` (r − x3)."""
        e = {"scale": self.error_scale, "tool": self.error_tool}.get(which)
        if e is None:
            raise ValueError(
                f"`Simulation.rms_error(which=...)` must be 'scale' or 'tool', got {which!r}"
            )
        return jnp.sqrt(jnp.mean(e * e, axis=-1))

    @property
    def message(self) -> str:
        """One line per run, e.g. "closed loop unstable at table position 0.7 m: pole at
        93.4 Hz growing at 12.3 1/s" or "… diverged …: stopped at t = 0.123 s, table position
        0.7 m"."""
        codes = np.atleast_1d(np.asarray(self.result._value))
        k = np.atleast_1d(np.asarray(self.failed_at))
        t = np.asarray(self.t).reshape(codes.shape[0], -1)
        pos = np.asarray(self.position_m).reshape(codes.shape[0], -1)
        poles = (
            None
            if self.least_stable_pole is None
            else np.atleast_1d(np.asarray(self.least_stable_pole))
        )
        names = {
            int(getattr(SimulationResult, a)._value): a
            for a in ("successful", "diverged", "solver_failed", "unstable")
        }
        lines = []
        for i, code in enumerate(codes):
            name = names[int(code)]
            j = min(int(k[i]), t.shape[1] - 1)
            if name == "successful":
                lines.append(f"simulation ok at table position {pos[i, 0]:.4g} m")
            elif name == "unstable":
                g = np.atleast_1d(np.asarray(self.growth_rate))[i]
                at = "" if poles is None else f"pole at {abs(poles[i].imag) / (2 * np.pi):.4g} Hz "
                lines.append(
                    f"closed loop unstable at table position {pos[i, 0]:.4g} m: "
                    f"{at}growing at {g:.4g} 1/s"
                )
            else:
                what = SimulationResult[getattr(SimulationResult, name)]
                lines.append(
                    f"{what}: stopped at t = {t[i, j]:.6g} s, table position {pos[i, j]:.4g} m"
                )
        return "\n".join(lines)


# ------------------------------------------------------------------------------------ sampled
def _tustin(A, B, C, D, h):
    """Bilinear (Tustin) discretisation of a continuous state space, unprewarped."""
    n = A.shape[0]
    Q = jnp.linalg.inv(jnp.eye(n) - 0.5 * h * A)
    Ad = Q @ (jnp.eye(n) + 0.5 * h * A)
    Bd = Q @ B * h
    Cd = C @ Q
    Dd = D + Cd @ B * (0.5 * h)
    return Ad, Bd, Cd, Dd


def _delay_samples(loop: AbstractLoop, method: SampledData) -> int:
    """d = τ/T, checked to be a whole number ≥ 1 (eagerly when τ is concrete; under jit, where
    ``SampledData(delay_samples=...)`` must give it, by the ``eqx.error_if`` of
    :func:`_check_delay`)."""
    concrete = _checks.is_concrete(loop.tau)
    if method.delay_samples is None and not concrete:
        raise ValueError(
            "`SampledData(delay_samples=...)` is required when the loop's delay τ is traced "
            "(a loop built inside jit/grad): the number of delay samples is static"
        )
    if not concrete:
        return int(method.delay_samples)
    ratio = float(loop.tau) / method.period
    d = round(ratio) if method.delay_samples is None else int(method.delay_samples)
    if d < 1 or abs(ratio - d) > 1e-6 * max(1.0, ratio):
        raise ValueError(
            f"`{type(loop).__name__}(tau=...)` must be a whole number ≥ 1 of servo periods for "
            f"the sampled-data simulation{'' if method.delay_samples is None else f' ({d})'}, "
            f"got τ = {float(loop.tau):.6g} s = {ratio:.6g} × `SampledData(period=...)` "
            f"{method.period:.6g} s"
        )
    return d


def _check_delay(loop, period: float, d: int, x):
    """Under jit: τ must be d servo periods (else the sampled loop would not be the loop)."""
    if _checks.is_concrete(loop.tau):
        return x
    bad = jnp.abs(loop.tau - d * period) > 1e-6 * d * period
    return eqx.error_if(x, bad, f"the loop's τ must equal SampledData(delay_samples={d}) × period")


def _sampled_impl(
    loop: AbstractLoop, plant: StateSpace, period: float, d: int, filter_method: str
) -> SampledLoop:
    h = jnp.asarray(period, jnp.float64)
    npl = plant.A.shape[0]
    # Plant: exact ZOH over one period.
    Mz = jnp.zeros((npl + 2, npl + 2)).at[:npl, :npl].set(plant.A).at[:npl, npl:].set(plant.B)
    E = _expm(Mz * h)
    Phi, Gam = E[:npl, :npl], E[:npl, npl:]
    if isinstance(loop, DoubleLoop):
        Ac = jnp.zeros((1, 1))
        Bc, Cc, Dc = jnp.ones((1, 1)), (loop.kv * loop.ki).reshape(1, 1), loop.kv.reshape(1, 1)
        fA, fB, fC, fD = loop.mcm.discretize(h, filter_method).state_space()
    elif isinstance(loop, PIDLoop):
        # z integrator and the derivative filter x_d (ẋ_d = −ω_d x_d + e), as in closed_loop.
        kd, wd = loop.kd, loop.wd
        Ac = jnp.diag(jnp.stack([jnp.zeros(()), -wd]))
        Bc = jnp.ones((2, 1))
        Cc = jnp.stack([loop.ki, -kd * wd * wd]).reshape(1, 2)
        Dc = (loop.kp + kd * wd).reshape(1, 1)
        fA, fB, fC, fD = jnp.zeros((0, 0)), jnp.zeros(0), jnp.zeros(0), jnp.ones(())
    else:
        raise TypeError(f"sampled-data simulation of {type(loop).__name__} is not implemented")
    cA, cB, cC, cD = _tustin(Ac, Bc, Cc, Dc, h)
    nc, nf = cA.shape[0], fA.shape[0]
    R = _Layout({"x": npl, "th": 1, "c": nc, "f": nf, "b": d})
    T1 = R.vector(b=jnp.zeros(d).at[d - 1].set(loop.k_motor))
    F3 = R.unit_input("F3")

    def out(i):
        return R.vector(x=plant.C[i]) + plant.D[i, 0] * T1 + plant.D[i, 1] * F3

    theta, x2 = out(0), out(1)
    if isinstance(loop, DoubleLoop):
        v_m = (theta - R.vector(th=jnp.ones(1))) * (loop.i_sc / h)
        e = (R.unit_input("r") - x2) * loop.kp + R.unit_input("r_dot") * loop.k_ffv - v_m
    else:
        e = R.unit_input("r") - x2
    u_c = R.vector(c=cC[0]) + cD[0, 0] * e
    u_f = R.vector(f=fC) + fD * u_c if nf else fD * u_c
    if isinstance(loop, DoubleLoop):
        u = u_f + R.unit_input("r_ddot") * loop.k_ffa
    else:
        u = u_f + R.unit_input("r_dot") * loop.k_ffv + R.unit_input("r_ddot") * loop.k_ffa
    rows = [
        jnp.concatenate([Phi, jnp.zeros((npl, R.width - npl))], 1)
        + Gam[:, :1] * T1[None, :]
        + Gam[:, 1:] * F3[None, :],
        theta[None, :],
        jnp.concatenate([jnp.zeros((nc, npl + 1)), cA, jnp.zeros((nc, R.width - npl - 1 - nc))], 1)
        + cB[:, :1] * e[None, :],
    ]
    if nf:
        o = R.offsets["f"]
        rows.append(
            jnp.concatenate([jnp.zeros((nf, o)), fA, jnp.zeros((nf, R.width - o - nf))], 1)
            + fB[:, None] * u_c[None, :]
        )
    o = R.offsets["b"]
    shift = jnp.concatenate(
        [jnp.zeros((d - 1, o)), jnp.eye(d - 1, d), jnp.zeros((d - 1, R.width - o - d))], 1
    )
    rows += [u[None, :], shift]
    M = jnp.concatenate(rows, 0)
    Y = jnp.stack([theta, x2, out(2), T1])
    n = R.n
    return SampledLoop(
        A=M[:, :n],
        B=M[:, n:],
        C=Y[:, :n],
        D=Y[:, n:],
        dt=h,
        position_m=plant.position_m,
        delay_samples=d,
    )


def sampled_closed_loop(
    loop: AbstractLoop, plant: StateSpace, method: SampledData = SampledData()
) -> SampledLoop:
    r"""The sampled-data closed loop of ``loop`` around ``plant`` as one discrete LTI system.

    Plant by its exact ZOH discretisation at the servo period T; motor speed by the backward
    difference of the encoder angle, ``i_sc (θ1_k − θ1_{k−1})/T``; PI (PID) by Tustin's rule;
    MCM as its second-order sections (paper Eqs. 3–4, :meth:`fdjax.MCM.discretize` with
    ``method.filter_method``);
    T1_k = k_m u_{k−d}.  See the module docstring.

    Args:
        loop: a :class:`fdjax.DoubleLoop` or :class:`fdjax.PIDLoop`.
        plant: the twin at one position (:func:`fdjax.state_space`).
        method: the servo period and delay samples.
    """
    _check_method(method, SampledData, "sampled_closed_loop")
    d = _delay_samples(loop, method)
    return _sampled_jit(loop, plant, method.period, d, method.filter_method)


_sampled_jit = eqx.filter_jit(_sampled_impl)


def _check_method(method, cls, fn):
    if not isinstance(method, cls):
        raise TypeError(f"`{fn}(method=...)` must be a {cls.__name__}, got {type(method).__name__}")


# ------------------------------------------------------------------------------------ ODE terms
class _Inputs(eqx.Module):
    """w(t) = (r, ṙ, r̈, F3) interpolated linearly between samples on a uniform grid."""

    W: Float[Array, "n 4"]
    dt: Float[Array, ""]

    def __call__(self, t):
        x = jnp.clip(t / self.dt, 0.0, self.W.shape[0] - 1.0)
        k = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, self.W.shape[0] - 2)
        a = x - k.astype(jnp.float64)
        return (1.0 - a) * self.W[k] + a * self.W[k + 1]


class _LTITerm(diffrax.AbstractTerm):
    A: Float[Array, "n n"]
    B: Float[Array, "n 4"]
    inputs: _Inputs

    def vf(self, t, y, args):
        return self.A @ y + self.B @ self.inputs(t)

    def contr(self, t0, t1, **kwargs):
        return t1 - t0

    def prod(self, vf, control):
        return vf * control


class _MovingPlant(eqx.Module):
    """Galerkin projection of the FE model at Y on the fixed modal basis V (N × m)."""

    drive: BallScrewDrive
    V: Float[Array, "N m"]
    n_elements: int = eqx.field(static=True)

    def at(self, position_m) -> StateSpace:
        fe = _assemble(self.drive, position_m, self.n_elements, True)
        V = self.V
        Mr, Kr, Cr = V.T @ fe.mass @ V, V.T @ fe.stiffness @ V, V.T @ fe.damping @ V
        m = V.shape[1]
        MK = jnp.linalg.solve(Mr, jnp.concatenate([Kr, Cr, V.T @ fe.inputs], 1))
        zero, eye = jnp.zeros((m, m)), jnp.eye(m)
        A = jnp.block([[zero, eye], [-MK[:, :m], -MK[:, m : 2 * m]]])
        B = jnp.concatenate([jnp.zeros((m, 2)), MK[:, 2 * m :]], 0)
        Cq = fe.outputs @ V
        return StateSpace(
            A=A,
            B=B,
            C=jnp.concatenate([Cq, jnp.zeros_like(Cq)], 1),
            D=jnp.zeros((3, 2)),
            C_velocity=jnp.concatenate([jnp.zeros_like(Cq), Cq], 1),
            natural_freq_hz=jnp.zeros(m),
            position_m=jnp.asarray(position_m, jnp.float64),
        )


def _moving_basis(drive, position_m, n_el: int, n_modes: int):
    fe = _assemble(drive, position_m, n_el, True)
    lam, Psi, L, _ = _generalised_eigh(fe)
    psi0 = L.T @ _rigid_mode(drive, n_el)
    Psi_m = Psi[:, :n_modes].at[:, 0].set(psi0 / jnp.linalg.norm(psi0))
    return jsl.solve_triangular(L.T, Psi_m, lower=False)


class _MovingTerm(diffrax.AbstractTerm):
    loop: AbstractLoop
    plant: _MovingPlant
    inputs: _Inputs
    y0_m: Float[Array, ""]
    pade_order: int = eqx.field(static=True)

    def system(self, t):
        w = self.inputs(t)
        ss = self.plant.at(self.y0_m + w[0])
        A, B, C, D = self.loop._closed_loop(ss, _pade_ss(self.loop.tau, self.pade_order))
        return A, B, C, D, w

    def vf(self, t, y, args):
        A, B, _, _, w = self.system(t)
        return A @ y + B @ w

    def contr(self, t0, t1, **kwargs):
        return t1 - t0

    def prod(self, vf, control):
        return vf * control


# ------------------------------------------------------------------------------------ simulate
def simulate(
    loop: AbstractLoop,
    plant: StateSpace | BallScrewDrive,
    reference,
    method: SampledData | PadeODE = SampledData(),
    *,
    duration: float | None = None,
    position_m: Float[ArrayLike, ""] | None = None,
    disturbance: Float[ArrayLike, " n"] | None = None,
    moving: bool = False,
    n_modes: int | None = None,
    n_elements: int = DEFAULT_ELEMENTS,
    error_bound: float = 0.01,
    throw: bool = True,
) -> Simulation:
    r"""Simulate the closed loop on a reference motion (paper Figs. 16–17).

    The loop of :func:`fdjax.closed_loop` (DoubleLoop: P on x2 outside, PI on the motor speed
    inside, MCM, feed-forward k_ffv ṙ and k_ffa r̈ from the same reference, delay τ, motor gain)
    around the drive's twin, from rest at t = 0, over ``duration`` seconds:

    * ``method=SampledData(period)`` — the exact sampled-data loop (:func:`sampled_closed_loop`)
      run by ``lax.scan``; outputs at every servo period;
    * ``method=PadeODE(dt, pade_order, solver, …)`` — the continuous loop with a Padé delay,
      solved by ``diffrax.diffeqsolve``; outputs every ``dt``.

    With ``moving=True`` (either method, a drive plant) the plant's matrices follow the table,
    Y(t) = Y₀ + r(t): the FE model is rebuilt along the motion and projected on the modes at Y₀
    (exponential midpoint rule over each step; no growth rate, divergence is still caught).

    Differentiable (``jax.grad``) in every leaf of ``loop`` and of a drive plant; ``jax.vmap``
    over positions compiles once (pass ``throw=False`` and read ``result``).

    Args:
        loop: the controller (:class:`fdjax.DoubleLoop` or :class:`fdjax.PIDLoop`).
        plant: a :class:`fdjax.StateSpace` at one position, or a :class:`fdjax.BallScrewDrive`
            with ``position_m`` (its twin is built with :func:`fdjax.state_space`).
        reference: the motion, any object with ``evaluate(t) -> (r, ṙ, r̈, …)`` such as a
            :class:`fdjax.Trajectory`; r is the table's displacement from Y₀ (m).
        method: :class:`SampledData` (default) or :class:`PadeODE`.
        duration: simulated time (s), static; default the reference's ``duration``.
        position_m: table position Y₀ (m) for a drive plant.
        disturbance: force F3 at the tool point (N) on the output grid, (n,); default 0.
        moving: moving-table mode (a drive plant; slower: the loop is rebuilt every step).
        n_modes: modes of the twin (static); default the 4 kHz band's count.
        n_elements: screw elements of the twin (static).
        error_bound: a scale error |r − x2| beyond this (m) counts as divergence.
        throw: raise when the result is not ``successful`` — the loop is unstable (growth
            rate ≥ 0), the run diverged, or the solver failed — eagerly as a RuntimeError naming
            the table position (and the pole, or the time it stopped); under jit as an
            ``eqx.error_if``.

    Returns:
        A :class:`Simulation`; its ``result`` is ``successful``, ``unstable``, ``diverged`` or
        ``solver_failed``, and ``message`` says it in words.
    """
    fn = "simulate"
    if not isinstance(loop, AbstractLoop):
        raise TypeError(
            f"`{fn}(loop=...)` must be an fdjax.DoubleLoop or PIDLoop, got {type(loop).__name__}"
        )
    if not isinstance(method, SampledData | PadeODE):
        raise TypeError(
            f"`{fn}(method=...)` must be fdjax.SampledData or fdjax.PadeODE, "
            f"got {type(method).__name__}"
        )
    if not callable(getattr(reference, "evaluate", None)):
        raise TypeError(
            f"`{fn}(reference=...)` must have an evaluate(t) method (e.g. an "
            f"fdjax.Trajectory), got {type(reference).__name__}"
        )
    if duration is None:
        duration = getattr(reference, "duration", None)
        if duration is None:
            raise ValueError(f"`{fn}(duration=...)` is required for this reference")
        knots = getattr(reference, "t_knots", None)
        if not _checks.is_concrete(duration) and knots is not None and _checks.is_concrete(knots):
            # inside jit, indexing a closed-over trajectory is staged: read its end on the host
            duration = float(np.asarray(knots)[-1])
    if not _checks.is_concrete(duration):
        raise ValueError(
            f"`{fn}(duration=...)` must be a concrete number (it sets the number of output samples)"
        )
    duration = float(duration)
    if not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"`{fn}(duration=...)` must be positive, got {duration:.6g}")
    eb = float(error_bound)
    if not (math.isfinite(eb) and eb > 0):
        raise ValueError(f"`{fn}(error_bound=...)` must be positive, got {eb:.6g}")
    dt = method.period if isinstance(method, SampledData) else method.dt
    n = int(round(duration / dt)) + 1
    if moving and not isinstance(plant, BallScrewDrive):
        raise ValueError(
            f"`{fn}(moving=True)` needs a BallScrewDrive plant (the model is rebuilt along the "
            f"motion), got {type(plant).__name__}"
        )
    if isinstance(plant, BallScrewDrive):
        if position_m is None:
            raise ValueError(f"`{fn}(position_m=...)` is required when the plant is a drive")
        plant._check_positions(position_m)
        ratio = plant.screw.ratio
        if (
            isinstance(loop, DoubleLoop)
            and _checks.is_concrete(loop.i_sc)
            and _checks.is_concrete(ratio)
            and abs(float(loop.i_sc) / float(ratio) - 1.0) > 1e-9
        ):
            raise ValueError(
                f"`DoubleLoop(i_sc=...)` must be the drive's screw ratio lead/2π = "
                f"{float(ratio):.6g} m/rad (it scales the encoder speed), "
                f"got {float(loop.i_sc):.6g}"
            )
        if n_modes is None:
            n_modes = count_modes(plant, n_elements=n_elements)
    elif isinstance(plant, StateSpace):
        if position_m is not None or moving:
            raise ValueError(f"`{fn}(position_m=...)` is only for a BallScrewDrive plant")
    else:
        raise TypeError(
            f"`{fn}(plant=...)` must be an fdjax.StateSpace or BallScrewDrive, "
            f"got {type(plant).__name__}"
        )
    if disturbance is None:
        force = jnp.zeros(n)
    else:
        force = jnp.asarray(disturbance, jnp.float64)
        if force.shape != (n,):
            raise ValueError(
                f"`{fn}(disturbance=...)` must have shape ({n},) (one value per "
                f"output sample), got {force.shape}"
            )
    d = _delay_samples(loop, method) if isinstance(method, SampledData) else 0
    sim, A = _simulate_jit(
        loop,
        plant,
        reference,
        method,
        position_m,
        force,
        n,
        d,
        moving,
        None if n_modes is None else int(n_modes),
        int(n_elements),
        eb,
    )
    if A is not None and _checks.is_concrete(A):
        # Poles on the host (NumPy): a batched non-symmetric eig has dead-locked XLA:CPU.
        lam = np.linalg.eigvals(np.asarray(A)).astype(complex)
        if isinstance(method, SampledData):
            lam = np.log(lam[lam != 0]) / method.period  # z = 0: the delay line's shift
        pole = lam[np.argmax(lam.real)]
        sim = eqx.tree_at(
            lambda s: s.least_stable_pole, sim, jnp.asarray(pole), is_leaf=lambda x: x is None
        )
    if throw:
        failed = sim.result != SimulationResult.successful
        if _checks.is_concrete(sim.failed_at):
            if bool(np.any(np.asarray(failed))):
                raise RuntimeError(sim.message)
        else:
            sim = eqx.error_if(sim, failed, "closed-loop simulation diverged or failed")
    return sim


@eqx.filter_jit
def _simulate_jit(
    loop, plant, reference, method, position_m, force, n, d, moving, n_modes, n_el, error_bound
):
    dt = method.period if isinstance(method, SampledData) else method.dt
    t = jnp.arange(n, dtype=jnp.float64) * dt
    r, v, a = (jnp.asarray(x, jnp.float64) for x in reference.evaluate(t)[:3])
    W = jnp.stack([r, v, a, force], 1)
    if isinstance(plant, BallScrewDrive):
        pos0 = jnp.asarray(position_m, jnp.float64)
        if not moving:
            plant = state_space(plant, pos0, n_modes=n_modes, n_elements=n_el)
    else:
        pos0 = plant.position_m
    if isinstance(method, SampledData) and moving:
        r_mid = jnp.asarray(reference.evaluate(t + 0.5 * dt)[0], jnp.float64)
        Y, finite = _sampled_moving(loop, plant, method, d, W, pos0, r_mid, n_modes, n_el)
        failed_at, Y = _first_bad(finite, Y, W, error_bound)
        result = SimulationResult.where(
            failed_at < n, SimulationResult.diverged, SimulationResult.successful
        )
        growth, A, pos = None, None, pos0 + W[:, 0]
    elif isinstance(method, SampledData):
        sl = _sampled_impl(loop, plant, method.period, d, method.filter_method)
        Y, finite = _lifted_outputs(_check_delay(loop, method.period, d, sl.A), sl.B, sl.C, sl.D, W)
        failed_at, Y = _first_bad(finite, Y, W, error_bound)
        result = SimulationResult.where(
            failed_at < n, SimulationResult.diverged, SimulationResult.successful
        )
        growth = _growth_rate(sl.A, sl.dt)
        result = SimulationResult.where(growth >= 0, SimulationResult.unstable, result)
        pos = jnp.full(n, pos0)
        A = sl.A
    else:
        Y, failed_at, result, pos, A, growth = _ode(
            loop, plant, method, W, t, pos0, moving, n_modes, n_el, error_bound
        )
    sim = Simulation(
        t=t,
        reference=W[:, :3],
        theta1=Y[:, 0],
        x2=Y[:, 1],
        x3=Y[:, 2],
        torque=Y[:, 3],
        current=Y[:, 3] / loop.k_motor,
        error_scale=r - Y[:, 1],
        error_tool=r - Y[:, 2],
        position_m=pos,
        result=result,
        failed_at=failed_at,
        growth_rate=growth,
    )
    return sim, A


def _growth_rate(Phi, h, squarings: int = 48):
    r"""σ = ln ρ(Φ)/h (1/s): the growth rate of the least stable pole of a loop whose state
    advances by Φ every h seconds, from ‖Φ^N‖^{1/N} → ρ(Φ) at N = 2^48 (Gelfand's formula),
    by repeated squaring with the scale carried in logarithms.  Only matrix products, so it
    runs under jit and vmap (a batched non-symmetric eig has dead-locked XLA:CPU); the error of
    ln ρ is the 1/N-th power of the eigenvector condition, negligible, plus a few ulps."""
    Phi = jax.lax.stop_gradient(Phi)
    nrm = jnp.linalg.norm(Phi)
    M, log_s = Phi / nrm, jnp.log(nrm)
    for _ in range(squarings):
        M = M @ M
        nrm = jnp.linalg.norm(M)
        M, log_s = M / nrm, 2.0 * log_s + jnp.log(nrm)
    return log_s / (2.0**squarings * h)


_CHUNK = 16  # samples per block of the lifted recursion


def _lifted_outputs(A, B, C, D, W, K: int = _CHUNK):
    r"""Outputs y_k = C s_k + D w_k of s_{k+1} = A s_k + B w_k, s_0 = 0, by the lifted
    (block) recursion: with s_c the state at the start of block c of K samples,

        s_{c+1} = A^K s_c + Σ_{i<K} A^{K−1−i} B w_{cK+i},
        y_{cK+j} = C A^j s_c + Σ_{i<j} C A^{j−1−i} B w_{cK+i} + D w_{cK+j}.

    Only the block states are sequential (n/K steps); the input terms of every block and the
    outputs from the block states are large matrix products.  The same arithmetic as the plain
    recursion, regrouped: on a CPU, a scan of one small matrix–vector product per sample is
    bound by its per-step overhead, and under ``vmap`` over positions by one tiny batched dot
    per position and step.  Returns the outputs (n, n_out) and, per sample, whether its block
    state is finite."""
    n, m = W.shape
    nb = -(-n // K)
    Wp = jnp.concatenate([W, jnp.zeros((nb * K - n, m))]).reshape(nb, K, m)
    powers = [jnp.eye(A.shape[0])]
    for _ in range(K):
        powers.append(A @ powers[-1])
    AK = powers[K]
    # Input to block state: G = [A^{K−1}B, …, AB, B] (n × K·m).
    G = jnp.concatenate([powers[K - 1 - i] @ B for i in range(K)], axis=1)
    U = Wp.reshape(nb, K * m) @ G.T

    def body(s, u):
        return AK @ s + u, s

    S = jax.lax.scan(body, jnp.zeros(A.shape[0]), U)[1]  # state at each block's start
    obs = jnp.stack([C @ powers[j] for j in range(K)])  # (K, p, n)
    markov = [C @ powers[k] @ B for k in range(K)]  # C A^k B
    p = C.shape[0]
    zero = jnp.zeros((p, m))
    T = jnp.block(
        [
            [D if i == j else markov[j - 1 - i] if i < j else zero for i in range(K)]
            for j in range(K)
        ]
    )  # (K·p, K·m), block lower triangular
    Y = jnp.einsum("jon,cn->cjo", obs, S) + (Wp.reshape(nb, K * m) @ T.T).reshape(nb, K, p)
    finite = jnp.repeat(jnp.all(jnp.isfinite(S), axis=1), K)[:n]
    return Y.reshape(nb * K, p)[:n], finite


def _sampled_moving(loop, drive, method: SampledData, d, W, pos0, r_mid, n_modes, n_el):
    r"""The sampled-data loop with the plant following the table: a time-varying recursion

        s_{k+1} = A_d(Y_{k+1/2}) s_k + B_d(Y_{k+1/2}) w_k,   y_k = C_d(Y_k) s_k + D_d(Y_k) w_k,

    the loop of :func:`sampled_closed_loop` rebuilt around the FE model at Y, projected on the
    modes at Y₀ (as for :class:`PadeODE`), over step k at the midpoint position
    Y_{k+1/2} = Y₀ + r(t_k + T/2) (exponential midpoint rule, second order in the plant's
    variation over a step) and at Y_k = Y₀ + r(t_k) for the outputs.  A ``lax.scan`` of one
    step per sample (no lifting: the matrices change every sample)."""
    V = _moving_basis(drive, pos0, n_el, n_modes)
    plant = _MovingPlant(drive, V, n_el)

    def system(y):
        return _sampled_impl(loop, plant.at(y), method.period, d, method.filter_method)

    s0 = _check_delay(loop, method.period, d, jnp.zeros(system(pos0).A.shape[0]))

    def step(s, inputs):
        w, y_k, y_mid = inputs
        out, tr = system(y_k), system(y_mid)
        return tr.A @ s + tr.B @ w, (out.C @ s + out.D @ w, jnp.all(jnp.isfinite(s)))

    _, (Y, finite) = jax.lax.scan(step, s0, (W, pos0 + W[:, 0], pos0 + r_mid))
    return Y, finite


def _first_bad(finite, Y, W, bound):
    """Index of the first output sample whose state is non-finite (``finite`` false) or whose
    scale error is beyond ``bound`` (n when none); the outputs from there on are frozen at the
    last good sample, so a diverging run never hands NaN or overflow to the user."""
    n = W.shape[0]
    e = W[:, 0] - Y[:, 1]
    good = jnp.isfinite(e) & (jnp.abs(e) <= bound) & finite & jnp.all(jnp.isfinite(Y), axis=1)
    first_bad = jnp.where(jnp.all(good), n, jnp.argmin(good)).astype(jnp.int32)
    keep = jnp.arange(n, dtype=jnp.int32) < first_bad
    last = jnp.maximum(first_bad - 1, 0)
    Y = jnp.where(jnp.isfinite(Y), Y, 0.0)
    Y = jnp.where(keep[:, None], Y, Y[last][None, :])
    return first_bad, Y


def _ode(loop, plant, method: PadeODE, W, t, pos0, moving, n_modes, n_el, bound):
    n = W.shape[0]
    dt = jnp.asarray(method.dt, jnp.float64)
    inputs = _Inputs(W, dt)
    if moving:
        V = _moving_basis(plant, pos0, n_el, n_modes)
        term = _MovingTerm(loop, _MovingPlant(plant, V, n_el), inputs, pos0, method.pade_order)
        A0 = term.system(0.0)[0]
        solver = method.solver if method.solver is not None else ExponentialFOH(method.dt)
    else:
        cl = _closed_loop_impl(loop, plant, method.pade_order)
        term = _LTITerm(cl.A, cl.B, inputs)
        A0 = cl.A
        solver = method.solver if method.solver is not None else ExponentialFOH(method.dt)
    if method.stepsize_controller is not None:
        controller = method.stepsize_controller
    elif isinstance(solver, ExponentialFOH):
        controller = diffrax.StepTo(ts=t)
    else:
        # Steps end on the input samples: the first-order-hold input has a kink at each one,
        # which an error estimate spanning it would mistake for stiffness.
        controller = diffrax.ClipStepSizeController(
            diffrax.PIDController(rtol=1e-8, atol=1e-12), step_ts=t
        )
    adjoint = method.adjoint if method.adjoint is not None else diffrax.RecursiveCheckpointAdjoint()
    if isinstance(solver, ExponentialFOH) and isinstance(adjoint, diffrax.BacksolveAdjoint):
        raise ValueError(
            "`PadeODE(adjoint=diffrax.BacksolveAdjoint())` is not supported with the "
            "ExponentialFOH solver (it solves a backward ODE with a general solver's terms); "
            "use diffrax.RecursiveCheckpointAdjoint() (default) or DirectAdjoint()"
        )
    max_steps = method.max_steps
    if max_steps is None:
        max_steps = n + 2 if isinstance(solver, ExponentialFOH) else 100_000

    dt0 = None if isinstance(controller, diffrax.StepTo) else method.dt
    sol = diffrax.diffeqsolve(
        term,
        solver,
        t0=0.0,
        t1=t[-1],
        dt0=dt0,
        y0=jnp.zeros(A0.shape[0]),
        saveat=diffrax.SaveAt(ts=t),
        stepsize_controller=controller,
        adjoint=adjoint,
        max_steps=max_steps,
        throw=False,
    )
    X = sol.ys
    if moving:
        C, D = jax.vmap(lambda tk: term.system(tk)[2:4])(t)
        Y = jnp.einsum("kon,kn->ko", C, X) + jnp.einsum("koi,ki->ko", D, W)
        pos = pos0 + W[:, 0]
    else:
        Y = X @ cl.C.T + W @ cl.D.T
        pos = jnp.full(n, pos0)
    first_bad, Y = _first_bad(jnp.all(jnp.isfinite(X), axis=1), Y, W, bound)
    if not moving:
        growth = _growth_rate(_expm(cl.A * dt), dt)
        unstable = growth >= 0
    else:
        growth = None
    solver_ok = sol.result == diffrax.RESULTS.successful
    failed_at = jnp.where(solver_ok, first_bad, jnp.minimum(first_bad, n - 1))
    result = SimulationResult.where(
        solver_ok,
        SimulationResult.where(
            first_bad < n, SimulationResult.diverged, SimulationResult.successful
        ),
        SimulationResult.solver_failed,
    )
    if not moving:
        result = SimulationResult.where(unstable, SimulationResult.unstable, result)
    return Y, failed_at, result, pos, (None if moving else cl.A), growth
