r"""The feed-drive controllers of paper Fig. 13 and their loop analysis (paper Sec. 4, Fig. 14).

**Plant** (paper Fig. 7).  The drive's 3×2 receptance H (outputs θ1, x2, x3; inputs T1, F3) at
one table position; the controller drives T1 only, F3 is the disturbance.  Two channels close
loops: the motor speed ``g_v(ω) = θ̇1/T1 = iω h_θ1,T1`` (collocated) and the linear scale
``g_x(ω) = x2/T1 = h_x2,T1`` (non-collocated).  The motor and its driver are the gain
``k_m = k_i·k_T`` (N·m/A) from the current command u (A) to torque, and the control delay τ
lumps computation and measurement (one or two servo periods).  Here τ sits **in series with the
plant input**, T1(t) = k_m·u(t − τ): every command (feedback and feed-forward) reaches the motor
τ late.  For a loop gain the place of a delay inside the loop does not matter; for the
feed-forward paths it means they are delayed as well.

**Double loop** (paper Fig. 13, :class:`DoubleLoop`).  With the reference position r (m):

    v_cmd = k_p (r − x2) + k_ffv ṙ                      outer P loop on the scale (m/s)
    v_m   = i_sc θ̇1                                    motor speed in linear units (m/s)
    u     = G_MCM(s) C_v(s) (v_cmd − v_m) + k_ffa r̈    current command (A)
    C_v(s) = k_v (1 + k_i/s)                            inner PI speed controller (A·s/m)
    T1    = k_m e^{−sτ} u

**Open loops.**  Broken at the motor-speed feedback with the outer loop open, and at the scale
with the inner loop closed:

    L_v(ω) = C_v(iω) G_MCM(iω) k_m e^{−iωτ} · i_sc iω h_θ1,T1(ω)                        (inner)

    L_p(ω) = k_p · x2/v_cmd = k_p · h_x2,T1(ω) C_v G_MCM k_m e^{−iωτ} / (1 + L_v(ω))   (outer)

(inner loop closed: T1 = G (v_cmd − i_sc g_v T1) with G = C_v G_MCM k_m e^{−iωτ}, so
T1/v_cmd = G/(1 + L_v)).  Both use the exact coupled FRF (paper Eq. 2) or any measured H; the
delay is exactly e^{−iωτ}, or its [n/n] Padé approximant where asked (``pade_order``).

**PID baseline** (:class:`PIDLoop`): one loop on the scale, u = C_pid(s)(r − x2) + k_ffv ṙ +
k_ffa r̈ with C_pid(s) = k_p + k_i/s + k_d s/(1 + s/ω_d), so L(ω) = C_pid k_m e^{−iωτ} h_x2,T1.

**Margins** (:func:`loop_margins`, :func:`stability_margins`), with python-control's
conventions (``control.stability_margins``): of all phase crossovers (L on the negative real
axis) the gain margin 1/|L| closest to 1 in the log sense; of all gain crossovers (|L| = 1)
the phase margin ``PM = (arg L mod 360°) − 180°`` smallest in magnitude; the modulus margin
``min_ω |1 + L(iω)|`` (the inverse peak sensitivity).  Crossings are found on the frequency grid
(log-frequency interpolation of log L within a grid interval) and, when the plant is the
state-space twin, refined by safeguarded Newton steps on the twin's own L(iω) to round-off; the
result is differentiable through the refined crossing (implicit function theorem: one last
Newton step carries the gradient).  The twin's speed output has no feed-through
(``StateSpace.C_velocity``), so its θ̇1 is not exactly iω times its θ1 (which keeps the
residual D): an FRF array of the twin must be built from its speed output to agree.

**Closed loop** (:func:`closed_loop`).  The state-space twin (:func:`fdjax.state_space`) with
the controller's states (PI integrator, MCM realisation, Padé delay) and the feed-forward as
inputs (r, ṙ, r̈, F3); its eigenvalues are the closed-loop poles, and :func:`check_stability`
reports stable/unstable with the position.  The delay there is the [n/n] Padé approximant
(default order :data:`DEFAULT_PADE_ORDER`), the only part that is not exact.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Complex, Float

from . import _checks
from ._drive import BallScrewDrive
from ._filters import MCM, AbstractFilter, FilterStateSpace
from ._statespace import StateSpace, count_modes, state_space

__all__ = [
    "AbstractLoop",
    "DoubleLoop",
    "PIDLoop",
    "OpenLoop",
    "Margins",
    "LoopMargins",
    "ClosedLoop",
    "Stability",
    "open_loop",
    "loop_margins",
    "stability_margins",
    "closed_loop",
    "check_stability",
    "pade",
    "DEFAULT_PADE_ORDER",
    "CLOSED_LOOP_INPUTS",
    "CLOSED_LOOP_OUTPUTS",
]

DEFAULT_PADE_ORDER = 6
"""Default order n of the [n/n] Padé delay in the closed-loop poles.  The approximant is
all-pass; its phase error grows as (ωτ)^{2n+1}: at n = 6 it is 1.3e-9 rad at ωτ = 2 (1.3 kHz at
τ = 250 µs), 2.3e-7 rad at ωτ = 3 and 1.9e-3 rad (0.11°) at ωτ = 6.3, i.e. at 4 kHz, the top of
the twin's default band."""

CLOSED_LOOP_INPUTS = ("r", "r_dot", "r_ddot", "F3")
"""Inputs of a :class:`ClosedLoop`: reference position (m), velocity (m/s), acceleration (m/s²)
and the disturbance force at the tool point (N)."""

CLOSED_LOOP_OUTPUTS = ("theta1", "x2", "x3", "T1")
"""Outputs of a :class:`ClosedLoop`: motor angle (rad), scale and tool-point positions (m),
motor torque (N·m)."""

_TWO_PI = 2.0 * math.pi
_N_CANDIDATES = 3  # crossings refined per criterion (the best ones on the grid)
_NEWTON_STEPS = 3  # safeguarded Newton from the grid estimate (then one step with gradients)

# Defaults of the reference drive (fdjax.reference_drive()); see DoubleLoop / PIDLoop.
_I_SC_REF = 0.005 / _TWO_PI  # m/rad: 5 mm lead (50×5 screw)
_J_EQ_REF = 1.2444e-2  # kg·m²: rotor + hubs + screw torsion + table reflected (m i_sc²)
_TAU_DEFAULT = 250e-6  # s: two servo periods at 8 kHz (measurement + computation)
_K_MOTOR_DEFAULT = 1.2  # N·m/A: k_i·k_T of a ~10 N·m servo motor and its amplifier


def _c(x) -> Array:
    return jnp.asarray(x).astype(jnp.complex128)


def _scalar_param(value, where: str) -> Array:
    """A real scalar parameter as float64 (shape and dtype are static facts)."""
    arr = jnp.asarray(value)
    if arr.ndim != 0:
        raise ValueError(f"`{where}` must be a scalar, got shape {arr.shape}")
    if jnp.issubdtype(arr.dtype, jnp.complexfloating):
        raise ValueError(f"`{where}` must be real, got dtype {arr.dtype}")
    return arr.astype(jnp.float64)


def _positive(value, where: str) -> Array:
    return _checks.positive(_scalar_param(value, where), where)


def _finite(value, where: str) -> Array:
    return _checks.finite(_scalar_param(value, where), where)


# ------------------------------------------------------------------------------------ delay
def _pade_coefficients(order: int) -> np.ndarray:
    """c_k = (2n − k)! n! / ((2n)! k! (n − k)!), k = 0 … n: Q_n(x) = Σ c_k x^k."""
    n = order
    f = math.factorial
    return np.array([f(2 * n - k) * f(n) / (f(2 * n) * f(k) * f(n - k)) for k in range(n + 1)])


def _delay_frf(tau, omega, pade_order: int | None):
    """e^{−iωτ}, or its [n/n] Padé approximant Q_n(−iωτ)/Q_n(iωτ)."""
    x = _c(omega * tau)
    if pade_order is None:
        return jnp.exp(x * -1j)
    c = _pade_coefficients(pade_order)
    z = x * 1j
    num = jnp.zeros_like(z)
    den = jnp.zeros_like(z)
    for ck in c[::-1]:  # Horner
        num = num * -z + float(ck)
        den = den * z + float(ck)
    return num / den


def pade(tau: ArrayLike, order: int) -> FilterStateSpace:
    r"""State-space realisation of the [n/n] Padé approximant of the delay e^{−sτ}.

        e^{−x} ≈ Q_n(−x)/Q_n(x),   Q_n(x) = Σ_{k=0}^{n} (2n−k)! n! / ((2n)! k! (n−k)!) x^k,
        x = sτ,

    the same approximant as ``control.pade(tau, n)``.  Realised in controllable canonical form
    in the scaled variable y = sτ/ρ with ρ = (c_0/c_n)^{1/n} (the geometric mean of the pole
    magnitudes of Q_n in x), which keeps the companion coefficients O(1) and the realisation
    well conditioned up to order ~12; then A = (ρ/τ)A_y, B = (ρ/τ)B_y, D = (−1)^n.

    Args:
        tau: the delay τ (s), positive.
        order: n ≥ 1 (static).
    """
    n = _pade_order(order, "pade(order=...)")
    tau = _positive(tau, "pade(tau=...)")
    return _pade_ss(tau, n)


def _pade_order(order, where: str) -> int:
    if isinstance(order, bool) or not isinstance(order, int | np.integer):
        raise ValueError(f"`{where}` must be an int, got {order!r}")
    if not 1 <= order <= 16:
        raise ValueError(f"`{where}` must be in [1, 16], got {order}")
    return int(order)


def _pade_ss(tau, n: int) -> FilterStateSpace:
    c = _pade_coefficients(n)
    rho = (c[0] / c[n]) ** (1.0 / n)
    a = c * rho ** np.arange(n + 1) / (c[n] * rho**n)  # monic in y: a_n = 1, a_0 = 1
    sign = (-1.0) ** np.arange(n + 1)
    r = a * (sign - (-1.0) ** n)  # numerator minus D·denominator, coefficients of y^k
    A_y = np.zeros((n, n))
    A_y[0, :] = -a[n - 1 :: -1][:n]  # −a_{n−1}, …, −a_0
    A_y[1:, :-1] = np.eye(n - 1)
    scale = rho / tau
    return FilterStateSpace(
        A=scale * jnp.asarray(A_y),
        B=scale * jnp.asarray(np.eye(n)[:, :1]),
        C=jnp.asarray(r[n - 1 :: -1][:n][None, :]),
        D=jnp.full((1, 1), (-1.0) ** n),
    )


# ------------------------------------------------------------------------------------ controllers
class AbstractLoop(eqx.Module):
    r"""A feed-drive position controller acting on the motor torque through a delay and a gain.

    Concrete loops say how the open loops are formed from the plant's two channels
    ``g_v = θ̇1/T1`` and ``g_x = x2/T1`` and how the controller is realised in state space.
    Every loop has the control delay ``tau`` (s) in series with the plant input and the motor
    gain ``k_motor`` = k_i·k_T (N·m/A) from current command to torque (paper Fig. 7).
    """

    tau: eqx.AbstractVar[Float[Array, ""]]
    k_motor: eqx.AbstractVar[Float[Array, ""]]

    @abc.abstractmethod
    def open_loops(
        self,
        g_v: Complex[Array, "*freq"],
        g_x: Complex[Array, "*freq"],
        omega: Float[Array, "*freq"],
        *,
        pade_order: int | None = None,
    ) -> tuple[Complex[Array, "*freq"] | None, Complex[Array, "*freq"]]:
        """(inner, outer) open loops from the plant channels at angular frequencies ω (rad/s);
        ``inner`` is None for a single-loop controller.  Unchecked (usable inside jit/grad)."""

    @abc.abstractmethod
    def _closed_loop(self, plant: StateSpace, delay: FilterStateSpace) -> tuple[Array, ...]:
        """(A, B, C, D) of the loop closed around ``plant``."""


class DoubleLoop(AbstractLoop):
    r"""The nested double loop of paper Fig. 13: P position loop on the linear scale x2 outside,
    PI speed loop on the motor inside, MCM on the speed controller's output, feed-forward.

        v_cmd = k_p (r − x2) + k_ffv ṙ,      v_m = i_sc θ̇1,
        u = G_MCM(s) k_v (1 + k_i/s) (v_cmd − v_m) + k_ffa r̈,      T1 = k_motor e^{−sτ} u.

    Units: the speed controller's output u is a current command (A), so k_v is in A·s/m and
    k_ffa in A·s²/m; k_p and k_i in 1/s (k_i is the PI corner frequency, rad/s); k_ffv is
    dimensionless (1 = full velocity feed-forward).  The ideal acceleration feed-forward of a
    rigid drive is k_ffa = J_eq/(k_motor i_sc), J_eq the inertia reflected to the motor.

    Defaults: hand-set for :func:`fdjax.reference_drive` with τ = 250 µs (two servo periods at
    8 kHz) and an identity MCM, stable at every table position 0.1–0.7 m (also at τ = 125 µs).
    Speed loop: crossover 34.5 Hz, gain margin 13.5, phase margin 75°, modulus margin 0.90
    (the coupling mode at 131 Hz limits k_v).  Position loop: crossover 7.0 Hz, phase margin
    84°, gain margin 7.3, modulus margin 0.83, nearly the same over the travel (the calibrated
    drive's low modes, 49–131 Hz, hardly move with the table).

    Positivity by parameterisation: the gains k_p, k_v, k_i are stored as their logarithms
    (``log_kp``, ``log_kv``, ``log_ki``), so any gradient step keeps them positive; the physical
    values are properties.  The hardware constants ``tau``, ``k_motor`` and ``i_sc`` are stored
    as they are (validated positive) and the feed-forward gains are free reals.  As for the
    filters, ``eqx.filter_grad`` gives gradients on the stored leaves (``g.log_kp = k_p ∂/∂k_p``);
    ``jax.grad(lambda p: f(DoubleLoop(**p)))(loop.params())`` gives them in physical units.

    Attributes (arguments of the constructor):
        kp: outer position gain (1/s).
        kv: speed-loop proportional gain (A·s/m).
        ki: speed-loop integral corner (rad/s).
        k_ffv: velocity feed-forward (–).
        k_ffa: acceleration feed-forward (A·s²/m).
        mcm: the modal characteristic modifier (:class:`fdjax.MCM`, or any filter), acting on
            the speed controller's output; ``MCM()`` is the identity.
        tau: control delay τ (s), in series with the plant input.
        k_motor: k_i·k_T (N·m/A).
        i_sc: ball-screw ratio lead/2π (m/rad) scaling the encoder speed to linear units; set
            it to ``drive.screw.ratio``.
    """

    log_kp: Float[Array, ""]
    log_kv: Float[Array, ""]
    log_ki: Float[Array, ""]
    k_ffv: Float[Array, ""]
    k_ffa: Float[Array, ""]
    mcm: AbstractFilter
    tau: Float[Array, ""]
    k_motor: Float[Array, ""]
    i_sc: Float[Array, ""]

    def __init__(
        self,
        kp: ArrayLike = 40.0,
        kv: ArrayLike = 3.0e3,
        ki: ArrayLike = 60.0,
        *,
        k_ffv: ArrayLike = 1.0,
        k_ffa: ArrayLike = _J_EQ_REF / (_K_MOTOR_DEFAULT * _I_SC_REF),
        mcm: AbstractFilter | None = None,
        tau: ArrayLike = _TAU_DEFAULT,
        k_motor: ArrayLike = _K_MOTOR_DEFAULT,
        i_sc: ArrayLike = _I_SC_REF,
    ):
        if mcm is None:
            mcm = MCM()
        if not isinstance(mcm, AbstractFilter):
            raise TypeError(
                f"`DoubleLoop(mcm=...)` must be an fdjax.MCM (or another fdjax filter), "
                f"got {type(mcm).__name__}"
            )
        self.log_kp = jnp.log(_positive(kp, "DoubleLoop(kp=...)"))
        self.log_kv = jnp.log(_positive(kv, "DoubleLoop(kv=...)"))
        self.log_ki = jnp.log(_positive(ki, "DoubleLoop(ki=...)"))
        self.k_ffv = _finite(k_ffv, "DoubleLoop(k_ffv=...)")
        self.k_ffa = _finite(k_ffa, "DoubleLoop(k_ffa=...)")
        self.mcm = mcm
        self.tau = _positive(tau, "DoubleLoop(tau=...)")
        self.k_motor = _positive(k_motor, "DoubleLoop(k_motor=...)")
        self.i_sc = _positive(i_sc, "DoubleLoop(i_sc=...)")

    @property
    def kp(self) -> Float[Array, ""]:
        """Outer position gain k_p (1/s)."""
        return jnp.exp(self.log_kp)

    @property
    def kv(self) -> Float[Array, ""]:
        """Speed-loop gain k_v (A·s/m)."""
        return jnp.exp(self.log_kv)

    @property
    def ki(self) -> Float[Array, ""]:
        """Speed-loop integral corner k_i (rad/s)."""
        return jnp.exp(self.log_ki)

    def params(self) -> dict:
        """Physical parameters; ``DoubleLoop(**loop.params())`` rebuilds ``loop``."""
        return dict(
            kp=self.kp, kv=self.kv, ki=self.ki, k_ffv=self.k_ffv, k_ffa=self.k_ffa,
            mcm=self.mcm, tau=self.tau, k_motor=self.k_motor, i_sc=self.i_sc,
        )

    def speed_controller(self, s: ArrayLike) -> Complex[Array, "*shape"]:
        """C_v(s) = k_v (1 + k_i/s) (A·s/m) at complex ``s``."""
        s = _c(s)
        return (s + _c(self.ki)) / s * _c(self.kv)

    def open_loops(self, g_v, g_x, omega, *, pade_order=None):
        r"""L_v = C_v G_MCM k_m e^{−iωτ} i_sc g_v,  L_p = k_p g_x C_v G_MCM k_m e^{−iωτ}/(1 + L_v).

        ``g_v = θ̇1/T1`` (rad/(N·m·s)), ``g_x = x2/T1`` (m/(N·m)) at ω (rad/s).  Unchecked.
        """
        s = _c(omega) * 1j
        G = (
            self.speed_controller(s) * self.mcm.transfer(s) * _c(self.k_motor)
            * _delay_frf(self.tau, omega, pade_order)
        )
        L_v = G * _c(self.i_sc) * g_v
        L_p = _c(self.kp) * g_x * G / (1.0 + L_v)
        return L_v, L_p

    def _closed_loop(self, plant: StateSpace, delay: FilterStateSpace):
        f = self.mcm.state_space()
        nf, nd = f.A.shape[0], delay.A.shape[0]
        lf = _LinearForms(plant, {"z": 1, "f": nf, "d": nd})
        kp, kv, ki = self.kp, self.kv, self.ki
        # T1 = Cd x_d + Dd k_m u is solved for last: every signal is written as
        # (row over [states, inputs]) + (coefficient) · T1, the algebraic loop through the
        # plant's feed-through D (x2 → … → T1) is closed exactly.
        x2 = lf.plant_out(1)
        v_m = lf.row(plant=self.i_sc * plant.C_velocity[0])
        e_v = (lf.inp("r") - x2) * kp + lf.inp("r_dot") * self.k_ffv - v_m
        u_pi = (e_v + lf.row(z=jnp.ones(1)) * ki) * kv
        u = lf.row(f=f.C[0]) + u_pi * f.D[0, 0] + lf.inp("r_ddot") * self.k_ffa
        T1 = lf.solve_torque(delay, u, self.k_motor)
        return lf.assemble(
            T1,
            {
                "z": e_v,
                "f": (f.A, f.B[:, 0], u_pi),
                "d": (delay.A, delay.B[:, 0], u * self.k_motor),
            },
        )


class PIDLoop(AbstractLoop):
    r"""The paper's baseline: one PID position loop on the linear scale x2 (Figs. 16, 18).

        u = C_pid(s)(r − x2) + k_ffv ṙ + k_ffa r̈,   C_pid(s) = k_p + k_i/s + k_d s/(1 + s/ω_d),
        T1 = k_motor e^{−sτ} u,      L(ω) = C_pid(iω) k_motor e^{−iωτ} h_x2,T1(ω).

    Units (u is a current command, A): k_p in A/m, k_i in A/(m·s), k_d in A·s/m, the derivative
    filter corner ω_d in rad/s, k_ffv in A·s/m, k_ffa in A·s²/m.  Gains stored as logarithms
    (``log_kp``, ``log_ki``, ``log_kd``, ``log_wd``; the physical values are properties), the
    hardware constants ``tau`` and ``k_motor`` as validated positive values.

    Defaults: hand-set for :func:`fdjax.reference_drive`, τ = 250 µs: stable at every table
    position 0.1–0.7 m and soft, as the paper's baseline: crossover 1.6 Hz, phase margin 53°,
    gain margin 9.0 at 0.1 m falling to 8.6 at 0.7 m.
    """

    log_kp: Float[Array, ""]
    log_ki: Float[Array, ""]
    log_kd: Float[Array, ""]
    log_wd: Float[Array, ""]
    k_ffv: Float[Array, ""]
    k_ffa: Float[Array, ""]
    tau: Float[Array, ""]
    k_motor: Float[Array, ""]

    def __init__(
        self,
        kp: ArrayLike = 1.5e3,
        ki: ArrayLike = 5.0e3,
        kd: ArrayLike = 100.0,
        wd: ArrayLike = _TWO_PI * 150.0,
        *,
        k_ffv: ArrayLike = 0.0,
        k_ffa: ArrayLike = 0.0,
        tau: ArrayLike = _TAU_DEFAULT,
        k_motor: ArrayLike = _K_MOTOR_DEFAULT,
    ):
        self.log_kp = jnp.log(_positive(kp, "PIDLoop(kp=...)"))
        self.log_ki = jnp.log(_positive(ki, "PIDLoop(ki=...)"))
        self.log_kd = jnp.log(_positive(kd, "PIDLoop(kd=...)"))
        self.log_wd = jnp.log(_positive(wd, "PIDLoop(wd=...)"))
        self.k_ffv = _finite(k_ffv, "PIDLoop(k_ffv=...)")
        self.k_ffa = _finite(k_ffa, "PIDLoop(k_ffa=...)")
        self.tau = _positive(tau, "PIDLoop(tau=...)")
        self.k_motor = _positive(k_motor, "PIDLoop(k_motor=...)")

    @property
    def kp(self) -> Float[Array, ""]:
        """Proportional gain (A/m)."""
        return jnp.exp(self.log_kp)

    @property
    def ki(self) -> Float[Array, ""]:
        """Integral gain (A/(m·s))."""
        return jnp.exp(self.log_ki)

    @property
    def kd(self) -> Float[Array, ""]:
        """Derivative gain (A·s/m)."""
        return jnp.exp(self.log_kd)

    @property
    def wd(self) -> Float[Array, ""]:
        """Derivative filter corner ω_d (rad/s)."""
        return jnp.exp(self.log_wd)

    def params(self) -> dict:
        """Physical parameters; ``PIDLoop(**loop.params())`` rebuilds ``loop``."""
        return dict(
            kp=self.kp, ki=self.ki, kd=self.kd, wd=self.wd, k_ffv=self.k_ffv, k_ffa=self.k_ffa,
            tau=self.tau, k_motor=self.k_motor,
        )

    def controller(self, s: ArrayLike) -> Complex[Array, "*shape"]:
        """C_pid(s) = k_p + k_i/s + k_d s/(1 + s/ω_d) (A/m) at complex ``s``."""
        s = _c(s)
        return _c(self.kp) + _c(self.ki) / s + _c(self.kd) * s / (1.0 + s / _c(self.wd))

    def open_loops(self, g_v, g_x, omega, *, pade_order=None):
        """(None, C_pid k_m e^{−iωτ} g_x): a single loop.  Unchecked."""
        s = _c(omega) * 1j
        delay = _delay_frf(self.tau, omega, pade_order)
        return None, self.controller(s) * _c(self.k_motor) * delay * g_x

    def _closed_loop(self, plant: StateSpace, delay: FilterStateSpace):
        lf = _LinearForms(plant, {"z": 1, "xd": 1, "d": delay.A.shape[0]})
        wd, kd = self.wd, self.kd
        # k_d s/(1 + s/ω_d) = k_d ω_d (1 − ω_d/(s + ω_d)): filter state ẋ_d = −ω_d x_d + e.
        e = lf.inp("r") - lf.plant_out(1)
        x_der = lf.row(xd=jnp.ones(1))
        u = (
            e * (self.kp + kd * wd) + lf.row(z=jnp.ones(1)) * self.ki - x_der * (kd * wd * wd)
            + lf.inp("r_dot") * self.k_ffv + lf.inp("r_ddot") * self.k_ffa
        )
        T1 = lf.solve_torque(delay, u, self.k_motor)
        return lf.assemble(
            T1,
            {
                "z": e,
                "xd": (-wd.reshape(1, 1), jnp.ones(1), e),
                "d": (delay.A, delay.B[:, 0], u * self.k_motor),
            },
        )


class _Form(eqx.Module):
    """A signal ``row · [states, inputs] + t · T1`` (T1 the motor torque, solved last)."""

    row: Array
    t: Array

    def __add__(self, other):
        return _Form(self.row + other.row, self.t + other.t)

    def __sub__(self, other):
        return _Form(self.row - other.row, self.t - other.t)

    def __mul__(self, k):
        return _Form(self.row * k, self.t * k)


class _Layout:
    """Named state blocks laid out in one vector ``[blocks…, inputs]``, and rows over it (a
    linear signal of the loop is a row: its coefficients on every state and input)."""

    def __init__(self, sizes: dict[str, int], inputs: tuple[str, ...] = CLOSED_LOOP_INPUTS):
        self.sizes, self.inputs, self.offsets = dict(sizes), inputs, {}
        k = 0
        for name, size in self.sizes.items():
            self.offsets[name] = k
            k += size
        self.n = k
        self.width = k + len(inputs)

    def vector(self, **parts) -> Array:
        """The row with ``values`` at block ``name`` for each ``name=values`` ("inputs": the
        input slots)."""
        r = jnp.zeros(self.width, jnp.float64)
        for name, values in parts.items():
            values = jnp.atleast_1d(values)
            o = self.offsets[name] if name != "inputs" else self.n
            r = r.at[o : o + values.shape[0]].add(values)
        return r

    def unit_input(self, name: str) -> Array:
        """The row of input ``name`` alone."""
        return jnp.zeros(self.width, jnp.float64).at[self.n + self.inputs.index(name)].set(1.0)


class _LinearForms(_Layout):
    """Bookkeeping of the closed-loop states ``[plant, *controller blocks]`` and inputs."""

    def __init__(self, plant: StateSpace, blocks: dict[str, int]):
        super().__init__({"plant": plant.A.shape[0], **blocks})
        self.plant = plant

    def row(self, **parts) -> _Form:
        return _Form(self.vector(**parts), jnp.zeros((), jnp.float64))

    def inp(self, name: str) -> _Form:
        return _Form(self.unit_input(name), jnp.zeros((), jnp.float64))

    def plant_out(self, i: int) -> _Form:
        """Plant output i (θ1, x2, x3): C_i x + D_i,F3 F3 + D_i,T1 T1."""
        p = self.plant
        f = self.row(plant=p.C[i], inputs=jnp.zeros(4).at[3].set(p.D[i, 1]))
        return _Form(f.row, p.D[i, 0])

    def solve_torque(self, delay: FilterStateSpace, u: _Form, k_motor) -> Array:
        """T1 = C_d x_d + D_d k_m u(…, T1), solved for T1: a row over [states, inputs]."""
        rhs = self.row(d=delay.C[0]) + u * (delay.D[0, 0] * k_motor)
        return rhs.row / (1.0 - rhs.t)

    def assemble(self, T1: Array, blocks: dict) -> tuple[Array, Array, Array, Array]:
        p = self.plant

        def value(form: _Form) -> Array:
            return form.row + form.t * T1

        rows = [jnp.concatenate([p.A, jnp.zeros((p.A.shape[0], self.width - p.A.shape[0]))], 1)]
        rows[0] = rows[0] + p.B[:, :1] * T1[None, :]
        rows[0] = rows[0].at[:, self.n + 3].add(p.B[:, 1])
        for name in self.sizes:
            if name == "plant":
                continue
            spec = blocks[name]
            if isinstance(spec, _Form):  # an integrator: ż = signal
                rows.append(value(spec)[None, :])
                continue
            Ab, Bb, signal = spec
            o, m = self.offsets[name], self.sizes[name]
            own = jnp.zeros((m, self.width), jnp.float64).at[:, o : o + m].set(Ab)
            rows.append(own + Bb[:, None] * value(signal)[None, :])
        M = jnp.concatenate(rows, 0)
        outs = [value(self.plant_out(i)) for i in range(3)] + [T1]
        Y = jnp.stack(outs, 0)
        n = self.n
        return M[:, :n], M[:, n:], Y[:, :n], Y[:, n:]


# ------------------------------------------------------------------------------------ plants
def _plant_channels(plant: StateSpace, omega):
    """(g_v, g_x) = (θ̇1/T1, x2/T1) of the twin at ω (rad/s, any shape).  Unchecked.

    The twin's speed output has no feed-through (``C_velocity``); its position output keeps D.
    """

    def one(w):
        M = (_c(w) * 1j) * jnp.eye(plant.A.shape[0], dtype=jnp.complex128) - _c(plant.A)
        x = jnp.linalg.solve(M, _c(plant.B[:, 0]))
        return _c(plant.C_velocity[0]) @ x, _c(plant.C[1]) @ x + _c(plant.D[1, 0])

    w = jnp.asarray(omega)
    gv, gx = jax.vmap(one)(w.reshape(-1))
    return gv.reshape(w.shape), gx.reshape(w.shape)


def _frf_channels(H, omega):
    return (_c(omega) * 1j) * H[..., 0, 0], H[..., 1, 0]


# ------------------------------------------------------------------------------------ results
class OpenLoop(eqx.Module):
    """Open-loop frequency responses of a controller around a plant.

    Attributes:
        freq_hz: the frequency grid (Hz), (n_freq,).
        inner: L_v, the inner (speed) loop broken at the speed feedback, outer loop open;
            None for a single-loop controller.  Shape (*batch, n_freq).
        outer: L_p, the position loop broken at the scale, inner loop closed (or the PID loop).
    """

    freq_hz: Float[Array, " freq"]
    inner: Complex[Array, "*batch freq"] | None
    outer: Complex[Array, "*batch freq"]


class Margins(eqx.Module):
    """Stability margins of one open loop L (python-control's conventions; see module docs).

    Only crossings inside the frequency grid are found: make the grid span them.

    Attributes (shape ``*batch``):
        gain_margin: 1/|L| at the phase crossover whose margin is closest to 1 (log sense);
            inf when L never crosses the negative real axis on the grid.
        phase_margin_deg: (arg L mod 360°) − 180° at the gain crossover with the smallest
            |margin| (°); inf without gain crossover.
        modulus_margin: min |1 + L| (the inverse of the peak sensitivity).
        phase_crossover_hz, gain_crossover_hz, modulus_hz: where (Hz); NaN where none.
    """

    gain_margin: Float[Array, "*batch"]
    phase_margin_deg: Float[Array, "*batch"]
    modulus_margin: Float[Array, "*batch"]
    phase_crossover_hz: Float[Array, "*batch"]
    gain_crossover_hz: Float[Array, "*batch"]
    modulus_hz: Float[Array, "*batch"]

    @property
    def gain_margin_db(self) -> Float[Array, "*batch"]:
        """20 log10(gain_margin) (dB)."""
        return 20.0 * jnp.log10(self.gain_margin)


class LoopMargins(eqx.Module):
    """Margins of the inner (speed; None for a single loop) and outer (position) open loops."""

    inner: Margins | None
    outer: Margins


class ClosedLoop(eqx.Module):
    r"""The closed loop in state space: ẋ = A x + B w, y = C x + D w.

    ``w = (r, ṙ, r̈, F3)`` (:data:`CLOSED_LOOP_INPUTS`), ``y = (θ1, x2, x3, T1)``
    (:data:`CLOSED_LOOP_OUTPUTS`); the state is the twin's, then the controller's (PI
    integrator, MCM, Padé delay; for the PID the integrator, derivative filter and delay).
    """

    A: Float[Array, "n n"]
    B: Float[Array, "n 4"]
    C: Float[Array, "4 n"]
    D: Float[Array, "4 4"]
    position_m: Float[Array, ""]
    pade_order: int = eqx.field(static=True)

    def poles(self) -> Complex[Array, " n"]:
        """Eigenvalues of A (1/s), sorted by real part, largest first."""
        return _sorted_poles(self.A)

    def frf(self, freq_hz: Float[ArrayLike, " freq"]) -> Complex[Array, "freq 4 4"]:
        """Frequency response ``C (iωI − A)⁻¹ B + D`` (outputs × inputs), shape (n_freq, 4, 4)."""
        f = _checks.frequency_grid(freq_hz, "ClosedLoop.frf(freq_hz=...)")
        return _ss_frf(self.A, self.B, self.C, self.D, f)


class Stability(eqx.Module):
    """Result of :func:`check_stability`.

    Attributes:
        stable: all closed-loop poles in the open left half-plane.
        spectral_abscissa: max Re(pole) (1/s); negative when stable.
        min_damping: min over the poles of −Re λ/|λ| (damping ratio of the least damped pole).
        position_m: the table position (m).
        poles: closed-loop poles (1/s), sorted by real part, largest first.
        pade_order: order of the Padé delay used (static).
    """

    stable: Bool[Array, "*batch"]
    spectral_abscissa: Float[Array, "*batch"]
    min_damping: Float[Array, "*batch"]
    position_m: Float[Array, "*batch"]
    poles: Complex[Array, "*batch n"]
    pade_order: int = eqx.field(static=True)

    @property
    def message(self) -> str:
        """One line per position, e.g. "closed loop unstable at position 0.7 m (least stable
        pole: Re λ = 16.5 1/s at 93.7 Hz; …)"."""
        stable = np.atleast_1d(np.asarray(self.stable))
        pos = np.atleast_1d(np.asarray(self.position_m))
        poles = np.asarray(self.poles).reshape(stable.shape[0], -1)
        lines = []
        for ok, p, lam in zip(stable, pos, poles):
            worst = lam[0]
            what = "stable" if ok else "unstable"
            lines.append(
                f"closed loop {what} at position {p:.4g} m (least stable pole: "
                f"Re λ = {worst.real:.4g} 1/s at {abs(worst.imag) / _TWO_PI:.4g} Hz; "
                f"delay as Padé order {self.pade_order})"
            )
        return "\n".join(lines)


# ------------------------------------------------------------------------------------ margins
def _grid_candidates(u, L):
    """Crossing candidates per grid interval from log-frequency interpolation of log L.

    Within [u_k, u_{k+1}] (u = log ω) ``L(t) = L_k (L_{k+1}/L_k)^t``: exact for power laws
    (integrators, the rigid body) and second order in the spacing otherwise.  Returns, per
    criterion, (valid, u estimate, bracket lo, bracket hi, score, value, sign of the crossing
    equation at lo).
    """
    L0, L1 = L[:-1], L[1:]
    u0, u1 = u[:-1], u[1:]
    lm = jnp.log(jnp.abs(L))
    lm0, lm1 = lm[:-1], lm[1:]
    dphi = jnp.angle(L1 / L0)
    # Phase crossover: arg(−L) = a0 + t dphi crosses 0 (the negative real axis).
    a0 = jnp.angle(-L0)
    a1 = a0 + dphi
    pc = (a0 <= 0) != (a1 <= 0)
    t = jnp.where(pc, a0 / jnp.where(pc, a0 - a1, 1.0), 0.5)
    lm_pc = lm0 + t * (lm1 - lm0)
    sign = jnp.where(a0 <= 0, -1.0, 1.0)
    gm = (pc, u0 + t * (u1 - u0), u0, u1, jnp.abs(lm_pc), jnp.exp(-lm_pc), sign)
    # Gain crossover: log|L| = lm0 + t (lm1 − lm0) crosses 0.
    gc = (lm0 > 0) != (lm1 > 0)
    t = jnp.where(gc, lm0 / jnp.where(gc, lm0 - lm1, 1.0), 0.5)
    pm_deg = jnp.degrees(jnp.remainder(jnp.angle(L0) + t * dphi, _TWO_PI) - math.pi)
    sign = jnp.where(lm0 > 0, 1.0, -1.0)
    pm = (gc, u0 + t * (u1 - u0), u0, u1, jnp.abs(pm_deg), pm_deg, sign)
    # Modulus margin: local minima of |1 + L|² on the grid, vertex of the parabola through the
    # three points in u; the two ends of the grid are candidates too (not refined).
    d2 = jnp.abs(1.0 + L) ** 2
    xm, x0, xp = u[:-2], u[1:-1], u[2:]
    ym, y0, yp = d2[:-2], d2[1:-1], d2[2:]
    interior = (y0 <= ym) & (y0 < yp)
    num = (x0 - xm) ** 2 * (y0 - yp) - (x0 - xp) ** 2 * (y0 - ym)
    den = (x0 - xm) * (y0 - yp) - (x0 - xp) * (y0 - ym)
    safe = interior & (den != 0)
    xv = jnp.clip(x0 - 0.5 * num / jnp.where(safe, den, 1.0), xm, xp)
    xv = jnp.where(safe, xv, x0)
    # value of the interpolating parabola at xv (Lagrange form)
    yv = (
        ym * (xv - x0) * (xv - xp) / ((xm - x0) * (xm - xp))
        + y0 * (xv - xm) * (xv - xp) / ((x0 - xm) * (x0 - xp))
        + yp * (xv - xm) * (xv - x0) / ((xp - xm) * (xp - x0))
    )
    yv = jnp.clip(yv, 0.0, y0)
    ends = jnp.array([True, True])
    sm_valid = jnp.concatenate([ends[:1], interior, ends[1:]])
    sm_u = jnp.concatenate([u[:1], xv, u[-1:]])
    sm_lo = jnp.concatenate([u[:1], xm, u[-1:]])
    sm_hi = jnp.concatenate([u[:1], xp, u[-1:]])
    sm_val = jnp.sqrt(jnp.concatenate([d2[:1], yv, d2[-1:]]))
    sm = (sm_valid, sm_u, sm_lo, sm_hi, sm_val, sm_val, -jnp.ones_like(sm_u))
    return gm, pm, sm


def _pick(valid, score):
    s = jnp.where(valid, score, jnp.inf)
    k = jnp.argmin(s)
    return k, jnp.any(valid)


def _finish(gm, pm, sm) -> Margins:
    """Margins from the chosen (found, u, value) of each criterion."""

    def freq(found, u):
        return jnp.where(found, jnp.exp(jnp.where(found, u, 0.0)) / _TWO_PI, jnp.nan)

    (gf, gu, gv), (pf, pu, pv), (sf, su, sv) = gm, pm, sm
    return Margins(
        gain_margin=jnp.where(gf, gv, jnp.inf),
        phase_margin_deg=jnp.where(pf, pv, jnp.inf),
        modulus_margin=sv,
        phase_crossover_hz=freq(gf, gu),
        gain_crossover_hz=freq(pf, pu),
        modulus_hz=freq(sf, su),
    )


def _grid_margins(u, L) -> Margins:
    """Margins from a sampled open loop (no model): interpolated crossings."""
    out = []
    for valid, u_est, _, _, score, value, _ in _grid_candidates(u, L):
        k, found = _pick(valid, score)
        out.append((found, u_est[k], value[k]))
    return _finish(*out)


def _jet(L_fn, params, v):
    """L(e^v) of every loop and its first two derivatives in v = log ω (each shape (n_loops,))."""

    def Lv(w):
        return jnp.stack(L_fn(params, jnp.exp(w)))

    def first(w):
        return jax.jvp(Lv, (w,), (jnp.ones_like(w),))

    (L, L1), (_, L2) = jax.jvp(first, (v,), (jnp.ones_like(v),))
    return L, L1, L2


def _criteria(L, L1, L2):
    """(f, df/dv) of the three crossing equations, stacked (3,): arg(−L) = 0 (phase
    crossover), log|L| = 0 (gain crossover), d|1 + L|²/dv / 2 = 0 (modulus margin)."""
    r = L1 / L
    f = jnp.stack([jnp.angle(-L), jnp.log(jnp.abs(L)), jnp.real((1.0 + L) * jnp.conj(L1))])
    df = jnp.stack([
        jnp.imag(r), jnp.real(r), jnp.abs(L1) ** 2 + jnp.real((1.0 + L) * jnp.conj(L2)),
    ])
    return f, df


def _values(L):
    """(score, value) of each criterion at a crossing, stacked (3,)."""
    pm = jnp.degrees(jnp.remainder(jnp.angle(L), _TWO_PI) - math.pi)
    sm = jnp.abs(1.0 + L)
    score = jnp.stack([jnp.abs(jnp.log(jnp.abs(L))), jnp.abs(pm), sm])
    value = jnp.stack([1.0 / jnp.abs(L), pm, sm])
    return score, value


def _model_margins(u, Ls, L_fn, params) -> list[Margins]:
    """Margins of the loops ``L_fn(params, ω)`` (tuple, sampled as ``Ls`` on ω = e^u), every
    crossing refined on the model.

    Per loop and criterion the best ``_N_CANDIDATES`` grid crossings are bracketed and refined
    together (one vectorised, safeguarded Newton iteration over all of them: bisection when a
    step leaves its bracket) with the parameters' gradients stopped.  One last Newton step with
    live parameters, ``v* = v − f(v; θ)/f'(v)``, carries the derivative of the crossing
    (implicit function theorem: dv*/dθ = −f_θ/f_v), and L at v* is its first-order expansion
    from v (exact to round-off, with the right derivative).  Then the best is chosen again.
    """
    frozen = jax.tree_util.tree_map(jax.lax.stop_gradient, params)
    k = min(_N_CANDIDATES, u.shape[0] - 1)
    lanes = []  # (loop, criterion, valid, u0, lo, hi, sign at lo) per candidate
    for i, L in enumerate(Ls):
        for c, (valid, u_est, lo, hi, score, _, sign) in enumerate(_grid_candidates(u, L)):
            _, idx = jax.lax.top_k(-jnp.where(valid, score, jnp.inf), k)
            lanes.append((
                jnp.full(k, i), jnp.full(k, c), valid[idx], u_est[idx], lo[idx], hi[idx],
                sign[idx],
            ))
    loop_i, crit, valid, u0, lo, hi, sign_lo = (jnp.concatenate(x) for x in zip(*lanes))
    ok = lo < hi  # the ends of the grid (modulus margin) are not refined

    def f_at(p, v, i, c):
        f, df = _criteria(*(x[i] for x in _jet(L_fn, p, v)))
        return f[c], df[c]

    # Unrolled on purpose: a lax while loop here can deadlock XLA:CPU's thunk executor on small
    # thread pools; the grid start is O(Δu²) close, so a few quadratic steps reach round-off.
    v, a, b = jnp.clip(u0, lo, hi), lo, hi
    for _ in range(_NEWTON_STEPS):
        fv, dfv = jax.vmap(lambda v, i, c: f_at(frozen, v, i, c))(v, loop_i, crit)
        left = jnp.sign(fv) == sign_lo  # the root lies in [v, b]
        a, b = jnp.where(left, v, a), jnp.where(left, b, v)
        step = v - fv / dfv
        inside = (step > a) & (step < b) & jnp.isfinite(step)
        v = jnp.where((fv == 0) | ~ok, v, jnp.where(inside, step, 0.5 * (a + b)))
    v = jax.lax.stop_gradient(v)

    def final(v, i, c, ok):
        L, L1, L2 = (x[i] for x in _jet(L_fn, params, v))
        f, df = _criteria(L, L1, L2)
        df = jax.lax.stop_gradient(df[c])
        dv = jnp.where(ok & (df != 0), -f[c] / jnp.where(df != 0, df, 1.0), 0.0)
        score, value = _values(L + L1 * _c(dv))
        return v + dv, score[c], value[c]

    v, score, value = jax.vmap(final)(v, loop_i, crit, ok)
    out = []
    for i in range(len(Ls)):
        per = []
        for c in range(3):
            sl = slice((3 * i + c) * k, (3 * i + c + 1) * k)
            j, found = _pick(valid[sl], score[sl])
            per.append((found, v[sl][j], value[sl][j]))
        out.append(_finish(*per))
    return out


# ------------------------------------------------------------------------------------ checks
def _check_loop(loop, fn: str) -> AbstractLoop:
    if not isinstance(loop, AbstractLoop):
        raise TypeError(
            f"`{fn}(loop=...)` must be a DoubleLoop or PIDLoop, got {type(loop).__name__}"
        )
    return loop


def _check_pade(pade_order, fn: str) -> int | None:
    if pade_order is None:
        return None
    return _pade_order(pade_order, f"{fn}(pade_order=...)")


def _check_plant(plant, freq_hz, fn: str):
    """Normalise ``plant`` to ("frf", H) or ("model", StateSpace) and validate it."""
    if isinstance(plant, StateSpace):
        if plant.A.ndim not in (2, 3):
            raise ValueError(
                f"`{fn}(plant=...)` must be a StateSpace with A of shape (n, n), or (batch, n, n) "
                f"from jax.vmap over positions, got A of shape {plant.A.shape}"
            )
        return "model", plant
    if isinstance(plant, BallScrewDrive):
        raise TypeError(
            f"`{fn}(plant=...)` takes the drive's FRF, not the drive: pass "
            "`drive.frf(position_m, freq_hz)` (exact, Eq. 2) or `fdjax.state_space(drive, ...)`"
        )
    H = jnp.asarray(plant)
    if H.ndim < 3 or H.shape[-2:] != (3, 2) or H.shape[-3] != freq_hz.shape[0]:
        raise ValueError(
            f"`{fn}(plant=...)` must be an FRF array of shape (..., n_freq, 3, 2) with "
            f"n_freq = {freq_hz.shape[0]} (outputs θ1, x2, x3; inputs T1, F3) or a StateSpace, "
            f"got shape {H.shape}"
        )
    if not jnp.issubdtype(H.dtype, jnp.complexfloating):
        raise ValueError(f"`{fn}(plant=...)` must be a complex FRF array, got dtype {H.dtype}")
    H = _checks.finite(H.astype(jnp.complex128), f"{fn}(plant=...)")
    return "frf", H


# ------------------------------------------------------------------------------------ public
def open_loop(
    loop: AbstractLoop,
    plant,
    freq_hz: Float[ArrayLike, " freq"],
    *,
    pade_order: int | None = None,
) -> OpenLoop:
    r"""Open-loop frequency responses L_v (inner) and L_p (outer) of ``loop`` around ``plant``.

        L_v = C_v G_MCM k_m e^{−iωτ} i_sc iω h_θ1,T1,
        L_p = k_p h_x2,T1 C_v G_MCM k_m e^{−iωτ} / (1 + L_v)

    (module docstring; for a :class:`PIDLoop` ``inner`` is None and ``outer`` = C_pid k_m
    e^{−iωτ} h_x2,T1).  Differentiable w.r.t. the controller and the plant; vmap over positions.

    Args:
        loop: a :class:`DoubleLoop` or :class:`PIDLoop`.
        plant: one of
            * an FRF array (..., n_freq, 3, 2) on ``freq_hz`` (outputs θ1, x2, x3; inputs T1,
              F3), e.g. ``drive.frf(positions, freq_hz)`` or a measurement;
            * a :class:`fdjax.StateSpace` (the twin; speed from ``C_velocity``), or a batch of
              them (``jax.vmap(lambda p: fdjax.state_space(drive, p, n_modes=m))(positions)``).
        freq_hz: positive, increasing frequency grid (Hz).
        pade_order: None for the exact delay e^{−iωτ}; n for its [n/n] Padé approximant.
    """
    fn = "open_loop"
    loop = _check_loop(loop, fn)
    f = _checks.frequency_grid(freq_hz, f"{fn}(freq_hz=...)")
    pade_order = _check_pade(pade_order, fn)
    kind, p = _check_plant(plant, f, fn)
    inner, outer = _open_loop_jit(loop, kind, p, f, pade_order)
    return OpenLoop(freq_hz=f, inner=inner, outer=outer)


@eqx.filter_jit
def _open_loop_jit(loop, kind: str, plant, f, pade_order):
    omega = _TWO_PI * f
    if kind == "frf":
        gv, gx = _frf_channels(plant, omega)
        return loop.open_loops(gv, gx, omega, pade_order=pade_order)

    def one(plant):
        return loop.open_loops(*_plant_channels(plant, omega), omega, pade_order=pade_order)

    return jax.vmap(one)(plant) if plant.A.ndim == 3 else one(plant)


def stability_margins(
    freq_hz: Float[ArrayLike, " freq"], L: Complex[ArrayLike, "*batch freq"]
) -> Margins:
    r"""Gain, phase and modulus margins of a sampled SISO open loop L(i2πf) (negative feedback).

    python-control's conventions (module docstring).  Crossings are located inside grid
    intervals by interpolating log L linearly in log ω (exact for power laws, second order in
    the spacing otherwise); the modulus margin by a parabola through the three grid points
    around each local minimum of |1 + L|.  For a model use :func:`loop_margins`, which refines
    the crossings to round-off.  Leading batch axes are mapped over.

    Args:
        freq_hz: positive, increasing grid (Hz), long enough to contain the crossovers.
        L: complex open loop on that grid, shape (*batch, n_freq).
    """
    f = _checks.frequency_grid(freq_hz, "stability_margins(freq_hz=...)")
    L = jnp.asarray(L)
    if L.ndim < 1 or L.shape[-1] != f.shape[0] or f.shape[0] < 3:
        raise ValueError(
            f"`stability_margins(L=...)` must have shape (*batch, n_freq) with n_freq = "
            f"{f.shape[0]} ≥ 3, got {L.shape}"
        )
    L = _checks.finite(L.astype(jnp.complex128), "stability_margins(L=...)")
    return _stability_margins_jit(f, L)


@eqx.filter_jit
def _stability_margins_jit(f, L):
    u = jnp.log(_TWO_PI * f)
    fn = lambda x: _grid_margins(u, x)
    for _ in range(L.ndim - 1):
        fn = jax.vmap(fn)
    return fn(L)


def loop_margins(
    loop: AbstractLoop,
    plant,
    freq_hz: Float[ArrayLike, " freq"],
    *,
    pade_order: int | None = None,
) -> LoopMargins:
    r"""Gain, phase and modulus margins (with crossovers) of the inner and outer open loops.

    The open loops of :func:`open_loop` are sampled on ``freq_hz``; every crossing is
    bracketed on that grid.  For a state-space plant (the twin) the
    best crossings are then refined by safeguarded Newton iterations on the model's own
    L(iω) to round-off and the margins are differentiable through them; for an FRF array they
    are interpolated (:func:`stability_margins`).  The grid must be dense enough to bracket
    every crossing (a few hundred points per decade around lightly damped modes).

    Args: as :func:`open_loop` (leading batch axes of the FRF or of the StateSpace map).

    Returns:
        :class:`LoopMargins` (``inner`` is None for a :class:`PIDLoop`).
    """
    fn = "loop_margins"
    loop = _check_loop(loop, fn)
    f = _checks.frequency_grid(freq_hz, f"{fn}(freq_hz=...)")
    if f.shape[0] < 3:
        raise ValueError(f"`{fn}(freq_hz=...)` must have at least 3 points, got {f.shape[0]}")
    pade_order = _check_pade(pade_order, fn)
    kind, p = _check_plant(plant, f, fn)
    return _loop_margins_jit(loop, kind, p, f, pade_order)


def _loop_margins_impl(loop, kind: str, plant, f, pade_order):
    u = jnp.log(_TWO_PI * f)
    omega = _TWO_PI * f
    if kind == "frf":
        inner, outer = loop.open_loops(*_frf_channels(plant, omega), omega, pade_order=pade_order)

        def grid(L):
            fn = lambda x: _grid_margins(u, x)
            for _ in range(L.ndim - 1):
                fn = jax.vmap(fn)
            return fn(L)

        return LoopMargins(inner=None if inner is None else grid(inner), outer=grid(outer))

    def one(plant):
        def L_fn(params, w):
            lp, pl = params
            loops = lp.open_loops(*_plant_channels(pl, w), w, pade_order=pade_order)
            return tuple(L for L in loops if L is not None)

        Ls = L_fn((loop, plant), omega)
        ms = _model_margins(u, Ls, L_fn, (loop, plant))
        return LoopMargins(inner=ms[0] if len(ms) == 2 else None, outer=ms[-1])

    return jax.vmap(one)(plant) if plant.A.ndim == 3 else one(plant)


_loop_margins_jit = eqx.filter_jit(_loop_margins_impl)


def closed_loop(
    loop: AbstractLoop, plant: StateSpace, *, pade_order: int = DEFAULT_PADE_ORDER
) -> ClosedLoop:
    r"""The loop closed around the state-space twin, the delay as its [n/n] Padé approximant.

    States: the twin's (2m), then the controller's — for a :class:`DoubleLoop` the PI integrator
    z (ż = v_cmd − v_m), the MCM's realisation (:meth:`fdjax.MCM.state_space`, on the PI output)
    and the Padé delay (:func:`pade`, on k_m u); for a :class:`PIDLoop` the integrator, the
    derivative filter and the delay.  The motor speed is ``i_sc C_velocity[0] x``; the scale
    position ``C[1] x + D[1] u`` keeps the twin's residual feed-through, and the algebraic loop
    it makes through the controller's feed-through is solved exactly.  Inputs ``(r, ṙ, r̈, F3)``,
    outputs ``(θ1, x2, x3, T1)``.

    Args:
        loop: the controller.
        plant: a :class:`fdjax.StateSpace` at one position (vmap over positions).
        pade_order: order n of the delay's Padé approximant (static, 1–16).
    """
    loop = _check_loop(loop, "closed_loop")
    n = _pade_order(pade_order, "closed_loop(pade_order=...)")
    if not isinstance(plant, StateSpace):
        raise TypeError(
            f"`closed_loop(plant=...)` must be an fdjax.StateSpace, got {type(plant).__name__}"
        )
    return _closed_loop_jit(loop, plant, n)


def _closed_loop_impl(loop, plant, n):
    A, B, C, D = loop._closed_loop(plant, _pade_ss(loop.tau, n))
    return ClosedLoop(A=A, B=B, C=C, D=D, position_m=plant.position_m, pade_order=n)


_closed_loop_jit = eqx.filter_jit(_closed_loop_impl)


def check_stability(
    loop: AbstractLoop,
    plant,
    *,
    position_m: Float[ArrayLike, "*pos"] | None = None,
    pade_order: int = DEFAULT_PADE_ORDER,
    n_modes: int | None = None,
    throw: bool = False,
) -> Stability:
    r"""Closed-loop stability at a table position from the poles of :func:`closed_loop`.

    Stable when every pole of the twin closed by the controller (delay as its [n/n] Padé
    approximant) has Re λ < 0.  The result names the position; ``.message`` reads e.g.
    "closed loop unstable at position 0.7 m (least stable pole: Re λ = 16.5 1/s at 93.7 Hz; …)".
    For a drive and concrete positions the twins are built and closed in one compiled, vmapped
    program and the eigenvalues are taken one position at a time (a batched non-symmetric eig
    has dead-locked XLA:CPU); under ``jax.vmap``/``jit`` of the caller they are batched.

    Args:
        loop: the controller.
        plant: a :class:`fdjax.StateSpace`, or a :class:`fdjax.BallScrewDrive` with
            ``position_m`` (scalar or 1-D): its twin is built with :func:`fdjax.state_space`.
        position_m: table position(s) (m), for a drive plant only.
        pade_order: order of the delay's Padé approximant (static).
        n_modes: kept modes of the twin for a drive plant (default: the band's count).
        throw: raise when unstable (eagerly a RuntimeError naming the position; under jit an
            ``eqx.error_if``).  Off by default: an unstable loop is an answer, not a failure.
    """
    fn = "check_stability"
    loop = _check_loop(loop, fn)
    n = _pade_order(pade_order, f"{fn}(pade_order=...)")
    if isinstance(plant, BallScrewDrive):
        if position_m is None:
            raise ValueError(f"`{fn}(position_m=...)` is required when the plant is a drive")
        pos = plant._check_positions(position_m)
        if n_modes is None:
            n_modes = count_modes(plant)
        closed = _closed_loops_drive_jit(loop, plant, pos, n, int(n_modes))
        if _checks.is_concrete(closed.A):
            # One eigenvalue problem per position: a batched non-symmetric eig has been seen to
            # dead-lock XLA:CPU (jax 0.10), and so has a compiled loop of LAPACK calls.
            parts = [_stability_of_jit(jax.tree_util.tree_map(lambda x, i=i: x[i], closed))
                     for i in range(pos.shape[0])]
            result = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *parts)
        else:
            result = jax.vmap(_stability_of)(closed)
        if jnp.ndim(position_m) == 0:
            result = jax.tree_util.tree_map(lambda x: x[0], result)
    elif isinstance(plant, StateSpace):
        if position_m is not None:
            raise ValueError(f"`{fn}(position_m=...)` is only for a BallScrewDrive plant")
        result = _stability_jit(loop, plant, n)
    else:
        raise TypeError(
            f"`{fn}(plant=...)` must be an fdjax.StateSpace or BallScrewDrive, "
            f"got {type(plant).__name__}"
        )
    if throw:
        if _checks.is_concrete(result.stable):
            if not np.all(np.asarray(result.stable)):
                raise RuntimeError(result.message)
        else:
            result = eqx.error_if(
                result, jnp.logical_not(jnp.all(result.stable)), "closed loop unstable"
            )
    return result


def _stability_of(cl: ClosedLoop) -> Stability:
    poles = _sorted_poles(cl.A)
    re = jnp.real(poles)
    return Stability(
        stable=re[0] < 0,
        spectral_abscissa=re[0],
        min_damping=jnp.min(-re / jnp.abs(poles)),
        position_m=cl.position_m,
        poles=poles,
        pade_order=cl.pade_order,
    )


_stability_of_jit = eqx.filter_jit(_stability_of)


@eqx.filter_jit
def _stability_jit(loop, plant, n):
    return _stability_of(_closed_loop_impl(loop, plant, n))


@eqx.filter_jit
def _closed_loops_drive_jit(loop, drive, pos, n, n_modes):
    def one(p):
        return _closed_loop_impl(loop, state_space(drive, p, n_modes=n_modes), n)

    return jax.vmap(one)(pos)


def _sorted_poles(A):
    lam = jnp.linalg.eigvals(A)
    return lam[jnp.argsort(-jnp.real(lam))]


@eqx.filter_jit
def _ss_frf(A, B, C, D, f):
    s = (_c(_TWO_PI * f) * 1j)[:, None, None]
    n = A.shape[0]
    Z = s * jnp.eye(n, dtype=jnp.complex128) - _c(A)
    X = jnp.linalg.solve(Z, jnp.broadcast_to(_c(B), (f.shape[0], *B.shape)))
    return _c(C) @ X + _c(D)
