r"""How the loop around the drive is modelled and run: the sampled loop as the servo runs it,
the continuous loop, and the continuous loop solved by diffrax.

Each method carries its behaviour, as diffrax's solvers do, so the analyses
(:func:`fdjax.loop_margins`, :func:`fdjax.closed_loop`, :func:`fdjax.check_stability`) and
:func:`fdjax.simulate` never branch on the method's type:

* :class:`SampledData` — what a servo drive does.  At the servo period T the controller reads
  the scale x2 and the encoder angle θ1 and computes the current command u_k; the command
  reaches the motor d samples later (a shift register); between samples the torque is held
  (zero-order hold).  The plant's exact ZOH discretisation over one period,
  x_{k+1} = Φ x_k + Γ (T1_k, F3_k), [[Φ, Γ], [0, I]] = exp([[A, B], [0, 0]] T), the motor
  speed by the backward difference v_m,k = i_sc (θ1_k − θ1_{k−1})/T, every block of the law
  discretised as the servo runs it (PI and PID by Tustin's rule, the MCM as its second-order
  sections, :meth:`fdjax.MCM.discretize`), one discrete LTI system run by the lifted recursion.
  Exact for the sampled loop: nothing is approximated but the plant's modal truncation.
* :class:`Continuous` — the continuous loop, the delay e^{−sτ} exact in open loops and as its
  [n/n] Padé approximant where a realisation is needed (closed loop, poles).
* :class:`PadeODE` — the continuous loop with a Padé delay solved by ``diffrax.diffeqsolve``;
  the inputs w = (r, ṙ, r̈, F3) are sampled on the output grid and interpolated linearly in
  between (a first-order hold, as ``scipy.signal.lsim`` does).  The default solver
  :class:`ExponentialFOH` integrates that ODE exactly.

The sampled loop adds the half-sample lags of the ZOH and of the backward difference, which the
continuous loop lumps into τ: the two agree to O(T) (tested: first-order convergence as T → 0).
"""

from __future__ import annotations

import abc
import math
from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Complex, Float

from .._checks import is_concrete, static_number
from .._control._blocks import DEFAULT_PADE_ORDER, FILTER_METHODS, pade_order
from .._control._controllers import AbstractController
from .._control._interconnect import (
    SampledParts,
    SampledPlant,
    continuous_channels,
    continuous_closed_loop,
    continuous_open_loops,
    frf_channels,
    sampled_closed_loop_matrices,
    sampled_open_loops,
)
from .._control._servo import Servo
from .._drive._twin import StateSpace
from .._lti import LTI, expm
from .._results import RESULTS
from ._lifted import MARGINAL, first_bad, growth_rate, held, lifted_outputs

__all__ = ["AbstractLoopModel", "SampledData", "Continuous", "PadeODE", "ExponentialFOH"]

_TWO_PI = 2.0 * math.pi
_NO_BACKSOLVE = (
    "`PadeODE(adjoint=diffrax.BacksolveAdjoint())` is not supported with the ExponentialFOH "
    "solver (it solves a backward ODE with a general solver's terms); use "
    "diffrax.RecursiveCheckpointAdjoint() (default) or DirectAdjoint()"
)


class AbstractLoopModel(eqx.Module):
    """How the loop is modelled: its closed loop, its open loops, and (where it can) a run."""

    takes_frf: ClassVar[bool] = True  # open loops from a (measured) FRF array
    bytes_per_sample: ClassVar[int] = 520  # memory a run holds at its peak per output sample

    @abc.abstractmethod
    def closed_loop(self, controller: AbstractController, plant: StateSpace,
                    servo: Servo) -> LTI:
        """The closed loop around the twin ``plant`` (inputs r, ṙ, r̈, F3; outputs θ1, x2,
        x3, T1), continuous or discrete."""

    @abc.abstractmethod
    def open_loop_model(self, controller: AbstractController, plant: StateSpace,
                        servo: Servo) -> tuple:
        """(L_fn, params): ``L_fn(params, ω)`` gives the open loops at angular frequencies ω as
        a dict (``plant_input``, ``speed``, ``position``; None where the law closes no such
        loop), ``params`` the differentiable data it needs (the model margins refine their
        crossings on it)."""

    @abc.abstractmethod
    def frf_open_loops(self, controller: AbstractController, H: Complex[Array, "*b freq 3 2"],
                       omega: Float[Array, " freq"], screw_ratio: Float[ArrayLike, ""],
                       servo: Servo, position_m: Float[ArrayLike, "*b"] | None) -> dict:
        """The open loops from an FRF array H (…, freq, 3, 2) of the plant."""

    def max_freq_hz(self, servo: Servo) -> float:
        """The highest frequency the model's open loops are defined at (Hz)."""
        return math.inf

    def frozen_growth(self, controller: AbstractController, plant: StateSpace,
                      servo: Servo) -> Float[Array, ""]:
        """The growth rate (1/s) of the least stable pole of the closed loop around the twin
        ``plant`` (≥ 0: unstable); the models that run a simulation define it."""
        raise NotImplementedError

    def check_use(self, controller: AbstractController, plant: StateSpace | None,
                  servo: Servo, where: str) -> None:
        """Refuse, eagerly, a use the model cannot serve (``where``: the caller's argument);
        ``plant`` is one twin, a batch of them, or None for a drive or an FRF array."""

    def poles_to_s(self, lam: Complex[Array, "*b n"], servo: Servo) -> Complex[Array, "*b n"]:
        """Continuous-time equivalents of the closed loop's eigenvalues (1/s)."""
        return lam

    @property
    def name(self) -> str:
        """The model's class name (as printed in reports)."""
        return type(self).__name__


def growing(growth, period):
    """Whether a growth rate (1/s) is that of an unstable loop: above the round-off of a pole at
    s = 0 (:data:`MARGINAL` / ``period``), which is marginal, not unstable."""
    return growth * period > MARGINAL


def _check_filters_sampled(controller, servo, fn: str) -> None:
    """The MCM filters of ``controller`` (where it has one and its frequencies are concrete)
    below the Nyquist frequency of ``servo``: a ``ValueError`` naming ``fn(controller=...)``
    and the values, where the discretisation would fail inside the compiled program."""
    mcm = getattr(controller, "mcm", None)
    banks = [b for b in (getattr(mcm, "peak", None), getattr(mcm, "notch", None))
             if b is not None]
    omegas = [b.omega for b in banks]
    if not omegas or not all(is_concrete(w) for w in omegas):
        return
    top = max(float(jnp.max(w)) for w in omegas) / (2 * math.pi)
    nyquist = 0.5 / float(servo.period)
    if not top < nyquist:
        raise ValueError(f"`{fn}(controller=...)` has a filter at {top:.6g} Hz, not below the "
                         f"Nyquist frequency {nyquist:.6g} Hz of the servo that samples it "
                         f"(period {float(servo.period):.6g} s): lower the filter, or give a "
                         "faster servo")


class SampledData(AbstractLoopModel):
    r"""The sampled-data loop as the servo runs it (module docstring), at the servo's period
    with its delay of d whole samples (:class:`fdjax.Servo`); outputs at every period.

    Attributes:
        filter_method: how the MCM is discretised, ``"fitted"`` (default, within 1 % of the
            continuous filter below Nyquist/4) or ``"tustin"`` (prewarped bilinear, what many
            drives run); see :meth:`fdjax.MCM.discretize`.
        shared: None (default; each loop discretises the design where it is built) or the
            discretisation of one design around one plant (:meth:`sharing`).
    """

    filter_method: str = eqx.field(static=True, default="fitted")
    shared: SampledParts | None = None
    takes_frf: ClassVar[bool] = False
    # measured on the reference drive (6 kept modes): 260–315 B between runs of 0.2 and 1.6
    # million samples
    bytes_per_sample: ClassVar[int] = 320

    def __check_init__(self):
        if self.filter_method not in FILTER_METHODS:
            raise ValueError(
                "`SampledData(filter_method=...)` must be 'fitted' or 'tustin', "
                f"got {self.filter_method!r}"
            )

    def parts(self, controller, plant, servo) -> SampledParts:
        """The discrete law and the zero-order-hold plant at the plant's position: what both
        the closed loop and the open loops are built from (:meth:`sharing` computes them once
        for both)."""
        if self.shared is not None:
            return self.shared
        law = controller.law(plant.position_m)
        return SampledParts.of(law, plant, servo.period, self.filter_method)

    def check_use(self, controller, plant, servo, where: str) -> None:
        """A controller whose MCM (concrete) has a filter at or above the servo's Nyquist
        frequency is refused, naming the caller's controller argument (the discretisation
        would raise inside the compiled program, without the values).  A shared
        discretisation (:meth:`sharing`) serves the one design and twin it was
        built from: another plant than one twin is refused, and, where the arguments are
        concrete (an eager call), another controller, twin or servo is found by building the
        discretisation again and comparing.  One built from concrete values and used with
        traced arguments (inside ``jit``/``vmap``/``grad``) is refused: it cannot follow them
        (another position or design would run the shared one's, and the gradient through it
        is zero)."""
        _check_filters_sampled(controller, servo, where.split("(")[0])
        if self.shared is None:
            return
        if plant is None or plant.A.ndim != 2:
            raise ValueError(f"`{where}` holds the discretisation of one design around one twin "
                             "(SampledData.sharing): give that twin as the plant (not a drive, "
                             "a batch or an FRF array), or use SampledData() without it")
        concrete = lambda tree: all(is_concrete(x) for x in jax.tree_util.tree_leaves(  # noqa: E731
            eqx.filter(tree, eqx.is_array)))
        if concrete(self.shared) and not concrete((controller, plant)):
            raise ValueError(f"`{where}` holds a discretisation built outside this traced "
                             "function (SampledData.sharing of concrete values): it cannot "
                             "follow the traced controller or twin (their gradient "
                             "through it would be zero); call sharing inside the traced "
                             "function, or use SampledData()")
        if concrete((self.shared, controller, plant, servo)):
            fresh = _parts(SampledData(self.filter_method), controller, plant, servo)
            if not bool(eqx.tree_equal(fresh, self.shared)):
                raise ValueError(f"`{where}` holds the discretisation of another design, twin "
                                 "or servo (SampledData.sharing(controller, plant, servo) serves "
                                 "those three only); share this one's, or use SampledData()")

    def sharing(self, controller, plant, servo) -> SampledData:
        """This model holding the discretisation of ``controller`` around ``plant``: its closed
        loop and its open loops (a simulation and the margins of one design) then share one
        discrete law and one matrix exponential.  Only for that controller and plant: the
        twin at one position (:func:`fdjax.state_space`), not the drive."""
        from .._checks import instance
        from .._control._controllers import AbstractController
        from .._control._servo import Servo
        from .._drive._twin import StateSpace

        instance(controller, AbstractController, "SampledData.sharing(controller=...)",
                 "an fdjax controller")
        instance(plant, StateSpace, "SampledData.sharing(plant=...)",
                 "an fdjax.StateSpace (the twin at one position: fdjax.state_space(drive, "
                 "position_m))")
        instance(servo, Servo, "SampledData.sharing(servo=...)")
        # eagerly, compiled (once per shapes), so that the matrix exponential's loops do not
        # run op by op; traced, part of the caller's program
        leaves = jax.tree_util.tree_leaves(eqx.filter((controller, plant, servo), eqx.is_array))
        eager = all(is_concrete(x) for x in leaves)
        parts = (_parts if eager else SampledData.parts)(self, controller, plant, servo)
        return eqx.tree_at(lambda m: m.shared, self, parts, is_leaf=lambda x: x is None)

    def closed_loop(self, controller, plant, servo) -> LTI:
        return sampled_closed_loop_matrices(
            self.parts(controller, plant, servo), plant, servo.k_motor, servo.period,
            servo.delay_samples,
        )

    def open_loop_model(self, controller, plant, servo):
        law = controller.law(plant.position_m)
        reads = (law.reads("x2"), law.reads("v_m"))
        parts = self.parts(controller, plant, servo)
        params = (parts.sampled, SampledPlant.of(parts, plant, servo.period), servo.k_motor)
        d = servo.delay_samples

        def L_fn(p, omega):
            return sampled_open_loops(p[0], reads, p[1], omega, p[2], d)

        return L_fn, params

    def frf_open_loops(self, controller, H, omega, screw_ratio, servo, position_m):
        raise ValueError(
            "the sampled loop needs the plant in state space (its zero-order-hold equivalent "
            "is not a function of the FRF): pass the drive with `position_m=...` or a "
            "`fdjax.state_space(...)` twin, or analyse the FRF with `method=fdjax.Continuous()`"
        )

    def max_freq_hz(self, servo) -> float:
        return 0.5 / servo.period

    def poles_to_s(self, lam, servo):
        # z = 0 (the delay line's shift, a dead-beat pole) maps to −inf; keep it finite.
        mag = jnp.maximum(jnp.abs(lam), 1e-300)
        return jax.lax.complex(jnp.log(mag), jnp.angle(lam)) / servo.period

    # -------------------------------------------------------------- runs
    def output_period(self, servo) -> float:
        """The spacing of the run's output samples (s): the servo's period."""
        return float(servo.period)

    def run(self, controller, plant, W, servo, bound):
        r"""One run of the closed loop around the twin ``plant`` (the work of
        :func:`fdjax.simulate`, which builds ``W`` and reads the result): the discrete
        recursion s_{k+1} = A s_k + B w_k, y_k = C s_k + D w_k from s_0 = 0, one row of ``W``
        (r, ṙ, r̈, F3) per period.

        Returns:
            (Y, failed_at, result, growth): the outputs (θ1, x2, x3, T1) per sample, frozen
            from the first sample whose state is non-finite or whose error passes ``bound``
            (m); that sample's index (len(W) when none); the result code
            (:data:`fdjax.RESULTS`: successful, diverged or unstable); the growth rate of the
            least stable pole (1/s).
        """
        sl = self.closed_loop(controller, plant, servo)
        Y, finite = lifted_outputs(sl.A, sl.B, sl.C, sl.D, W)
        failed_at, Y = first_bad(finite, Y, W, bound)
        growth = self._growth(sl, servo)
        result = RESULTS.where(failed_at < W.shape[0], RESULTS.diverged, RESULTS.successful)
        result = RESULTS.where(growing(growth, servo.period), RESULTS.unstable, result)
        return Y, failed_at, result, growth

    def _growth(self, sl, servo):
        return growth_rate(sl.A, servo.period)

    def frozen_growth(self, controller, plant, servo):
        """The least stable pole's growth rate ln|z|/T (1/s) of the sampled loop around
        ``plant``."""
        return self._growth(self.closed_loop(controller, plant, servo), servo)

    def run_moving(self, controller, moving, W, positions, mid_positions, servo, bound):
        r"""The time-varying recursion s_{k+1} = A_d(Y_{k+1/2}) s_k + B_d(Y_{k+1/2}) w_k,
        y_k = C_d(Y_k) s_k + D_d(Y_k) w_k: the sampled loop rebuilt around the projected plant
        at the step's midpoint position (exponential midpoint rule, second order in the plant's
        variation over a step) and at Y_k for the outputs; a ``lax.scan`` of one step per
        sample (the matrices change every sample)."""

        if self.shared is not None:
            raise ValueError("`simulate(moving=True)` rebuilds the loop at every position: pass "
                             "fdjax.SampledData() without a shared discretisation")

        def system(y):
            return self.closed_loop(controller, moving.at(y), servo)

        s0 = jnp.zeros(system(positions[0]).A.shape[0])

        # rematerialised in the reverse pass: a gradient keeps the state per sample, not the
        # FE model and matrix exponentials of every sample (tens of GB for a 1 s run)
        @jax.checkpoint
        def step(carry, inputs):
            s, alive = carry
            w, y_k, y_mid = inputs
            out, tr = system(y_k), system(y_mid)
            # a diverging state is held below overflow (a NaN gradient otherwise)
            return held(tr.A @ s + tr.B @ w, s, alive), (out.C @ s + out.D @ w, alive)

        _, (Y, finite) = jax.lax.scan(step, (s0, jnp.ones((), bool)),
                                      (W, positions, mid_positions))
        failed_at, Y = first_bad(finite, Y, W, bound)
        result = RESULTS.where(failed_at < W.shape[0], RESULTS.diverged, RESULTS.successful)
        return Y, failed_at, result


class Continuous(AbstractLoopModel):
    r"""The continuous loop: open loops with the exact delay e^{−iωτ} (or, with ``pade_order``,
    its [n/n] Padé approximant); closed loop and poles with the Padé delay of order
    ``pade_order`` (default :data:`fdjax.DEFAULT_PADE_ORDER` when None).

    Attributes:
        pade_order: None (exact delay in open loops) or n in [1, 16] (static).
    """

    pade_order: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.pade_order is not None:
            pade_order(self.pade_order, "Continuous(pade_order=...)")

    def closed_loop(self, controller, plant, servo) -> LTI:
        n = DEFAULT_PADE_ORDER if self.pade_order is None else self.pade_order
        return continuous_closed_loop(
            controller.law(plant.position_m), plant, servo.k_motor, servo.tau, n
        )

    def open_loop_model(self, controller, plant, servo):
        n = self.pade_order

        def L_fn(p, omega):
            ctrl, pl, sv = p
            return continuous_open_loops(
                ctrl.law(pl.position_m), continuous_channels(pl, omega), omega, sv.k_motor,
                sv.tau, n,
            )

        return L_fn, (controller, plant, servo)

    def frf_open_loops(self, controller, H, omega, screw_ratio, servo, position_m):
        return continuous_open_loops(
            controller.law(position_m), frf_channels(H, omega, screw_ratio), omega,
            servo.k_motor, servo.tau, self.pade_order,
        )


# ------------------------------------------------------------------------------------ diffrax
class ExponentialFOH(diffrax.AbstractSolver):
    r"""Exponential solver for the linear loop ẋ = A x + B w(t) with the input linear over each
    step (a first-order hold), the method of ``scipy.signal.lsim``:

        x_{k+1} = Φ x_k + (Γ₀ − Γ₁) w_k + Γ₁ w_{k+1},
        exp([[A h, B h, 0], [0, 0, I], [0, 0, 0]]) = [[Φ, Γ₀, Γ₁], [0, I, I], [0, 0, I]].

    For a frozen plant (A, B constant) this is exact, whatever the stiffness of the Padé delay
    and the high modes; the exponential is computed once, at ``init``, for the step ``dt``, and
    every step must be dt (``diffrax.StepTo`` on the output grid, as :func:`fdjax.simulate`
    does; another step length is an error).  For the moving table A(Y(t)), B(Y(t)) are taken at
    the step's midpoint (the exponential midpoint rule, second order in the variation of the
    plant over a step — the table moves micrometres per step) and the exponential is computed
    every step.  No error estimate, so no adaptive stepping.  Works with the loop terms of
    :func:`fdjax.simulate` only.
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
        # a diverging state is held below overflow (a NaN gradient otherwise): the run is
        # judged diverged by its error first
        y1, _ = held(Phi @ y0 + G0 @ w0 + G1 @ (w1 - w0), y0, jnp.ones((), bool))
        return y1, None, dict(y0=y0, y1=y1), solver_state, diffrax.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


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


def _foh_matrices(A, B, h):
    n, m = A.shape[0], B.shape[1]
    M = jnp.zeros((n + 2 * m, n + 2 * m), A.dtype)
    M = M.at[:n, :n].set(A * h).at[:n, n : n + m].set(B * h)
    M = M.at[n : n + m, n + m :].set(jnp.eye(m, dtype=A.dtype))
    E = expm(M)
    return E[:n, :n], E[:n, n : n + m], E[:n, n + m :]


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


class _MovingTerm(diffrax.AbstractTerm):
    model: Continuous
    controller: eqx.Module
    servo: eqx.Module
    plant: eqx.Module  # MovingPlant
    inputs: _Inputs
    y0_m: Float[Array, ""]

    def system(self, t):
        w = self.inputs(t)
        cl = self.model.closed_loop(self.controller, self.plant.at(self.y0_m + w[0]), self.servo)
        return cl.A, cl.B, cl.C, cl.D, w

    def vf(self, t, y, args):
        A, B, _, _, w = self.system(t)
        return A @ y + B @ w

    def contr(self, t0, t1, **kwargs):
        return t1 - t0

    def prod(self, vf, control):
        return vf * control


class PadeODE(AbstractLoopModel):
    r"""The continuous loop (delay as its [n/n] Padé approximant) solved by ``diffrax``.

    Attributes:
        dt: output period (s), static; also the step of the default :class:`ExponentialFOH`
            solver and the spacing of the input samples.  Default: the servo's period.
        pade_order: order n of the delay's Padé approximant (static).
        solver: a diffrax solver; default :class:`ExponentialFOH` (exact for the frozen plant,
            exponential midpoint for the moving table).  General solvers (``diffrax.Tsit5()``,
            ``diffrax.Kvaerno5()``) work too, but the loop is stiff (the order-6 Padé delay's
            poles reach ~4e4 1/s, the closed loop's ~1e5), so they need many small steps.
        stepsize_controller: default ``StepTo(ts=output grid)`` for ExponentialFOH, else
            ``PIDController(rtol=1e-8, atol=1e-12)`` clipped to end steps on the output grid
            (where the first-order-hold input has its kinks).
        adjoint: diffrax adjoint; default ``RecursiveCheckpointAdjoint()``: reverse-mode through
            the solver's own steps with diffrax's online (treeverse) checkpointing — exact
            gradients of the discrete solution in little memory.  Backsolve adjoints would
            integrate the damped loop backwards, which is unstable, and :class:`ExponentialFOH`
            does not support them.
        max_steps: diffrax's step budget (static); default: the number of output steps for
            :class:`ExponentialFOH`, 100 000 for other solvers.
    """

    dt: float | None = eqx.field(static=True, default=None)
    pade_order: int = eqx.field(static=True, default=DEFAULT_PADE_ORDER)
    solver: diffrax.AbstractSolver | None = None
    stepsize_controller: diffrax.AbstractStepSizeController | None = None
    adjoint: diffrax.AbstractAdjoint | None = None
    max_steps: int | None = eqx.field(static=True, default=None)
    # measured with the default solver on the reference drive (6 kept modes, dt 1.25e-4 s):
    # 500 B per sample over a run of 1.44 million samples, 465 B per added sample
    bytes_per_sample: ClassVar[int] = 520

    def __check_init__(self):
        if self.dt is not None:
            static_number(self.dt, "PadeODE(dt=...)", lambda v: v > 0, "a positive number")
        pade_order(self.pade_order, "PadeODE(pade_order=...)")
        if self.solver is None or isinstance(self.solver, ExponentialFOH):
            if isinstance(self.adjoint, diffrax.BacksolveAdjoint):
                raise ValueError(_NO_BACKSOLVE)

    @property
    def continuous(self) -> Continuous:
        """The continuous model (same Padé order) whose closed and open loops this model
        integrates."""
        return Continuous(self.pade_order)

    def closed_loop(self, controller, plant, servo) -> LTI:
        return self.continuous.closed_loop(controller, plant, servo)

    def open_loop_model(self, controller, plant, servo):
        return self.continuous.open_loop_model(controller, plant, servo)

    def frf_open_loops(self, controller, H, omega, screw_ratio, servo, position_m):
        return self.continuous.frf_open_loops(controller, H, omega, screw_ratio, servo,
                                              position_m)

    def output_period(self, servo) -> float:
        """The spacing of the run's output samples (s): ``dt``, or the servo's period.  An
        :class:`ExponentialFOH` solver stepping another length on the output grid is refused
        here, before the run (its steps must be exactly its ``dt``)."""
        dt = float(servo.period) if self.dt is None else float(self.dt)
        h = getattr(self.solver, "dt", None)
        if (isinstance(self.solver, ExponentialFOH) and self.stepsize_controller is None
                and abs(float(h) - dt) > 1e-9 * dt):
            raise ValueError(f"`PadeODE(solver=...)` is an ExponentialFOH stepping {h:.6g} s, "
                             f"which must be the output period {dt:.6g} s (PadeODE(dt=...), "
                             "else the servo's period): give ExponentialFOH of that step, or "
                             "leave solver=None")
        return dt

    def _solve(self, term, y0, t, dt: float):
        solver = self.solver if self.solver is not None else ExponentialFOH(dt)
        if self.stepsize_controller is not None:
            controller = self.stepsize_controller
        elif isinstance(solver, ExponentialFOH):
            controller = diffrax.StepTo(ts=t)
        else:
            # Steps end on the input samples: the first-order-hold input has a kink at each
            # one, which an error estimate spanning it would mistake for stiffness.
            controller = diffrax.ClipStepSizeController(
                diffrax.PIDController(rtol=1e-8, atol=1e-12), step_ts=t
            )
        adjoint = self.adjoint if self.adjoint is not None else diffrax.RecursiveCheckpointAdjoint()
        if isinstance(solver, ExponentialFOH) and isinstance(adjoint, diffrax.BacksolveAdjoint):
            raise ValueError(_NO_BACKSOLVE)
        n = t.shape[0]
        max_steps = self.max_steps
        if max_steps is None:
            max_steps = n + 2 if isinstance(solver, ExponentialFOH) else 100_000
        dt0 = None if isinstance(controller, diffrax.StepTo) else dt
        return diffrax.diffeqsolve(
            term, solver, t0=0.0, t1=t[-1], dt0=dt0, y0=y0, saveat=diffrax.SaveAt(ts=t),
            stepsize_controller=controller, adjoint=adjoint, max_steps=max_steps, throw=False,
        )

    def _result(self, sol, X, Y, W, bound):
        n = W.shape[0]
        first, Y = first_bad(jnp.all(jnp.isfinite(X), axis=1), Y, W, bound)
        solver_ok = sol.result == diffrax.RESULTS.successful
        failed_at = jnp.where(solver_ok, first, jnp.minimum(first, n - 1))
        result = RESULTS.where(
            solver_ok,
            RESULTS.where(first < n, RESULTS.diverged, RESULTS.successful),
            RESULTS.solver_failed,
        )
        return Y, failed_at, result

    def run(self, controller, plant, W, servo, bound):
        r"""One run of the continuous closed loop around the twin ``plant`` (the work of
        :func:`fdjax.simulate`): ẋ = A x + B w(t), y = C x + D w from x(0) = 0, with w the
        first-order hold of the rows of ``W`` (r, ṙ, r̈, F3), by ``diffrax.diffeqsolve``.

        Returns:
            (Y, failed_at, result, growth) as :meth:`fdjax.SampledData.run`, with
            ``RESULTS.solver_failed`` when the solver stops.
        """
        dt = self.output_period(servo)
        cl = self.closed_loop(controller, plant, servo)
        t = jnp.arange(W.shape[0], dtype=jnp.float64) * dt
        term = _LTITerm(cl.A, cl.B, _Inputs(W, jnp.asarray(dt, jnp.float64)))
        sol = self._solve(term, jnp.zeros(cl.A.shape[0]), t, dt)
        X = sol.ys
        Y, failed_at, result = self._result(sol, X, X @ cl.C.T + W @ cl.D.T, W, bound)
        growth = self._growth(cl, dt)
        result = RESULTS.where(growing(growth, servo.period), RESULTS.unstable, result)
        return Y, failed_at, result, growth

    @staticmethod
    def _growth(cl, dt):
        return growth_rate(expm(cl.A * dt), dt)

    def frozen_growth(self, controller, plant, servo):
        """The least stable pole's growth rate max Re s (1/s) of the continuous loop around
        ``plant`` (from its transition matrix over one output period)."""
        return self._growth(self.closed_loop(controller, plant, servo),
                            self.output_period(servo))

    def run_moving(self, controller, moving, W, positions, mid_positions, servo, bound):
        r"""One run with the table moving (:func:`fdjax.simulate` with ``moving=True``): the
        continuous loop rebuilt around the projected plant wherever the solver evaluates it,
        ẋ = A(Y(t)) x + B(Y(t)) w(t), Y(t) = Y₀ + r(t) (:class:`fdjax.ExponentialFOH`: at each
        step's midpoint).

        Returns:
            (Y, failed_at, result) as :meth:`fdjax.SampledData.run`, without the growth rate
            (a time-varying loop has no poles).
        """
        del mid_positions  # the exponential midpoint rule takes the step's midpoint itself
        dt = self.output_period(servo)
        t = jnp.arange(W.shape[0], dtype=jnp.float64) * dt
        term = _MovingTerm(
            self.continuous, controller, servo, moving, _Inputs(W, jnp.asarray(dt, jnp.float64)),
            positions[0] - W[0, 0],
        )
        A0 = term.system(0.0)[0]
        sol = self._solve(term, jnp.zeros(A0.shape[0]), t, dt)
        X = sol.ys
        C, D = jax.vmap(lambda tk: term.system(tk)[2:4])(t)
        Y = jnp.einsum("kon,kn->ko", C, X) + jnp.einsum("koi,ki->ko", D, W)
        return self._result(sol, X, Y, W, bound)


@eqx.filter_jit
def _parts(model: SampledData, controller, plant, servo) -> SampledParts:
    return model.parts(controller, plant, servo)
