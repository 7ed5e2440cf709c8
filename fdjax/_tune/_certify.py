r"""Certification of a controller between its design points: stability from the eigenvalues of
the sampled closed loop and the exact sampled margins on a fine grid of table positions (every
1 mm by default), the worst position named.

A gain schedule tuned at design points says nothing about the positions between them; here the
loop is checked where it will run.  At every position Y_k of the grid:

    stable_k   = max |z| < 1 over the sampled closed loop's poles (:func:`fdjax.check_stability`),
    GM_k, PM_k, MM_k = the margins of :func:`fdjax.loop_margins` (sampled loop), the least of
                       the break points (plant input, speed feedback, scale),

and the controller passes when every position is stable with |GM| ≥ GM_min, |PM| ≥ PM_min and
MM ≥ MM_min (gain margin in the log sense: a phase crossover 6 dB away in either direction).
A margin is read from the crossings the frequency grid brackets; a gain crossover below the
grid's lowest frequency would leave its phase margin unread, so a position passes only where
every open loop's gain there is above 1 (|L(f_min)| > 1: the loops' integrators put every gain
crossover above it).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .._analysis import check_stability, loop_margins, open_loop
from .._checks import instance, real_array, static_number
from .._control._controllers import AbstractController
from .._control._servo import Servo
from .._drive._model import BallScrewDrive
from .._drive._twin import TwinOptions, state_space
from .._memory import release
from .._simulation import SampledData, simulate
from .._trajectory import Trajectory
from ._parameterisation import check_sampled_by
from ._penalties import MARGIN_REQUIREMENTS, grid_below_nyquist

__all__ = ["Certificate", "certify"]


class Certificate(eqx.Module):
    """Result of :func:`certify` (NumPy arrays over the positions).

    Attributes:
        positions_m: the grid (m).
        stable: the sampled closed loop is stable at each position.
        growth_rate: growth rate of the least stable pole (1/s; negative when stable).
        gain_margin_db, phase_margin_deg, modulus_margin: the least over the break points (of
            |GM| in dB and |PM| in degrees: a margin below 0 dB or 0° counts by its size).
        requirements: (GM_min dB, PM_min °, MM_min).
        passed: per position, stable with every margin met and the grid below every gain
            crossover.
        low_gain: the least |L| over the break points at the grid's lowest frequency (above 1:
            every gain crossover lies on the grid).
    """

    positions_m: np.ndarray
    stable: np.ndarray
    growth_rate: np.ndarray
    gain_margin_db: np.ndarray
    phase_margin_deg: np.ndarray
    modulus_margin: np.ndarray
    passed: np.ndarray
    requirements: tuple[float, float, float] = eqx.field(static=True)
    low_gain: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        """Every position passes."""
        return bool(np.all(self.passed))

    def worst(self, what: str = "modulus_margin", *,
              stable_only: bool = False) -> tuple[float, float]:
        """(position (m), value) where ``what`` (a margin) is least; an unstable position
        counts as the least of all (the most unstable one, by its growth rate, first), or with
        ``stable_only`` is left out (the margins of an unstable loop mean nothing; NaN where no
        position is stable)."""
        if what not in ("gain_margin_db", "phase_margin_deg", "modulus_margin"):
            raise ValueError("`Certificate.worst(what=...)` must be 'gain_margin_db', "
                             f"'phase_margin_deg' or 'modulus_margin', got {what!r}")
        v = np.abs(np.asarray(getattr(self, what), float))
        if stable_only:
            if not np.any(self.stable):
                return math.nan, math.nan
            v = np.where(self.stable, v, np.inf)
        elif not np.all(self.stable):  # the most unstable position
            g = np.where(self.stable, -np.inf, np.asarray(self.growth_rate, float))
            k = int(np.argmax(g))
            return float(self.positions_m[k]), float(np.asarray(getattr(self, what))[k])
        k = int(np.argmin(v))
        return float(self.positions_m[k]), float(np.asarray(getattr(self, what))[k])

    @property
    def message(self) -> str:
        """One paragraph: passed or failed, where, and the least margins with their positions."""
        gm, pm, mm = self.requirements
        n = self.positions_m.size
        y = np.asarray(self.positions_m)  # in the order given: the span is their range
        span = f"{y.min() * 1e3:.0f}–{y.max() * 1e3:.0f} mm"
        head = (f"certified at {n} positions ({span})" if self.ok else
                f"NOT certified: {int(np.sum(~self.passed))} of {n} positions ({span}) fail")
        parts = [head]
        if not np.all(self.stable):
            bad = np.sort(y[~self.stable])
            g = np.asarray(self.growth_rate, float)
            k = int(np.argmax(np.where(self.stable, -np.inf, g)))
            parts.append(f"unstable at {bad.size} positions, from {bad[0] * 1e3:.0f} mm to "
                         f"{bad[-1] * 1e3:.0f} mm, most at {y[k] * 1e3:.0f} mm (growing at "
                         f"{g[k]:.4g} 1/s)")
        if self.low_gain is not None and not np.all(self.low_gain > 1):
            low = np.sort(y[~(self.low_gain > 1)])
            parts.append(f"the loop gain at the grid's lowest frequency is not above 1 at "
                         f"{low.size} positions, lowest {low[0] * 1e3:.0f} mm (a gain crossover "
                         "below the grid: give freq_hz starting lower)")
        if not np.any(self.stable):
            return "; ".join(parts)
        where = "" if np.all(self.stable) else " where stable"
        for what, label, unit, req in (("gain_margin_db", "gain margin", " dB", gm),
                                       ("phase_margin_deg", "phase margin", "°", pm),
                                       ("modulus_margin", "modulus margin", "", mm)):
            y, v = self.worst(what, stable_only=True)
            parts.append(f"least {label}{where} {v:.3g}{unit} at {y * 1e3:.0f} mm "
                         f"(required {req:g}{unit})")
        return "; ".join(parts)

    def rows(self) -> dict[str, list]:
        """Columns of a CSV or JSON table, one row per position."""
        low = {} if self.low_gain is None else {
            "loop_gain_at_lowest_freq": np.asarray(self.low_gain).tolist()}
        return {"position_mm": (self.positions_m * 1e3).tolist(),
                "stable": self.stable.tolist(), "growth_rate_per_s": self.growth_rate.tolist(),
                "gain_margin_db": self.gain_margin_db.tolist(),
                "phase_margin_deg": self.phase_margin_deg.tolist(),
                "modulus_margin": self.modulus_margin.tolist(), **low,
                "passed": self.passed.tolist()}


def _least(m, attr, absolute=False):
    vals = []
    for loop in (m.plant_input, m.speed, m.position):
        if loop is not None:
            v = getattr(loop, attr)
            vals.append(jnp.abs(v) if absolute else v)
    return jnp.min(jnp.stack(vals), axis=0)


def point_checks(controllers: AbstractController, drive: BallScrewDrive, positions_m, *,
                 servo: Servo, freq_hz, twin: TwinOptions, motion: Trajectory | None = None):
    """For each pair (controller_k, Y_k) of stacked fixed controllers and positions: stability
    (growth rate of the least stable pole), the least margins over the break points and, with
    ``motion``, the RMS scale error of its sampled-data simulation.  Dict of arrays."""
    return _point_checks(controllers, drive, jnp.asarray(positions_m, jnp.float64), servo,
                         jnp.asarray(freq_hz, jnp.float64), twin, motion,
                         None if motion is None else float(motion.duration))


@eqx.filter_jit
def _point_checks(controllers, drive, ys, servo, f, twin, motion, duration):
    def one(args):
        c, y = args
        plant = state_space(drive, y, twin=twin)
        # one discrete law and one zero-order-hold plant for the poles, margins and run
        method = SampledData().sharing(c, plant, servo)
        st = check_stability(c, plant, servo=servo, method=method)
        m = loop_margins(c, plant, f, servo=servo, method=method)
        first = open_loop(c, plant, f[:1], servo=servo, method=method)
        low = jnp.min(jnp.stack([jnp.abs(L[0]) for L in (
            first.plant_input, first.speed, first.position) if L is not None]))
        out = {"growth": st.growth_rate, "stable": st.stable,
               "gm": _least(m, "gain_margin_db", absolute=True),
               "pm": _least(m, "phase_margin_deg", absolute=True),
               "mm": _least(m, "modulus_margin"), "low_gain": low}
        if motion is not None:
            sim = simulate(c, plant, motion, method, servo=servo, duration=duration,
                           throw=False)
            out["rms"] = sim.rms_error("scale")
        return out

    return jax.lax.map(one, (controllers, ys))


def default_grid(servo: Servo) -> np.ndarray:
    """The margins' default frequency grid: 2000 points log-spaced from 5 Hz to 0.995 of the
    servo's Nyquist frequency."""
    return np.geomspace(5.0, 0.995 * 0.5 / float(servo.period), 2000)


MAX_GRID_STEP = 0.05
"""The largest relative step between neighbouring frequencies of a margins' grid: a floor that
refuses grids of a few points, not a guarantee.  The margins are refined between grid points,
so steps wider than a mode's half-width are not in themselves an error: on the reference
drive, whose least damped closed-loop poles have relative half-widths of 0.0043–0.0046, a
300-point grid (2.3 % steps) gives the certificates of the default grid (0.34 % steps) to
3.4e-13 at 61 positions for three of the shipped designs.  A pair of crossings hidden between
two grid points is looked for near a few candidate points only, so where the plant's modes are
lighter or crowded, give a finer grid."""


def check_grid_resolves(fixed: AbstractController, freq_hz: np.ndarray, where: str,
                        remedy: str = "give a grid with points closer than {} Hz around it"
                        ) -> None:
    """Refuse a frequency grid on which a crossing could hide between two points: a step
    between neighbours above :data:`MAX_GRID_STEP`, or one wider than a filter's own relative
    half-width (ξ of a peak filter, ζ_d of a notch) where that filter acts, at any of the
    stacked controllers ``fixed`` (a sharp filter between two grid points is invisible)."""
    f = np.asarray(freq_hz, float)
    step = f[1:] / f[:-1] - 1.0
    k = int(np.argmax(step))
    if step[k] > MAX_GRID_STEP:
        raise ValueError(f"`{where}` must have neighbouring frequencies within "
                         f"{100 * MAX_GRID_STEP:g} % of each other (a crossing between two points "
                         f"is not seen), got {100 * step[k]:.3g} % between {f[k]:.6g} and "
                         f"{f[k + 1]:.6g} Hz")
    mcm = getattr(fixed, "mcm", None)
    for kind, bank, width in (("peak", getattr(mcm, "peak", None), "xi"),
                              ("notch", getattr(mcm, "notch", None), "zeta_d")):
        if bank is None:
            continue
        p = bank.params()
        fc = np.ravel(np.asarray(p["omega"])) / (2 * np.pi)
        w = np.ravel(np.broadcast_to(np.asarray(p[width]), np.shape(p["omega"])))
        j = np.clip(np.searchsorted(f, fc), 1, f.size - 1)
        bad = (fc > f[0]) & (fc < f[-1]) & (step[j - 1] > w)
        if np.any(bad):
            i = int(np.argmax(bad))
            raise ValueError(f"`{where}` must resolve the controller's {kind} filter at "
                             f"{fc[i]:.6g} Hz (relative half-width {w[i]:.3g}), got a step of "
                             f"{100 * step[j[i] - 1]:.3g} % there: "
                             + remedy.format(f"{w[i] * fc[i]:.3g}"))


def certificate(y, checks, gain_margin_db=6.0, phase_margin_deg=30.0,
                modulus_margin=0.5) -> Certificate:
    """A :class:`Certificate` from the arrays of :func:`point_checks`."""
    c = {k: np.asarray(v) for k, v in checks.items()}
    stable = c["stable"].astype(bool)
    passed = (stable & (c["gm"] >= gain_margin_db) & (c["pm"] >= phase_margin_deg)
              & (c["mm"] >= modulus_margin) & (c["low_gain"] > 1))
    return Certificate(np.asarray(y, float), stable, c["growth"], c["gm"], c["pm"], c["mm"],
                       passed, (float(gain_margin_db), float(phase_margin_deg),
                                float(modulus_margin)), c["low_gain"])


def certify(
    controller: AbstractController,
    drive: BallScrewDrive,
    positions_m: Float[ArrayLike, " n"] | None = None,
    *,
    servo: Servo = Servo(),
    freq_hz: Float[ArrayLike, " freq"] | None = None,
    twin: TwinOptions | None = None,
    gain_margin_db: float = 6.0,
    phase_margin_deg: float = 30.0,
    modulus_margin: float = 0.5,
) -> Certificate:
    r"""Stability and the exact sampled margins of ``controller`` on a grid of table positions
    (module docstring); by default every 1 mm over the drive's travel.

    Args:
        controller: any controller (a scheduled one is evaluated at each position).
        drive: the drive.
        positions_m: the grid (m), inside the travel; default every 1 mm.
        servo: the servo hardware.
        freq_hz: the margins' frequency grid, below Nyquist (default :func:`default_grid`),
            fine enough that no crossing hides between two points: neighbours within
            :data:`MAX_GRID_STEP` of each other, and steps narrower than each filter's
            relative half-width where it acts (:func:`check_grid_resolves`).
        twin: how the drive becomes its twin (default: every mode in the twin's band, counted
            over the travel).
        gain_margin_db, phase_margin_deg, modulus_margin: the requirements.
    """
    fn = "certify"
    instance(controller, AbstractController, f"{fn}(controller=...)", "an fdjax controller")
    instance(drive, BallScrewDrive, f"{fn}(drive=...)")
    instance(servo, Servo, f"{fn}(servo=...)")
    if twin is not None:
        instance(twin, TwinOptions, f"{fn}(twin=...)")
    check_sampled_by(controller.highest_frequency_hz, servo, f"{fn}(controller=...)")
    given = {"gain_margin_db": gain_margin_db, "phase_margin_deg": phase_margin_deg,
             "modulus_margin": modulus_margin}
    for name, ok, expected in MARGIN_REQUIREMENTS:
        static_number(given[name], f"{fn}({name}=...)", ok, expected)
    lo, hi = drive.travel_m
    if positions_m is None:
        positions_m = np.linspace(lo, hi, int(round((hi - lo) / 1e-3)) + 1)
    y = np.atleast_1d(np.asarray(real_array(positions_m, f"{fn}(positions_m=...)")))
    if y.ndim != 1 or y.size == 0:
        raise ValueError(f"`{fn}(positions_m=...)` must be a 1-D array of at least one "
                         f"position, got shape {y.shape}")
    y = np.asarray(drive._check_travel(y, fn, "positions_m"))
    y = np.asarray(controller.check_position(y, f"{fn}(positions_m=...)"))
    f = default_grid(servo) if freq_hz is None else grid_below_nyquist(
        freq_hz, servo, f"{fn}(freq_hz=...)")
    twin = (TwinOptions() if twin is None else twin).resolve(drive, fn)
    fixed = controller.fixed_at(y)
    check_grid_resolves(fixed, f, f"{fn}(freq_hz=...)")
    release()
    checks = point_checks(fixed, drive, y, servo=servo, freq_hz=f, twin=twin)
    return certificate(y, checks, gain_margin_db, phase_margin_deg, modulus_margin)
