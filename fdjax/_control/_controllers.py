r"""Controllers: each one's law written once, as an LTI map from the loop's signals to the
current command (paper Fig. 13).

The signals a feed-drive controller reads are

    w = (r, ṙ, r̈, x2, v_m)     (:data:`LAW_SIGNALS`)

— the reference position, velocity and acceleration (m, m/s, m/s²), the linear scale x2 (m) and
the motor speed in linear units v_m = i_sc θ̇1 (m/s; the servo forms it from the encoder) — and
its output is the current command u (A).  A controller's :meth:`~AbstractController.law` is a
sum of *paths*, each a linear combination of the signals passed through a chain of SISO blocks
(:mod:`fdjax._control._blocks`):

    u = Σ_p G_p,1(s) ⋯ G_p,k(s) · (Σ_j g_pj w_j).

From the law alone follow the exact-delay open loops, the continuous closed loop (delay as a
Padé approximant) and the sampled closed loop (each block discretised as the servo runs it):
:mod:`fdjax._control._interconnect`.  A new controller is one subclass with ``law``; a
scheduled controller's law depends on the table position it is asked at.

Controllers hold tunable leaves only (gains as logarithms, filters); the hardware (period,
delay, motor constant) is a :class:`fdjax.Servo`, the screw ratio the drive's.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .. import _checks
from .._filters import MCM, AbstractFilter
from .._lti import LTI, series
from ._blocks import PI, PID, AbstractBlock, as_block
from ._servo import REFERENCE_K_MOTOR

__all__ = ["AbstractController", "DoubleLoop", "PIDLoop", "Path", "Law", "SampledLaw",
           "LAW_SIGNALS"]

LAW_SIGNALS = ("r", "r_dot", "r_ddot", "x2", "v_m")
"""Inputs of a controller's law: reference position (m), velocity (m/s), acceleration (m/s²),
the scale position x2 (m) and the motor speed in linear units v_m = i_sc θ̇1 (m/s)."""

_TWO_PI = 2.0 * math.pi
# The reference drive's screw ratio and reflected inertia, for the default acceleration
# feed-forward (a rigid drive needs k_ffa = J_eq/(k_m i_sc)).
_I_SC_REF = 0.010 / _TWO_PI  # m/rad: 10 mm lead (63×10 screw)
_J_EQ_REF = 1.30769e-2  # kg·m²: rotor + hubs + screw torsion + saddle reflected (m i_sc²)


class Path(eqx.Module):
    """One path of a law: ``blocks`` in series applied to Σ_j gains[j]·w_j.

    Attributes:
        gains: signal name (one of :data:`LAW_SIGNALS`) → gain; the names are static (which
            signals a controller reads is part of its structure), the gains are leaves.
        blocks: SISO blocks applied in order (first to last); empty for a static gain.
    """

    gains: dict[str, Array]
    blocks: tuple[AbstractBlock, ...] = ()

    def __init__(self, gains: dict, blocks=()):
        for name in gains:
            if name not in LAW_SIGNALS:
                raise ValueError(
                    f"`Path(gains=...)` keys must be among {LAW_SIGNALS}, got {name!r}"
                )
        self.gains = {k: _checks.finite_scalar(v, f"Path(gains[{k!r}]=...)")
                      for k, v in gains.items()}
        self.blocks = tuple(as_block(b, "Path(blocks=...)") for b in blocks)

    def row(self) -> Float[Array, " 5"]:
        """The gains as a row over :data:`LAW_SIGNALS`."""
        r = jnp.zeros(len(LAW_SIGNALS), jnp.float64)
        for name, g in self.gains.items():
            r = r.at[LAW_SIGNALS.index(name)].add(g)
        return r


class Law(eqx.Module):
    """u = Σ over ``paths``: a controller's law (module docstring)."""

    paths: tuple[Path, ...]

    def __check_init__(self):
        paths = self.paths
        if not (isinstance(paths, tuple | list) and paths
                and all(isinstance(p, Path) for p in paths)):
            got = (f"{type(paths).__name__} of {len(paths)}" if isinstance(paths, tuple | list)
                   else type(paths).__name__)
            raise ValueError("`Law(paths=...)` must be a non-empty tuple of fdjax.Path (the "
                             f"law's signal paths), got {got}"
                             + (": " + ", ".join(type(p).__name__ for p in paths)
                                if isinstance(paths, tuple | list) and paths else ""))

    def reads(self, signal: str) -> bool:
        """Whether the law reads ``signal`` (static: from the paths' structure)."""
        return any(signal in p.gains for p in self.paths)

    def transfer(self, s) -> Array:
        """K(s), shape (*s.shape, 5): the law's response from each signal to u."""
        return _response([p.row() for p in self.paths],
                         [[b.transfer for b in p.blocks] for p in self.paths], s)

    def realisation(self) -> LTI:
        """The continuous law as one LTI from w to u (each path's chain of blocks, in series,
        side by side)."""
        return _realise([p.row() for p in self.paths],
                        [[b.continuous() for b in p.blocks] for p in self.paths], None)

    def discretised(self, period, filter_method: str = "fitted") -> SampledLaw:
        """The law as the servo runs it at period T: every block discretised once
        (:meth:`fdjax.AbstractBlock.discretised`)."""
        return SampledLaw(
            tuple(p.row() for p in self.paths),
            tuple(tuple(b.discretised(period, filter_method) for b in p.blocks)
                  for p in self.paths),
            jnp.asarray(period, jnp.float64),
        )

    def discrete_transfer(self, z, period, filter_method: str) -> Array:
        """K_d(z), shape (*z.shape, 5): the sampled law's response."""
        return self.discretised(period, filter_method).transfer(z)


class SampledLaw(eqx.Module):
    r"""A law with each block discretised as the servo runs it: per path, the signal row and
    the blocks' discrete elements.  The sampled loop's realisation (:meth:`realisation`) and the
    open loops' response K_d(z) = Σ_p G_p,1(z) ⋯ G_p,k(z) · row_p (:meth:`transfer`, each
    element's own response, e.g. a filter's sections in closed form: no solve with the law's
    whole state matrix) come from the same elements."""

    rows: tuple[Array, ...]
    elements: tuple[tuple, ...]
    period: Array

    def realisation(self) -> LTI:
        """The discrete law as one LTI from w to u."""
        return _realise(self.rows, [[e.state_space() for e in es] for es in self.elements],
                        self.period)

    def transfer(self, z) -> Array:
        """K_d(z), shape (*z.shape, 5)."""
        return _response(self.rows, [[e.transfer for e in es] for es in self.elements], z)


def _response(rows, chains, x) -> Array:
    """Σ_p Π_b G_p,b(x) · row_p, shape (*x.shape, 5), from each block's response function."""
    x = jnp.asarray(x)
    out = 0.0
    for row, chain in zip(rows, chains):
        g = jnp.ones(x.shape, jnp.complex128)
        for response in chain:
            g = g * response(x)
        out = out + g[..., None] * row.astype(jnp.complex128)
    return out


def _realise(rows, chains, dt) -> LTI:
    """Σ over paths of (chain in series)(row · w) as one LTI from w to u: the paths' states
    side by side."""
    parts = []
    for row, chain in zip(rows, chains):
        row = row[None, :]
        if not chain:
            parts.append((jnp.zeros((0, 0)), jnp.zeros((0, len(LAW_SIGNALS))),
                          jnp.zeros((1, 0)), row))
            continue
        lti = chain[0]
        for b in chain[1:]:
            lti = series(lti, b)
        parts.append((lti.A, lti.B @ row, lti.C, lti.D @ row))
    n = sum(x[0].shape[0] for x in parts)
    A = jnp.zeros((n, n), jnp.float64)
    i = 0
    for x in parts:
        k = x[0].shape[0]
        A = A.at[i:i + k, i:i + k].set(x[0])
        i += k
    B = jnp.concatenate([x[1] for x in parts], 0)
    C = jnp.concatenate([x[2] for x in parts], 1)
    D = sum(x[3] for x in parts)
    return LTI(A, B, C, D, None if dt is None else jnp.asarray(dt, jnp.float64))


class AbstractController(eqx.Module):
    r"""A feed-drive controller: its law maps (r, ṙ, r̈, x2, v_m) to the current command.

    Subclasses implement :meth:`law`; everything else — open loops (:func:`fdjax.open_loop`),
    margins of the continuous and of the sampled loop (:func:`fdjax.loop_margins`), closed
    loops (:func:`fdjax.closed_loop`), stability (:func:`fdjax.check_stability`) and both
    simulations (:func:`fdjax.simulate`) — follows from it.  Hold tunable leaves only; the
    hardware is a :class:`fdjax.Servo`.
    """

    @abc.abstractmethod
    def law(self, position_m: Float[Array, ""]) -> Law:
        """The law at table position ``position_m`` (m; a fixed controller ignores it)."""

    def check_position(self, position_m: Float[ArrayLike, ""] | None, where: str):
        """The table positions (m) the controller is asked to run at, checked: a fixed
        controller runs anywhere and returns them as they are; a scheduled one checks them
        against the positions it was built for (eagerly where they are concrete, naming
        ``where``, the caller's argument) and requires them (``None`` is refused)."""
        return position_m

    @property
    def highest_frequency_hz(self) -> float | None:
        """The highest filter frequency (Hz) the controller may take at any position, where
        its filters are bounded by construction (a schedule's :class:`fdjax.MCMBounds`): the
        servo that runs it must sample it, which :func:`fdjax.certify` and
        :func:`fdjax.evaluate` check before they compile.  None (default): a fixed
        controller's filters are checked where they are discretised."""
        return None

    def fixed_at(self, positions_m: Float[ArrayLike, " n"]) -> AbstractController:
        """The fixed controllers this one runs at ``positions_m`` (m, 1-D), stacked along a
        leading axis: itself repeated for a fixed controller, a scheduled one's controller at
        each position.  One compiled program of the stacked controllers' kind then serves
        every controller that runs as that kind (:func:`fdjax.certify`, :func:`fdjax.evaluate`)."""
        y = jnp.asarray(positions_m, jnp.float64)
        arrays, static = eqx.partition(self, eqx.is_array)
        arrays = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, y.shape + x.shape), arrays)
        return eqx.combine(arrays, static)


def _log_positive(value, where: str) -> Array:
    return jnp.log(_checks.positive(_checks.real_scalar(value, where), where))


def _finite(value, where: str) -> Array:
    return _checks.finite(_checks.real_scalar(value, where), where)


class DoubleLoop(AbstractController):
    r"""The nested double loop of paper Fig. 13: P position loop on the linear scale x2 outside,
    PI speed loop on the motor inside, MCM on the speed controller's output, feed-forward.

        v_cmd = k_p (r − x2) + k_ffv ṙ,      v_m = i_sc θ̇1,
        u = G_MCM(s) k_v (1 + k_i/s) (v_cmd − v_m) + k_ffa r̈,      T1 = k_m e^{−sτ} u.

    Units: u is a current command (A), so k_v is in A·s/m and k_ffa in A·s²/m; k_p and k_i in
    1/s (k_i is the PI corner frequency, rad/s); k_ffv is dimensionless (1 = full velocity
    feed-forward).  The ideal acceleration feed-forward of a rigid drive is
    k_ffa = J_eq/(k_m i_sc), J_eq the inertia reflected to the motor.

    Defaults: hand-set for :func:`fdjax.reference_drive` and the reference :class:`fdjax.Servo`
    (τ = 250 µs: two periods at 8 kHz) with an identity MCM, stable at every table position
    0.1–0.7 m with 8 dB of gain margin.  They are soft on purpose: without a notch the drive's
    lightly damped 1260 Hz torsional mode allows no k_v above ≈ 375 A·s/m;
    :func:`fdjax.reference_controller` is the tuned loop with its MCM.

    Positivity by parameterisation: the gains k_p, k_v, k_i are stored as their logarithms
    (``log_kp``, ``log_kv``, ``log_ki``), so any gradient step keeps them positive; the physical
    values are properties.  The feed-forward gains are free reals.  ``eqx.filter_grad`` gives
    gradients on the stored leaves (``g.log_kp = k_p ∂/∂k_p``) and on the MCM's;
    ``jax.grad(lambda p: f(DoubleLoop(**p)))(loop.params())`` gives them in physical units.

    Attributes (arguments of the constructor):
        kp: outer position gain (1/s).
        kv: speed-loop proportional gain (A·s/m).
        ki: speed-loop integral corner (rad/s).
        k_ffv: velocity feed-forward (–).
        k_ffa: acceleration feed-forward (A·s²/m).
        mcm: the modal characteristic modifier (:class:`fdjax.MCM`, or any filter), acting on
            the speed controller's output; ``MCM()`` is the identity.
    """

    log_kp: Float[Array, ""]
    log_kv: Float[Array, ""]
    log_ki: Float[Array, ""]
    k_ffv: Float[Array, ""]
    k_ffa: Float[Array, ""]
    mcm: AbstractFilter

    def __init__(
        self,
        kp: ArrayLike = 10.0,
        kv: ArrayLike = 150.0,
        ki: ArrayLike = 10.0,
        *,
        k_ffv: ArrayLike = 1.0,
        k_ffa: ArrayLike = _J_EQ_REF / (REFERENCE_K_MOTOR * _I_SC_REF),
        mcm: AbstractFilter | None = None,
    ):
        if mcm is None:
            mcm = MCM()
        _checks.instance(mcm, AbstractFilter, "DoubleLoop(mcm=...)",
                         "an fdjax.MCM (or another fdjax filter)")
        self.log_kp = _log_positive(kp, "DoubleLoop(kp=...)")
        self.log_kv = _log_positive(kv, "DoubleLoop(kv=...)")
        self.log_ki = _log_positive(ki, "DoubleLoop(ki=...)")
        self.k_ffv = _finite(k_ffv, "DoubleLoop(k_ffv=...)")
        self.k_ffa = _finite(k_ffa, "DoubleLoop(k_ffa=...)")
        self.mcm = mcm

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
            kp=self.kp, kv=self.kv, ki=self.ki, k_ffv=self.k_ffv, k_ffa=self.k_ffa, mcm=self.mcm
        )

    def law(self, position_m: Float[ArrayLike, ""] | None = None) -> Law:
        """u = G_MCM C_v (k_p r + k_ffv ṙ − k_p x2 − v_m) + k_ffa r̈."""
        kp = self.kp
        speed = Path(
            {"r": kp, "r_dot": self.k_ffv, "x2": -kp, "v_m": -jnp.ones(())},
            (PI(self.kv, self.ki), self.mcm),
        )
        return Law((speed, Path({"r_ddot": self.k_ffa})))


class PIDLoop(AbstractController):
    r"""The paper's baseline: one PID position loop on the linear scale x2 (Figs. 16, 18).

        u = C_pid(s)(r − x2) + k_ffv ṙ + k_ffa r̈,   C_pid(s) = k_p + k_i/s + k_d s/(1 + s/ω_d),
        T1 = k_m e^{−sτ} u,      L(ω) = C_pid(iω) k_m e^{−iωτ} h_x2,T1(ω).

    Units (u is a current command, A): k_p in A/m, k_i in A/(m·s), k_d in A·s/m, the derivative
    filter corner ω_d in rad/s, k_ffv in A·s/m, k_ffa in A·s²/m.  Gains stored as logarithms
    (``log_kp``, ``log_ki``, ``log_kd``, ``log_wd``; the physical values are properties), so
    each is positive: a PI or PD position loop is a controller of its own, a subclass of
    :class:`fdjax.AbstractController` whose law is a :class:`fdjax.Path` through
    :class:`fdjax.PID` or :class:`fdjax.PI` blocks (which take zero gains).

    Defaults: hand-set for :func:`fdjax.reference_drive` and the reference servo: stable at
    every table position 0.1–0.7 m with 16.6–22.2 dB of gain margin, soft
    (:func:`fdjax.reference_pid` is the tuned baseline).
    """

    log_kp: Float[Array, ""]
    log_ki: Float[Array, ""]
    log_kd: Float[Array, ""]
    log_wd: Float[Array, ""]
    k_ffv: Float[Array, ""]
    k_ffa: Float[Array, ""]

    def __init__(
        self,
        kp: ArrayLike = 1.5e3,
        ki: ArrayLike = 5.0e3,
        kd: ArrayLike = 100.0,
        wd: ArrayLike = _TWO_PI * 150.0,
        *,
        k_ffv: ArrayLike = 0.0,
        k_ffa: ArrayLike = 0.0,
    ):
        self.log_kp = _log_positive(kp, "PIDLoop(kp=...)")
        self.log_ki = _log_positive(ki, "PIDLoop(ki=...)")
        self.log_kd = _log_positive(kd, "PIDLoop(kd=...)")
        self.log_wd = _log_positive(wd, "PIDLoop(wd=...)")
        self.k_ffv = _finite(k_ffv, "PIDLoop(k_ffv=...)")
        self.k_ffa = _finite(k_ffa, "PIDLoop(k_ffa=...)")

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
            kp=self.kp, ki=self.ki, kd=self.kd, wd=self.wd, k_ffv=self.k_ffv, k_ffa=self.k_ffa
        )

    def controller(self, s: ArrayLike):
        """C_pid(s) = k_p + k_i/s + k_d s/(1 + s/ω_d) (A/m) at complex ``s``."""
        return PID(self.kp, self.ki, self.kd, self.wd).transfer(s)

    def law(self, position_m: Float[ArrayLike, ""] | None = None) -> Law:
        """u = C_pid (r − x2) + k_ffv ṙ + k_ffa r̈."""
        one = jnp.ones(())
        pid = Path({"r": one, "x2": -one}, (PID(self.kp, self.ki, self.kd, self.wd),))
        return Law((pid, Path({"r_dot": self.k_ffv, "r_ddot": self.k_ffa})))
