r"""A parameterisation of the double loop that gradient steps cannot break.

A tuner (or the scheduling network) works on a vector θ of unconstrained reals of order one; the
controller is built from θ through maps whose image is the admissible set, so no step of any
size can leave it:

* gains by logarithms about a reference value: k = k_ref e^{clip(θ, ±30)} (k_p, k_v, k_i),
  finite and positive for every finite θ (a step of any length, e.g. an L-BFGS step after
  convergence, cannot overflow the exponential to ∞ or 0; e^30 ≈ 1e13 is beyond any design);
  the feed-forward gains, free reals, in units of their reference: k_ff = k_ff,ref θ;
* each filter frequency, damping and gain inside a box, logarithmically:
  x = x_lo (x_hi/x_lo)^{σ(θ)}, σ the logistic function, with every frequency below a fraction
  of the Nyquist frequency π/T of the servo (the discretisation needs ω T < π);
* the peak filter's phase inside (−φ_max, φ_max): φ = φ_max tanh θ;
* the notch depth ζ_n/ζ_d inside (d_min, 1) by construction: ζ_n = ζ_d d_min^{σ(θ)}, so the
  notch can never turn into a lead element (ζ_n > ζ_d).

The seven filter parameters (paper Secs. 4.2 and 5: the peak filter's K, ω, ξ, φ on mode 3 and the
notch's ω, ζ_n, ζ_d on mode 5) in this normalised form are what the scheduling network outputs.
The hardware (servo period, delay, motor constant) is not part of θ.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import (
    check,
    concrete_float,
    instance,
    is_concrete,
    static_bool,
    static_number,
)
from .._control import DoubleLoop, PIDLoop
from .._control._controllers import AbstractController
from .._control._servo import Servo
from .._filters import MCM, NotchFilter, PeakFilter

__all__ = ["MCM_PARAMETERS", "GAIN_PARAMETERS", "PID_PARAMETERS", "MCMBounds",
           "AbstractParameterisation", "DoubleLoopParameterisation", "PIDParameterisation"]

MCM_PARAMETERS = ("peak_K", "peak_omega", "peak_xi", "peak_phi",
                  "notch_omega", "notch_zeta_d", "notch_depth")
"""The seven normalised filter parameters, in the order of θ (notch_depth = ζ_n/ζ_d)."""

GAIN_PARAMETERS = ("kp", "kv", "ki", "k_ffv", "k_ffa")
"""The five normalised gains of a :class:`fdjax.DoubleLoop`, in the order of θ."""

PID_PARAMETERS = ("kp", "ki", "kd", "wd", "k_ffv", "k_ffa")
"""The six normalised parameters of a :class:`fdjax.PIDLoop`, in the order of θ."""

_TWO_PI = 2.0 * math.pi


def _pair(value, where: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(
            f"`{where}` must be a (low, high) pair of numbers, got {value!r}"
        ) from None
    if not (0.0 < lo < hi < math.inf):
        raise ValueError(
            f"`{where}` must satisfy 0 < low < high < inf, got ({lo:.6g}, {hi:.6g})"
        )
    return lo, hi


def _float(v) -> float:
    """A concrete real scalar as a Python float; anything else a ``TypeError``/``ValueError``."""
    if isinstance(v, bool) or not is_concrete(v) or np.ndim(v) != 0 or not np.isrealobj(v):
        raise TypeError
    return float(v)


def _static(pair: bool, **kwargs):
    """A static bounds field whose value is kept as Python floats (a number, or a (low, high)
    pair with ``pair``), so that the bounds hash, compare and serialise as numbers; anything
    else is left as it is for ``__check_init__`` to name."""
    def convert(value):
        try:
            if pair:  # a tuple, a list or an array of two numbers
                if np.ndim(value) != 1 or np.shape(value)[0] != 2:
                    return value
                return tuple(_float(v) for v in value)
            return _float(value)
        except (TypeError, ValueError):
            return value

    return eqx.field(static=True, converter=convert, **kwargs)


LOG_GAIN_LIMIT = 30.0
"""|θ| of a gain beyond which its exponential is held (module docstring)."""


def _gain(reference: float, theta: Array) -> Array:
    """k_ref e^{clip(θ, ±LOG_GAIN_LIMIT)}: finite and positive for every finite θ."""
    return reference * jnp.exp(jnp.clip(theta, -LOG_GAIN_LIMIT, LOG_GAIN_LIMIT))


def _box(theta: Array, lo: float, hi: float) -> Array:
    """lo (hi/lo)^{σ(θ)}: inside (lo, hi) for every real θ (clipped to [lo, hi] against the
    round-off of a saturated σ, where the gradient vanishes anyway)."""
    return jnp.clip(lo * jnp.exp(math.log(hi / lo) * jax.nn.sigmoid(theta)), lo, hi)


_LOGIT_EPS = float(np.finfo(np.float64).eps)
"""The distance from 0 and 1 at which ``_unbox`` holds σ(θ): |θ| ≤ 36, where ``_box``'s σ has
saturated, so that a filter on the boundary of the bounds (``to_mcm`` of a large θ) reads back."""


def _within(x: Array, lo: float, hi: float, where: str, name: str) -> Array:
    """x checked inside [lo, hi] by :func:`fdjax._checks.check` (eagerly or as an
    ``eqx.error_if``), to 1e-12 of each bound's size: the filters keep log ω, log ξ, log ζ, and
    a bound comes back from exp(log x) to a few ulps."""
    a, b = lo - 1e-12 * abs(lo), hi + 1e-12 * abs(hi)
    return check(x, lambda v: (v >= a) & (v <= b), where,
                 f"a filter with {name} inside [{lo:.6g}, {hi:.6g}]")


def _unbox(x: Array, lo: float, hi: float, name: str, where: str, *,
           inverted: bool = False) -> Array:
    """The inverse of ``_box``, logit(log(x/lo)/log(hi/lo)); with ``inverted`` the inverse of
    x = lo^{σ(θ)} on (lo, 1) (the notch depth), logit(log x/log lo).  x on the closed interval
    [lo, hi] (where ``_box`` saturates) reads back as the θ of σ(θ) = ε or 1 − ε."""
    x = _within(x, lo, hi, where, name)
    u = jnp.log(x) / math.log(lo) if inverted else jnp.log(x / lo) / math.log(hi / lo)
    u = jnp.clip(u, _LOGIT_EPS, 1.0 - _LOGIT_EPS)
    return jnp.log(u) - jnp.log1p(-u)


class MCMBounds(eqx.Module):
    r"""The admissible set of an MCM with one peak and one notch filter, and the maps between
    its seven normalised parameters θ ∈ ℝ⁷ (:data:`fdjax.MCM_PARAMETERS`) and the filter:

        K = K_lo (K_hi/K_lo)^{σ(θ₀)},    ω_pf = ω_lo (ω_hi/ω_lo)^{σ(θ₁)},
        ξ = ξ_lo (ξ_hi/ξ_lo)^{σ(θ₂)},    φ = φ_max tanh θ₃,
        ω_nf = ω_lo (ω_hi/ω_lo)^{σ(θ₄)}, ζ_d = ζ_lo (ζ_hi/ζ_lo)^{σ(θ₅)},  ζ_n = ζ_d d_min^{σ(θ₆)},

    with (ω_lo, ω_hi) = 2π ``freq_hz``, ω_hi below the Nyquist frequency π/T of the servo
    period T (``for_servo`` sets ``freq_hz[1]`` = ``nyquist_fraction`` × Nyquist; paper
    Eqs. (3)–(4) for the filters).  Every θ gives a filter the sampled loop can run
    (``discretize`` needs ω T < π) and a notch of depth ζ_n/ζ_d < 1.

    Attributes (static numbers; build with ``MCMBounds.for_servo(servo)`` or directly):
        period: servo period T (s).
        freq_hz: (low, high) bound of both filter frequencies (Hz); high ≤ ``nyquist_fraction``
            of the Nyquist frequency.
        peak_gain: (low, high) of K (> 0).
        peak_damping: (low, high) of ξ.
        peak_phase_max: φ_max (rad), in (0, π].
        notch_damping: (low, high) of ζ_d.
        notch_depth_min: d_min, the deepest notch ζ_n/ζ_d, in (0, 1).
    """

    period: float = _static(False)
    freq_hz: tuple[float, float] = _static(True, default=(10.0, 3600.0))
    peak_gain: tuple[float, float] = _static(True, default=(1e-3, 10.0))
    peak_damping: tuple[float, float] = _static(True, default=(0.02, 1.0))
    peak_phase_max: float = _static(False, default=math.pi)
    notch_damping: tuple[float, float] = _static(True, default=(0.01, 2.0))
    notch_depth_min: float = _static(False, default=1e-3)

    def __check_init__(self):
        T = concrete_float(self.period, "MCMBounds(period=...)")
        if not (0.0 < T < 1.0):
            raise ValueError(f"`MCMBounds(period=...)` must be in (0, 1) s, got {T:.6g}")
        lo, hi = _pair(self.freq_hz, "MCMBounds(freq_hz=...)")
        nyquist = 0.5 / T
        if hi >= nyquist:
            raise ValueError(
                f"`MCMBounds(freq_hz=...)` must stay below the Nyquist frequency "
                f"{nyquist:.6g} Hz of the period {T:.6g} s, got high = {hi:.6g} Hz"
            )
        _pair(self.peak_gain, "MCMBounds(peak_gain=...)")
        _pair(self.peak_damping, "MCMBounds(peak_damping=...)")
        _pair(self.notch_damping, "MCMBounds(notch_damping=...)")
        static_number(self.peak_phase_max, "MCMBounds(peak_phase_max=...)",
                      lambda v: 0.0 < v <= math.pi, "a number in (0, π] rad")
        static_number(self.notch_depth_min, "MCMBounds(notch_depth_min=...)",
                      lambda v: 0.0 < v < 1.0, "a number in (0, 1)")

    @classmethod
    def for_servo(cls, servo: Servo, *, nyquist_fraction: float = 0.9,
                  freq_min_hz: float = 10.0, **kwargs) -> MCMBounds:
        """Bounds for a servo: filter frequencies from ``freq_min_hz`` up to
        ``nyquist_fraction`` of its Nyquist frequency; other bounds as the defaults or
        ``kwargs``."""
        fn = "MCMBounds.for_servo"
        instance(servo, Servo, f"{fn}(servo=...)")
        for name in ("period", "freq_hz"):
            if name in kwargs:
                raise TypeError(f"`{fn}({name}=...)` is set from the servo (its period and "
                                "nyquist_fraction, freq_min_hz); build MCMBounds(...) directly "
                                f"to give {name}")
        nyquist_fraction = static_number(nyquist_fraction, f"{fn}(nyquist_fraction=...)",
                                         lambda v: 0.0 < v < 1.0, "a number in (0, 1)")
        hi = nyquist_fraction * 0.5 / float(servo.period)
        freq_min_hz = static_number(freq_min_hz, f"{fn}(freq_min_hz=...)",
                                    lambda v: 0.0 < v < hi,
                                    f"a positive number below the filters' highest "
                                    f"frequency {hi:.6g} Hz")
        return cls(period=float(servo.period), freq_hz=(freq_min_hz, hi), **kwargs)

    @property
    def _omega(self) -> tuple[float, float]:
        return _TWO_PI * self.freq_hz[0], _TWO_PI * self.freq_hz[1]

    def to_mcm(self, theta: Float[ArrayLike, " 7"]) -> MCM:
        """The MCM of the normalised parameters θ (class docstring); differentiable, and any
        real θ gives an admissible filter."""
        th = jnp.asarray(theta, jnp.float64)
        if th.shape[-1:] != (7,) or th.ndim != 1:
            raise ValueError(f"`MCMBounds.to_mcm(theta=...)` must have shape (7,), got {th.shape}")
        _finite_theta(th, "MCMBounds.to_mcm(theta=...)")
        w_lo, w_hi = self._omega
        zeta_d = _box(th[5], *self.notch_damping)
        peak = PeakFilter(
            _box(th[0], *self.peak_gain),
            _box(th[1], w_lo, w_hi),
            _box(th[2], *self.peak_damping),
            self.peak_phase_max * jnp.tanh(th[3]),
        )
        notch = NotchFilter(
            _box(th[4], w_lo, w_hi),
            zeta_d * jnp.exp(math.log(self.notch_depth_min) * jax.nn.sigmoid(th[6])),
            zeta_d,
        )
        return MCM(peak, notch)

    def from_mcm(self, mcm: MCM) -> Float[Array, " 7"]:
        """θ of an MCM with one peak and one notch filter inside the bounds (the inverse of
        :meth:`to_mcm`); a parameter outside them is a ``ValueError`` naming it."""
        return self._from_mcm(mcm, "MCMBounds.from_mcm(mcm=...)")

    def _from_mcm(self, mcm, where: str):
        """:meth:`from_mcm`, its errors naming ``where`` (the argument the user gave)."""
        if not isinstance(mcm, MCM) or mcm.peak is None or mcm.notch is None:
            raise TypeError(f"`{where}` must be an fdjax.MCM with a peak and a notch filter")
        pk, nt = mcm.peak, mcm.notch
        if pk.K.shape != (1,) or nt.omega.shape != (1,):
            raise ValueError(
                f"`{where}` must hold one peak and one notch filter, got {pk.K.shape[0]} "
                f"and {nt.omega.shape[0]}"
            )
        w_lo, w_hi = self._omega
        pm = self.peak_phase_max
        phi = _within(pk.phi[0], -pm, pm, where, "the peak phase (rad)")
        depth = nt.zeta_n[0] / nt.zeta_d[0]
        return jnp.stack([
            _unbox(pk.K[0], *self.peak_gain, "the peak gain K", where),
            _unbox(pk.omega[0], w_lo, w_hi, "the peak frequency ω (rad/s)", where),
            _unbox(pk.xi[0], *self.peak_damping, "the peak damping ξ", where),
            jnp.arctanh(jnp.clip(phi / pm, _LOGIT_EPS - 1.0, 1.0 - _LOGIT_EPS)),
            _unbox(nt.omega[0], w_lo, w_hi, "the notch frequency ω (rad/s)", where),
            _unbox(nt.zeta_d[0], *self.notch_damping, "the notch damping ζ_d", where),
            _unbox(depth, self.notch_depth_min, 1.0, "the notch depth ζ_n/ζ_d", where,
                   inverted=True),
        ])


def _finite_theta(th, where: str) -> None:
    """A concrete θ finite, the first bad entry named by its index (a traced one is checked by
    the controller's own fields, under their names)."""
    if is_concrete(th):
        bad = np.flatnonzero(~np.isfinite(np.asarray(th)))
        if bad.size:
            raise ValueError(f"`{where}` must be finite, got {float(np.asarray(th)[bad[0]])} at "
                             f"index {int(bad[0])}")


class AbstractParameterisation(eqx.Module):
    """A map θ ∈ ℝⁿ ↔ controller whose image is the admissible set: what the tuners
    (:func:`fdjax.tune_local`, :func:`fdjax.tune_robust`) descend on."""

    @property
    def names(self) -> tuple[str, ...]:
        """Names of θ's entries."""
        raise NotImplementedError

    def to_controller(self, theta: Float[ArrayLike, " n"]) -> AbstractController:
        """The controller of θ."""
        raise NotImplementedError

    def from_controller(self, controller: AbstractController) -> Float[Array, " n"]:
        """θ of a controller (the inverse of :meth:`to_controller`)."""
        raise NotImplementedError

    @property
    def highest_frequency_hz(self) -> float | None:
        """The highest filter frequency (Hz) any θ gives, which the servo that runs the
        controller must sample (below its Nyquist frequency); None: no filter."""
        return None


def check_sampled_by(highest_hz: float | None, servo: Servo, where: str) -> None:
    """Refuse filter bounds that reach the Nyquist frequency of ``servo``, the servo whose
    sampled loop the controllers run in (bounds built for another servo): eagerly, naming
    ``where``, instead of the discretisation's error in the middle of a run."""
    if highest_hz is None:
        return
    nyquist = 0.5 / float(servo.period)
    if not highest_hz < nyquist:
        raise ValueError(
            f"`{where}` lets the filters reach {highest_hz:.6g} Hz, not below the Nyquist "
            f"frequency {nyquist:.6g} Hz of the servo they run on (period {float(servo.period):.6g}"
            " s): build the bounds for that servo, e.g. MCMBounds.for_servo(servo)")


def _reference_scales(where: str, values, names) -> tuple[float, ...]:
    if not all(is_concrete(v) for v in values):
        raise TypeError(f"`{where}` needs concrete gains")
    scales = tuple(float(v) for v in values)
    for name, v in zip(names, scales):
        if v == 0.0 or not math.isfinite(v):
            raise ValueError(
                f"`{where}`: {name} sets the scale of its parameter and must be finite and "
                f"nonzero, got {v:.6g}"
            )
    return scales


class DoubleLoopParameterisation(AbstractParameterisation):
    r"""θ ∈ ℝ¹² ↔ a :class:`fdjax.DoubleLoop` with an MCM (one peak, one notch):

        k_p = k_p,ref e^{θ₀},  k_v = k_v,ref e^{θ₁},  k_i = k_i,ref e^{θ₂},
        k_ffv = k_ffv,ref θ₃,  k_ffa = k_ffa,ref θ₄,  MCM = ``mcm.to_mcm(θ₅…θ₁₁)``,

    so that θ = (0, 0, 0, 1, 1, …) is the reference gains, every entry is of order one and every
    θ gives an admissible controller (:class:`MCMBounds`).  The reference values are static
    numbers (the scales of the problem), not tunable leaves.  With ``feedforward=False`` the
    loop has no feed-forward (k_ffv = k_ffa = 0 whatever θ₃, θ₄): a feedback-only design.
    """

    mcm: MCMBounds
    reference: tuple[float, float, float, float, float] = eqx.field(static=True)
    feedforward: bool = eqx.field(static=True)

    def __init__(self, mcm: MCMBounds, reference: DoubleLoop | None = None, *,
                 feedforward: bool = True):
        instance(mcm, MCMBounds, "DoubleLoopParameterisation(mcm=...)")
        feedforward = static_bool(feedforward, "DoubleLoopParameterisation(feedforward=...)")
        ref = DoubleLoop() if reference is None else reference
        instance(ref, DoubleLoop, "DoubleLoopParameterisation(reference=...)")
        vals = [ref.kp, ref.kv, ref.ki, ref.k_ffv, ref.k_ffa]
        if not feedforward:
            vals = vals[:3] + [1.0, 1.0]
        self.feedforward = bool(feedforward)
        self.mcm = mcm
        self.reference = _reference_scales("DoubleLoopParameterisation(reference=...)", vals,
                                           GAIN_PARAMETERS)

    @property
    def names(self) -> tuple[str, ...]:
        """Names of θ's entries."""
        return GAIN_PARAMETERS + MCM_PARAMETERS

    def to_controller(self, theta: Float[ArrayLike, " 12"]) -> DoubleLoop:
        """The double loop of θ (class docstring)."""
        th = jnp.asarray(theta, jnp.float64)
        if th.shape != (12,):
            raise ValueError(
                f"`DoubleLoopParameterisation.to_controller(theta=...)` must have shape (12,), "
                f"got {th.shape}"
            )
        _finite_theta(th, "DoubleLoopParameterisation.to_controller(theta=...)")
        kp, kv, ki, ffv, ffa = self.reference
        on = 1.0 if self.feedforward else 0.0
        return DoubleLoop(_gain(kp, th[0]), _gain(kv, th[1]), _gain(ki, th[2]),
                          k_ffv=on * ffv * th[3], k_ffa=on * ffa * th[4],
                          mcm=self.mcm.to_mcm(th[5:]))

    @property
    def highest_frequency_hz(self) -> float:
        """The MCM's highest filter frequency (Hz), ``mcm.freq_hz[1]``."""
        return float(self.mcm.freq_hz[1])

    def from_controller(self, loop: DoubleLoop) -> Float[Array, " 12"]:
        """θ of a double loop whose MCM lies inside the bounds (inverse of
        :meth:`to_controller`)."""
        instance(loop, DoubleLoop, "DoubleLoopParameterisation.from_controller(loop=...)")
        kp, kv, ki, ffv, ffa = self.reference
        ff = ((loop.k_ffv / ffv, loop.k_ffa / ffa) if self.feedforward
              else (jnp.ones(()), jnp.ones(())))
        gains = jnp.stack([loop.log_kp - math.log(kp), loop.log_kv - math.log(kv),
                           loop.log_ki - math.log(ki), *ff])
        return jnp.concatenate([gains, self.mcm._from_mcm(
            loop.mcm, "DoubleLoopParameterisation.from_controller(loop=...).mcm")])


class PIDParameterisation(AbstractParameterisation):
    r"""θ ∈ ℝ⁶ ↔ a :class:`fdjax.PIDLoop` (:data:`fdjax.PID_PARAMETERS`):

        k_p = k_p,ref e^{θ₀},  k_i = k_i,ref e^{θ₁},  k_d = k_d,ref e^{θ₂},
        ω_d = ω_lo (ω_hi/ω_lo)^{σ(θ₃)},  k_ffv = k_ffv,ref θ₄,  k_ffa = k_ffa,ref θ₅,

    the derivative filter's corner ω_d inside (``wd_hz`` bounds) below the servo's Nyquist
    frequency, so every θ gives a PID the sampled loop can run.  The reference values are
    static scales; θ = (0, 0, 0, ·, 1, 1) is the reference PID.  With ``feedforward=False``
    k_ffv = k_ffa = 0 whatever θ₄, θ₅ (a feedback-only design).

    Built from the reference :class:`fdjax.PIDLoop`; ``servo`` (default ``Servo()``) sets the
    default ``wd_hz`` = (10 Hz, 0.9 × its Nyquist frequency).

    Attributes:
        reference: (k_p, k_i, k_d, k_ffv, k_ffa) of the reference PID (static).
        wd_hz: (low, high) bound of ω_d/2π (Hz), static.
        feedforward: whether θ₄, θ₅ set the feed-forward gains (static).
    """

    reference: tuple[float, float, float, float, float] = eqx.field(static=True)
    wd_hz: tuple[float, float] = eqx.field(static=True)
    feedforward: bool = eqx.field(static=True)

    def __init__(self, reference: PIDLoop, *, servo: Servo | None = None,
                 wd_hz: tuple[float, float] | None = None, feedforward: bool = True):
        where = "PIDParameterisation(reference=...)"
        instance(reference, PIDLoop, where)
        feedforward = static_bool(feedforward, "PIDParameterisation(feedforward=...)")
        vals = [reference.kp, reference.ki, reference.kd, reference.k_ffv, reference.k_ffa]
        if not feedforward:
            vals = vals[:3] + [1.0, 1.0]
        self.feedforward = bool(feedforward)
        self.reference = _reference_scales(where, vals, ("kp", "ki", "kd", "k_ffv", "k_ffa"))
        sv = Servo() if servo is None else servo
        instance(sv, Servo, "PIDParameterisation(servo=...)")
        if wd_hz is None:
            wd_hz = (10.0, 0.9 * 0.5 / float(sv.period))
        lo, hi = _pair(wd_hz, "PIDParameterisation(wd_hz=...)")
        if hi >= 0.5 / float(sv.period):
            raise ValueError(
                f"`PIDParameterisation(wd_hz=...)` must stay below the Nyquist frequency "
                f"{0.5 / float(sv.period):.6g} Hz, got high = {hi:.6g} Hz"
            )
        self.wd_hz = (lo, hi)

    @property
    def names(self) -> tuple[str, ...]:
        """Names of θ's entries."""
        return PID_PARAMETERS

    @property
    def highest_frequency_hz(self) -> float:
        """The derivative filter's highest corner (Hz), ``wd_hz[1]``."""
        return float(self.wd_hz[1])

    def to_controller(self, theta: Float[ArrayLike, " 6"]) -> PIDLoop:
        """The PID of θ (class docstring)."""
        th = jnp.asarray(theta, jnp.float64)
        if th.shape != (6,):
            raise ValueError(
                f"`PIDParameterisation.to_controller(theta=...)` must have shape (6,), got "
                f"{th.shape}"
            )
        _finite_theta(th, "PIDParameterisation.to_controller(theta=...)")
        kp, ki, kd, ffv, ffa = self.reference
        wd = _box(th[3], _TWO_PI * self.wd_hz[0], _TWO_PI * self.wd_hz[1])
        on = 1.0 if self.feedforward else 0.0
        return PIDLoop(_gain(kp, th[0]), _gain(ki, th[1]), _gain(kd, th[2]), wd,
                       k_ffv=on * ffv * th[4], k_ffa=on * ffa * th[5])

    def from_controller(self, loop: PIDLoop) -> Float[Array, " 6"]:
        """θ of a PID whose ω_d lies inside the bounds (inverse of :meth:`to_controller`)."""
        where = "PIDParameterisation.from_controller(loop=...)"
        instance(loop, PIDLoop, where)
        kp, ki, kd, ffv, ffa = self.reference
        lo, hi = _TWO_PI * self.wd_hz[0], _TWO_PI * self.wd_hz[1]
        return jnp.stack([loop.log_kp - math.log(kp), loop.log_ki - math.log(ki),
                          loop.log_kd - math.log(kd),
                          _unbox(loop.wd, lo, hi, "the derivative corner ω_d (rad/s)", where),
                          *((loop.k_ffv / ffv, loop.k_ffa / ffa) if self.feedforward
                            else (jnp.ones(()), jnp.ones(())))])
