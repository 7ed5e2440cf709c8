r"""Smooth robustness penalties of an open loop on a frequency grid, for gradient tuning.

The exact margins (:func:`fdjax.loop_margins`) are picked from crossings: a crossing that
appears or disappears makes them jump, and they are infinite where there is none, so a penalty
built on them is discontinuous and can blind the optimiser.  Here each requirement is a
forbidden set of the Nyquist plane that the open loop L(e^{iωT}) must keep away from, measured
by a smooth minimum of a distance over the grid:

* modulus margin m: |1 + L| ≥ m, i.e. L outside the disc of radius m around −1
  (sensitivity peak ‖S‖∞ ≤ 1/m; m = 0.5 is the 6 dB sensitivity peak);
* gain margin g (dB): no crossing of the negative real axis at 10^{−g/20} ≤ |L| ≤ 10^{g/20},
  i.e. L off the segment [−10^{g/20}, −10^{−g/20}] (a gain change by a factor within
  10^{±g/20} cannot destabilise the loop; a crossing at |L| > 10^{g/20}, that of a
  conditionally stable loop's low frequencies, is a gain-reduction margin above g, as
  :func:`fdjax.stability_margins` counts it);
* phase margin φ: no unit-gain crossing within φ of −1, i.e. L off the arc
  {e^{iθ} : |θ − π| ≤ φ}.

The smooth minimum over the grid is −(1/β) log Σ_k exp(−β d_k) ≤ min_k d_k, below the true
minimum by at most (log n)/β; each penalty is softplus((d_req − d̃)/w)², zero-ish when the
requirement holds with room, growing quadratically when it fails, finite and differentiable for
any L (the grid must resolve the loop's resonances, as for the exact margins).

The modulus term's set is a disc: its distance grows with the violation, and on the tuning
grid (400 frequencies) the smooth minimum is within about 1 % of the exact modulus margin of
the shipped designs.  The gain and phase sets are a segment and an arc: their distances say
how near the loop passes, not how deep it crosses, so each term saturates near
softplus(1/4 + log(n)/(βw))² whatever the violation, and a crossing between two grid points
of a coarse grid can go unseen (the fixed MCM tuned at 115 mm, at 0.7 m: exact gain margin
5.79 dB, gain term 0.032 on the 400 frequencies at w = 0.01, 0.56 on 4000).  With the default
requirements a modulus margin of 0.5 already implies GM ≥ 6.02 dB and PM ≥ 28.96°, so the
modulus term carries the robustness; stricter gain or phase requirements are held only
approximately by these terms.  Final designs are checked with the exact margins
(:func:`fdjax.loop_margins`, :func:`fdjax.certify`).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from .. import _checks

__all__ = ["soft_min", "modulus_distance", "gain_distance", "phase_distance", "margin_penalty"]


MARGIN_REQUIREMENTS = (
    ("modulus_margin", lambda v: 0 < v <= 1, "in (0, 1] (|1 + L| → 1 at high frequency)"),
    ("gain_margin_db", lambda v: v >= 0, "finite and non-negative (dB)"),
    ("phase_margin_deg", lambda v: 0 <= v < 180, "in [0, 180) degrees"),
)
"""The margin requirements an objective and a certificate take: (name, test, expected)."""


def grid_below_nyquist(freq_hz, servo, where: str) -> np.ndarray:
    """A margins' grid (Hz) as the sampled loop of ``servo`` needs it: 1-D, positive, strictly
    increasing, below the servo's Nyquist frequency; ``where`` names the caller's argument."""
    top = 0.5 / float(servo.period)
    f = np.asarray(_checks.frequency_grid(freq_hz, where), float)
    _checks.check(f, lambda v: v < top, where, f"below the servo's Nyquist frequency {top:.6g} "
                  "Hz (the margins are those of the sampled loop)")
    return f


def soft_min(d: Float[ArrayLike, "*batch freq"], beta: float) -> Float[Array, "*batch"]:
    r"""Smooth minimum over the last axis, −(1/β) log Σ_k e^{−β d_k}: at most min d, and above
    min d − (log n)/β.  β finite and positive (checked under ``jit`` too)."""
    return _soft_min(d, _checks.positive(_checks.real_scalar(beta, "soft_min(beta=...)"),
                                         "soft_min(beta=...)"))


def _soft_min(d, beta):
    # Far from −1 (β min d > 1e4, where the penalties are zero to underflow) about the row's
    # minimum m: m − (1/β) log Σ e^{−β(d − m)}, so that no exponent is large.  Unshifted there,
    # a loop with |L| ~ 1e27 (gains e^30 above a design's) gave −∞ and a NaN gradient under
    # XLA:CPU's jit; elsewhere the shift is 0 and the arithmetic is the plain formula's.
    d = jnp.asarray(d)
    m = jax.lax.stop_gradient(jnp.min(d, axis=-1, keepdims=True))
    shift = jnp.where(beta * m > 1e4, m, 0.0)
    return shift[..., 0] - jax.nn.logsumexp(-beta * (d - shift), axis=-1) / beta


def modulus_distance(L: Complex[ArrayLike, "*batch freq"]) -> Float[Array, "*batch freq"]:
    """|1 + L|: the distance from −1 (its minimum over ω is the modulus margin)."""
    return jnp.abs(1.0 + jnp.asarray(L))


def _segment_distance(x, y, a, b):
    """Distance of (x, y) from the segment {(−t, 0): a ≤ t ≤ b}."""
    dx = x - jnp.clip(x, -b, -a)  # beyond either end: the distance to that end point
    return jnp.sqrt(dx * dx + y * y + 1e-300)


def gain_distance(
    L: Complex[ArrayLike, "*batch freq"], gain_margin_db: float
) -> Float[Array, "*batch freq"]:
    r"""Distance of L from the segment [−1/a, −a] of the negative real axis, a = 10^{−g/20}:
    zero where the Nyquist curve crosses the negative real axis with a gain margin below
    g dB, up or down (a crossing at |L| = r is destabilised by the gain factor 1/r)."""
    L = jnp.asarray(L)
    a = 10.0 ** (-gain_margin_db / 20.0)
    return _segment_distance(L.real, L.imag, a, 1.0 / a)


def phase_distance(
    L: Complex[ArrayLike, "*batch freq"], phase_margin_deg: float
) -> Float[Array, "*batch freq"]:
    r"""Distance of L from the arc {e^{iθ} : |θ − π| ≤ φ} of the unit circle: zero where the
    loop crosses unit gain with a phase margin below φ."""
    L = jnp.asarray(L)
    phi = math.radians(phase_margin_deg)
    r = jnp.abs(L)
    # angle of L measured from the negative real axis, in [0, π]
    theta = jnp.abs(jnp.angle(-L))
    # inside the arc's sector the nearest point is the radial projection; outside, an end point
    ends = (-math.cos(phi) + 1j * math.sin(phi), -math.cos(phi) - 1j * math.sin(phi))
    end = jnp.minimum(jnp.abs(L - ends[0]), jnp.abs(L - ends[1]))
    return jnp.where(theta <= phi, jnp.abs(r - 1.0), end)


def margin_penalty(
    L: Complex[ArrayLike, "*batch freq"],
    *,
    modulus_margin: float = 0.5,
    gain_margin_db: float = 6.0,
    phase_margin_deg: float = 30.0,
    beta: float = 200.0,
    width: float = 0.05,
) -> Float[Array, "*batch"]:
    r"""Sum of the three smooth penalties (module docstring) of an open loop L on a grid:

        P = Σ_j softplus((d_j − d̃_j)/w)²,

    d̃_j the smooth minimum of the j-th distance over the grid and d_j its requirement: the
    modulus margin m for |1 + L|, and a clearance of w/4 from the gain-margin segment and the
    phase-margin arc (zero distance is the violation there).  ``beta`` sets the smooth
    minimum's sharpness (error ≤ log(n)/β), ``width`` w the penalty's scale: both finite and
    positive (checked under ``jit`` too); the requirements are numbers (modulus margin in
    (0, 1], gain margin ≥ 0 dB, phase margin in [0°, 180°)).
    """
    fn = "margin_penalty"
    given = {"modulus_margin": modulus_margin, "gain_margin_db": gain_margin_db,
             "phase_margin_deg": phase_margin_deg}
    for name, ok, expected in MARGIN_REQUIREMENTS:
        _checks.static_number(given[name], f"{fn}({name}=...)", ok, expected)
    beta, width = (_checks.positive(_checks.real_scalar(v, f"{fn}({name}=...)"),
                                    f"{fn}({name}=...)")
                   for name, v in (("beta", beta), ("width", width)))
    L = _checks.numeric(L, f"{fn}(L=...)")
    if L.ndim < 1 or L.shape[-1] < 1:
        raise ValueError(f"`{fn}(L=...)` must be the open loop on a frequency grid (its last "
                         f"axis), got shape {L.shape}")
    L = _checks.finite(L, f"{fn}(L=...)")
    return penalty(L, modulus_margin, gain_margin_db, phase_margin_deg, beta, width)


def penalty(L, modulus_margin, gain_margin_db, phase_margin_deg, beta, width):
    """:func:`margin_penalty` without its checks: for :class:`fdjax.Objective`, whose settings
    were checked where it was built (its requirements are static, its β and w leaves)."""
    L = jnp.asarray(L)
    terms = (
        (modulus_distance(L), modulus_margin),
        (gain_distance(L, gain_margin_db), width / 4),
        (phase_distance(L, phase_margin_deg), width / 4),
    )
    return sum(jax.nn.softplus((req - _soft_min(d, beta)) / width) ** 2 for d, req in terms)
