r"""The reference settings of the paper's closed-loop figures (Figs. 14, 16, 17, 18): the servo,
the reference controller with its MCM, the PID baseline, and the feed-forward of the rigid drive.

These are tuned at 115 mm by hand and by the largest stable gain (gradient tuning improves on
them); :mod:`fdjax.cli`
reproduces the figures with them and the tests pin them, so they live here, once, as functions
of the drive and the servo rather than as numbers copied where they are used.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._checks import finite, instance, real_scalar
from .._drive._model import BallScrewDrive
from .._drive._reference import reference_drive
from .._filters import MCM, NotchFilter, PeakFilter
from ._controllers import DoubleLoop, PIDLoop
from ._servo import (
    REFERENCE_CURRENT_LIMIT_A,
    REFERENCE_DELAY_SAMPLES,
    REFERENCE_K_MOTOR,
    REFERENCE_PERIOD_S,
    Servo,
)

__all__ = [
    "reference_controller",
    "reference_servo",
    "reference_mcm",
    "reference_pid",
    "rigid_feedforward",
]

_TWO_PI = 2.0 * math.pi


def reference_servo() -> Servo:
    r"""The reference servo of the simulations of paper Figs. 14, 16–17: T = 125 µs (8 kHz),
    d = 2 periods of delay (τ = d·T = 250 µs), k_m = k_i·k_T = 1.2 N·m/A, a 40 A peak current
    rating.  The same hardware as ``Servo()``."""
    return Servo(period=REFERENCE_PERIOD_S, delay_samples=REFERENCE_DELAY_SAMPLES,
                 k_motor=REFERENCE_K_MOTOR, current_limit=REFERENCE_CURRENT_LIMIT_A)


def reference_mcm() -> MCM:
    r"""The MCM of :func:`reference_controller`, tuned at Y_table = 115 mm for
    :func:`fdjax.reference_drive`, G_MCM = G_pf · G_nf (paper Eqs. (3)–(4)):

    * a peak filter on the saddle's axial mode (174 Hz at 115 mm), K = 0.34, ξ = 0.20,
      φ = −50°: it corrects the phase of the mode in the position loop;
    * a notch on the screw's torsional mode (1260 Hz, the mode the motor encoder sees),
      ζ_n = 0.005, ζ_d = 0.34: depth ζ_n/ζ_d ≈ 0.015 (−37 dB).

    The seven values maximise the largest stable k_v of the sampled loop at 115 mm
    (``examples/servo_drive_study.py``).
    """
    return MCM(
        PeakFilter(0.34, _TWO_PI * 174.0, 0.20, math.radians(-50.0)),
        NotchFilter(_TWO_PI * 1260.0, 0.005, 0.34),
    )


def reference_controller(drive: BallScrewDrive | None = None,
                         servo: Servo | None = None) -> DoubleLoop:
    r"""The reference controller of Figs. 14, 17 and 18: the double loop of paper Fig. 13 tuned
    at Y_table = 115 mm for :func:`fdjax.reference_drive` and :func:`reference_servo`,

        k_p = 200 1/s,  k_v = 5400 A·s/m,  k_i = 60 rad/s,  G_MCM = :func:`reference_mcm`,

    full velocity feed-forward (k_ffv = 1) and the rigid drive's acceleration feed-forward
    (:func:`rigid_feedforward`).  On the sampled loop its k_v headroom (the factor by which k_v
    alone can grow before the loop goes unstable) is 10.8 dB at 115 mm; without the MCM the
    largest stable k_v is 375 A·s/m, 50× less.  Held fixed it loses its headroom toward the
    screw end (2.5 dB at 0.3 m, unstable from 0.5 m): the saddle's axial mode moves from 177 to
    118 Hz, which is what a schedule of the filters is for.

    Args:
        drive: the drive the feed-forward is computed for (default :func:`fdjax.reference_drive`).
        servo: its servo (default :func:`reference_servo`).
    """
    if drive is None:
        drive = reference_drive()
    _, k_ffa = _rigid_feedforward(drive, servo, "reference_controller")
    return DoubleLoop(200.0, 5400.0, 60.0, k_ffv=1.0, k_ffa=k_ffa, mcm=reference_mcm())


def reference_pid(*, k_ffv: Float[ArrayLike, ""] = 0.0,
                  k_ffa: Float[ArrayLike, ""] = 0.0) -> PIDLoop:
    r"""The PID of Figs. 16 and 18: the default :class:`fdjax.PIDLoop` gains × 6.2,

        C_pid(s) = 6.2 (k_p + k_i/s + k_d s/(1 + s/ω_d)),   ω_d unchanged,

    all gains scaled together to 6 dB of gain margin at Y_table = 115 mm in the sampled loop,
    as a servo engineer would set it there.  Toward the screw end the saddle's axial mode softens
    and its margin falls to 0.7 dB at 0.7 m.  ``k_ffv`` (A·s/m) and ``k_ffa`` (A·s²/m) are
    the feed-forward gains, e.g. from :func:`rigid_feedforward`.
    """
    k_ffv, k_ffa = (finite(real_scalar(v, f"reference_pid({n}=...)"), f"reference_pid({n}=...)")
                    for n, v in (("k_ffv", k_ffv), ("k_ffa", k_ffa)))
    base = PIDLoop()
    s = 6.2
    return PIDLoop(s * base.kp, s * base.ki, s * base.kd, base.wd, k_ffv=k_ffv, k_ffa=k_ffa)


def rigid_feedforward(
    drive: BallScrewDrive, servo: Servo | None = None
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    r"""Feed-forward of the rigid drive: the current that makes a rigid drive follow r exactly.

    A rigid drive turns as θ1 = x/i_sc under J_eq θ̈1 + c_eq θ̇1 = T1 = k_m u, so

        u_ff = (c_eq ṙ + J_eq r̈) / (k_m i_sc),   k_ffv = c_eq/(k_m i_sc),  k_ffa = J_eq/(k_m i_sc),

    with J_eq and c_eq the inertia and viscous damping reflected to the motor
    (:meth:`fdjax.BallScrewDrive.reflected_inertia`, ``reflected_damping``: rotor and hubs, the
    screw in torsion, the table through m·i_sc²), i_sc = lead/2π and k_m the servo's motor gain.

    Both gains are a :class:`fdjax.PIDLoop`'s (its ``k_ffv`` is in A·s/m).  A
    :class:`fdjax.DoubleLoop` takes ``k_ffa`` alone: its ``k_ffv`` is the dimensionless velocity
    feed-forward into its speed loop (1 = full).  Differentiable in the drive's and the servo's
    leaves.

    Args:
        drive: the drive.
        servo: its servo (default: :func:`reference_servo`).

    Returns:
        (k_ffv in A·s/m, k_ffa in A·s²/m).
    """
    return _rigid_feedforward(drive, servo, "rigid_feedforward")


def _rigid_feedforward(drive, servo, fn: str):
    """:func:`rigid_feedforward`, its arguments named as those of ``fn``, the function the
    user called."""
    instance(drive, BallScrewDrive, f"{fn}(drive=...)")
    if servo is None:
        servo = reference_servo()
    instance(servo, Servo, f"{fn}(servo=...)")
    scale = servo.k_motor * jnp.asarray(drive.screw.ratio)
    return drive.reflected_damping() / scale, drive.reflected_inertia() / scale
