r"""The servo's hardware: sampling, the control delay, the motor constant and the current
rating.

What a drive's hardware fixes is kept apart from what a designer tunes: a controller
(:class:`fdjax.DoubleLoop`, :class:`fdjax.PIDLoop`, or a user's own) holds only gains and
filters, so ``eqx.filter_grad`` of a loss over a controller differentiates those alone and an
optax step cannot touch the hardware.  The screw ratio i_sc = lead/2π that scales the encoder's
motor speed to linear units is the drive's, read from the plant.
"""

from __future__ import annotations

import equinox as eqx
import numpy as np
from jaxtyping import Array, Float

from .. import _checks

__all__ = ["Servo"]

REFERENCE_PERIOD_S = 1.25e-4
"""Servo period of the reference servo (s): an 8 kHz current/speed/position loop."""

REFERENCE_DELAY_SAMPLES = 2
"""Control delay of the reference servo in servo periods: one for the measurement (encoder and
scale are read at the start of the period), one for the computation (the command is applied at
the next period's start)."""

REFERENCE_K_MOTOR = 1.2
"""k_i·k_T of the reference servo (N·m/A): a ~10 N·m servo motor and its amplifier."""

REFERENCE_CURRENT_LIMIT_A = 40.0
"""Peak current of the reference servo's amplifier (A): 48 N·m of peak torque at k_T·k_i 1.2."""


def _static_float(v):
    """A real scalar as a Python float (a static field); anything else as given, for the
    check's named error."""
    if isinstance(v, bool | str):
        return v
    try:
        return float(v) if np.ndim(v) == 0 else v
    except (TypeError, ValueError):
        return v


class Servo(eqx.Module):
    r"""The servo drive's hardware (paper Fig. 7): servo period T, control delay τ = d·T, the
    motor gain k_m = k_i·k_T from current command to torque, and the amplifier's current
    rating.

        T1(t) = k_m u(t − τ),      τ = d T,

    The delay lumps measurement and computation; in the sampled loop it is d whole samples, in
    the continuous loop e^{−sτ} exactly (or its Padé approximant).

    Attributes:
        period: servo period T (s, static: it sets the number of samples of a run); default
            125 µs (8 kHz).  Drives close these loops at 8–16 kHz.
        delay_samples: d ≥ 1, the delay in servo periods (static: it sets the sampled loop's
            size); default 2.
        k_motor: k_i·k_T (N·m/A); default 1.2.
        current_limit: the amplifier's peak current (A, static), the rating the tuning
            objective keeps the current command below (:class:`fdjax.Objective`); default 40.
    """

    period: float = eqx.field(static=True, default=REFERENCE_PERIOD_S, converter=_static_float)
    delay_samples: int = eqx.field(static=True, default=REFERENCE_DELAY_SAMPLES)
    k_motor: Float[Array, ""] = _checks.positive_field("Servo(k_motor=...)",
                                                       default=REFERENCE_K_MOTOR)
    current_limit: float = eqx.field(static=True, default=REFERENCE_CURRENT_LIMIT_A,
                                     converter=_static_float)

    def __check_init__(self):
        p = self.period
        number = isinstance(p, int | float) and not isinstance(p, bool)
        if not (number and 0 < p <= 0.01):
            hint = ""  # the units a wrong value was likely given in
            if number and p >= 1:
                hint = (f"; if {p:g} is a rate in Hz, the period is {1 / p:.6g} s; if it is "
                        f"in µs, {p * 1e-6:.6g} s")
            elif number and 0.01 < p < 1:
                hint = f"; if {p:g} is in ms, the period is {p * 1e-3:.6g} s"
            raise ValueError(f"`Servo(period=...)` must be a number in (0, 0.01] s (a servo's "
                             f"sampling period), got {p!r}{hint}")
        _checks.static_int(self.delay_samples, "Servo(delay_samples=...)", 1, 64)
        _checks.static_number(self.current_limit, "Servo(current_limit=...)", lambda v: v > 0,
                              "finite and positive (A)")
        if self.k_motor.ndim != 0:
            raise ValueError(
                f"`Servo(k_motor=...)` must be a scalar, got shape {self.k_motor.shape}"
            )

    @property
    def tau(self) -> float:
        """The control delay τ = d·T (s)."""
        return self.delay_samples * float(self.period)
