r"""The reference settings of the paper's closed-loop figures (Figs. 14, 16, 17): the servo, the
hand-set MCM and PID, and the feed-forward of the rigid drive.

These are hand-set starting points (gradient tuning improves on them); :mod:`fdjax.cli`
reproduces the figures with them and the tests pin them, so they live here, once, as functions
of the drive and the servo rather than as numbers copied where they are used.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Float

from .._drive._model import BallScrewDrive
from .._filters import MCM, NotchFilter, PeakFilter
from ._controllers import PIDLoop
from ._servo import REFERENCE_DELAY_SAMPLES, REFERENCE_K_MOTOR, REFERENCE_PERIOD_S, Servo

__all__ = ["reference_servo", "reference_mcm", "reference_pid", "rigid_feedforward"]

_TWO_PI = 2.0 * math.pi


def reference_servo() -> Servo:
    r"""The reference servo of Figs. 14–17: T = 125 µs (8 kHz), d = 2 periods of delay
    (τ = d·T = 250 µs), k_m = k_i·k_T = 1.2 N·m/A.  The same hardware as ``Servo()``."""
    return Servo(period=REFERENCE_PERIOD_S, delay_samples=REFERENCE_DELAY_SAMPLES,
                 k_motor=REFERENCE_K_MOTOR)


def reference_mcm() -> MCM:
    r"""The hand-set MCM of Figs. 14, 16 and 17 for :func:`fdjax.reference_drive`,
    G_MCM = G_pf · G_nf (paper Eqs. (3)–(4)):

    * a peak filter on Table 1's mode 3 (131 Hz at Y_table = 115 mm), K = 0.5, ξ = 0.3,
      φ = −60°: a lobe of height K/(2ξ) ≈ 0.83 that turns the axial mode "in phase" in the
      speed loop;
    * a notch on mode 5 (1508 Hz), ζ_n = 0.05, ζ_d = 0.5: depth ζ_n/ζ_d = 0.1 (−20 dB).
    """
    return MCM(
        PeakFilter(0.5, _TWO_PI * 131.0, 0.3, math.radians(-60.0)),
        NotchFilter(_TWO_PI * 1508.0, 0.05, 0.5),
    )


def reference_pid(*, k_ffv=0.0, k_ffa=0.0) -> PIDLoop:
    r"""The PID of Fig. 16: the default :class:`fdjax.PIDLoop` gains × 3,

        C_pid(s) = 3 (k_p + k_i/s + k_d s/(1 + s/ω_d)),   ω_d unchanged,

    stiffer than the soft default, as a tuned baseline would be: on the reference drive and
    servo its gain margin is ≈ 3 over the travel (2.96–3.08 in the sampled loop, 2.88–3.00 with
    the exact delay; phase crossover at 88–90 Hz).  ``k_ffv`` (A·s/m) and ``k_ffa`` (A·s²/m) are
    the feed-forward gains, e.g. from :func:`rigid_feedforward`.
    """
    base = PIDLoop()
    return PIDLoop(3 * base.kp, 3 * base.ki, 3 * base.kd, base.wd, k_ffv=k_ffv, k_ffa=k_ffa)


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
    if not isinstance(drive, BallScrewDrive):
        raise TypeError(
            f"`rigid_feedforward(drive=...)` must be an fdjax.BallScrewDrive, got "
            f"{type(drive).__name__}"
        )
    if servo is None:
        servo = reference_servo()
    if not isinstance(servo, Servo):
        raise TypeError(
            f"`rigid_feedforward(servo=...)` must be an fdjax.Servo, got {type(servo).__name__}"
        )
    scale = servo.k_motor * jnp.asarray(drive.screw.ratio)
    return drive.reflected_damping() / scale, drive.reflected_inertia() / scale
