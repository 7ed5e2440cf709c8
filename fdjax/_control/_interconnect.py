r"""From a controller's law to the loop around the plant: open loops, the continuous closed loop
and the sampled closed loop.  One interconnection each, for every controller.

**Plant** (paper Fig. 7): the drive's twin or FRF at one table position, input T1 (and the
disturbance F3), outputs θ1, x2, x3.  The servo turns the current command into torque,
T1 = k_m u(t − τ), and forms the motor speed in linear units v_m = i_sc θ̇1 (i_sc the drive's
screw ratio).  The law (:class:`fdjax.Law`) reads w = (r, ṙ, r̈, x2, v_m).

**Open loops.**  With the law's responses K_x = ∂u/∂x2, K_v = ∂u/∂v_m, the actuator
P = k_m e^{−iωτ} and the plant's channels g_x = x2/T1, g_v = v_m/T1 (negative feedback):

    L_u = −P (K_x g_x + K_v g_v)                 broken at the plant input (all loops),
    L_v = −K_v P g_v                             broken at the speed feedback, x2 loop open,
    L_p = −K_x P g_x / (1 + L_v)                 broken at the scale, speed loop closed.

For the double loop of Fig. 13 (K_v = −G_MCM C_v, K_x = k_p K_v) these are
L_v = C_v G_MCM k_m e^{−iωτ} i_sc iω h_θ1,T1 and L_p = k_p h_x2,T1 C_v G_MCM k_m e^{−iωτ}/(1 + L_v).
**Sampled**: the same formulas on the unit circle z = e^{iωT} with the zero-order-hold plant
G(z) = C (zI − Φ)⁻¹ Γ + D, the backward-difference speed v_m = i_sc (1 − z⁻¹)/T θ1, the
discrete law K_d(z) and P = k_m z^{−d}: the loop as the servo runs it.

**Closed loops.**  Continuous: states (plant, law, Padé delay), the algebraic loop through the
plant's feed-through solved exactly.  Sampled: states (plant, previous encoder angle, discrete
law, d delayed commands), T1_k = k_m u_{k−d}.  Both with inputs (r, ṙ, r̈, F3) and outputs
(θ1, x2, x3, T1).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from .._lti import LTI, transfer, transfer_hessenberg, zoh
from ._blocks import delay_frf, pade_ss
from ._controllers import LAW_SIGNALS, Law, SampledLaw

__all__ = [
    "CLOSED_LOOP_INPUTS",
    "CLOSED_LOOP_OUTPUTS",
    "realise_law",
    "continuous_closed_loop",
    "sampled_closed_loop_matrices",
    "open_loops",
]

CLOSED_LOOP_INPUTS = ("r", "r_dot", "r_ddot", "F3")
"""Inputs of a closed loop: reference position (m), velocity (m/s), acceleration (m/s²) and the
disturbance force at the tool point (N)."""

CLOSED_LOOP_OUTPUTS = ("theta1", "x2", "x3", "T1")
"""Outputs of a closed loop: motor angle (rad), scale and tool-point positions (m), motor
torque (N·m)."""

_NW = len(LAW_SIGNALS)


def _c(x) -> Array:
    return jnp.asarray(x).astype(jnp.complex128)


def realise_law(law: Law, *, period=None, filter_method: str = "fitted") -> LTI:
    """The law as one LTI from w = (r, ṙ, r̈, x2, v_m) to u: continuous (``period`` None) or
    as the servo runs it at ``period`` (each block's own discretisation)."""
    if period is None:
        return law.realisation()
    return law.discretised(period, filter_method).realisation()


class _Rows:
    """Rows over the closed loop's [states…, external inputs (r, ṙ, r̈, F3)]."""

    def __init__(self, sizes: dict[str, int]):
        self.offsets, k = {}, 0
        for name, size in sizes.items():
            self.offsets[name] = (k, size)
            k += size
        self.n = k
        self.width = k + len(CLOSED_LOOP_INPUTS)

    def block(self, name: str, values) -> Array:
        """The rows (m, width) with ``values`` (m, size) at the columns of block ``name``."""
        o, size = self.offsets[name]
        values = jnp.atleast_2d(values)
        out = jnp.zeros((values.shape[0], self.width), jnp.float64)
        return out.at[:, o : o + size].set(values)

    def external(self, name: str) -> Array:
        k = self.n + CLOSED_LOOP_INPUTS.index(name)
        return jnp.zeros((1, self.width), jnp.float64).at[0, k].set(1.0)


def _law_input_rows(R: _Rows, x2, v_m) -> Array:
    """The rows (5, width) of w = (r, ṙ, r̈, x2, v_m)."""
    return jnp.concatenate(
        [R.external("r"), R.external("r_dot"), R.external("r_ddot"), x2, v_m], 0
    )


def continuous_closed_loop(law: Law, plant, k_motor, tau, pade_order: int) -> LTI:
    """The continuous loop (module docstring), the delay as its [n/n] Padé approximant."""
    K = realise_law(law)
    dl = pade_ss(tau, pade_order)
    npl, nk, nd = plant.A.shape[0], K.A.shape[0], dl.A.shape[0]
    R = _Rows({"plant": npl, "law": nk, "delay": nd})
    F3 = R.external("F3")

    # Every signal is (row over [states, inputs]) + (coefficient)·T1; T1 is solved last.
    def out(i):
        return R.block("plant", plant.C[i]) + plant.D[i, 1] * F3, plant.D[i, 0]

    x2, x2_t = out(1)
    v_m = R.block("plant", plant.screw_ratio * plant.C_velocity[0])
    W = _law_input_rows(R, x2, v_m)
    W_t = jnp.zeros((_NW, 1)).at[3, 0].set(x2_t)
    U = R.block("law", K.C) + K.D @ W
    U_t = K.D @ W_t
    # T1 = C_d x_d + D_d k_m u(…, T1)
    rhs = R.block("delay", dl.C) + (dl.D[0, 0] * k_motor) * U
    rhs_t = (dl.D[0, 0] * k_motor) * U_t
    T1 = rhs / (1.0 - rhs_t[0, 0])
    W = W + W_t * T1
    U = U + U_t * T1
    rows = jnp.concatenate(
        [
            R.block("plant", plant.A) + plant.B[:, :1] * T1 + plant.B[:, 1:] * F3,
            R.block("law", K.A) + K.B @ W,
            R.block("delay", dl.A) + dl.B * (k_motor * U),
        ],
        0,
    )
    Y = jnp.concatenate([o + t * T1 for o, t in (out(0), out(1), out(2))] + [T1], 0)
    n = R.n
    return LTI(rows[:, :n], rows[:, n:], Y[:, :n], Y[:, n:], None, plant.position_m)


class SampledParts(eqx.Module):
    """What the sampled loop is built from at one position: the law discretised block by
    block (``sampled``; its realisation K runs in the closed loop, its response in the open
    loops) and the zero-order-hold plant (Φ, Γ) from (T1, F3)."""

    sampled: SampledLaw
    Phi: Array
    Gam: Array

    @classmethod
    def of(cls, law: Law, plant, period, filter_method: str) -> SampledParts:
        h = jnp.asarray(period, jnp.float64)
        Phi, Gam = zoh(plant.A, plant.B, h)
        return cls(law.discretised(h, filter_method), Phi, Gam)

    @property
    def law(self) -> LTI:
        """The discrete law's realisation K."""
        return self.sampled.realisation()


def sampled_closed_loop_matrices(parts: SampledParts, plant, k_motor, period, d: int) -> LTI:
    """The sampled loop (module docstring) as one discrete LTI system."""
    h = jnp.asarray(period, jnp.float64)
    Phi, Gam, K = parts.Phi, parts.Gam, parts.law
    npl, nk = plant.A.shape[0], K.A.shape[0]
    R = _Rows({"plant": npl, "theta": 1, "law": nk, "delay": d})
    T1 = R.block("delay", jnp.zeros((1, d)).at[0, d - 1].set(k_motor))
    F3 = R.external("F3")

    def out(i):
        return R.block("plant", plant.C[i]) + plant.D[i, 0] * T1 + plant.D[i, 1] * F3

    theta, x2 = out(0), out(1)
    v_m = (theta - R.block("theta", jnp.ones((1, 1)))) * (plant.screw_ratio / h)
    W = _law_input_rows(R, x2, v_m)
    U = R.block("law", K.C) + K.D @ W
    shift = R.block("delay", jnp.eye(d - 1, d)) if d > 1 else jnp.zeros((0, R.width))
    rows = jnp.concatenate(
        [
            R.block("plant", Phi) + Gam[:, :1] * T1 + Gam[:, 1:] * F3,
            theta,
            R.block("law", K.A) + K.B @ W,
            U,
            shift,
        ],
        0,
    )
    Y = jnp.concatenate([theta, x2, out(2), T1], 0)
    n = R.n
    return LTI(rows[:, :n], rows[:, n:], Y[:, :n], Y[:, n:], h, plant.position_m)


# ------------------------------------------------------------------------------------ open loops
class Channels(eqx.Module):
    """The plant's two channels at the evaluation points: g_x = x2/T1, g_v = v_m/T1."""

    g_x: Array
    g_v: Array


def continuous_channels(plant, omega) -> Channels:
    """g_x = C_x2 (iωI − A)⁻¹ B_T1 + D, g_v = i_sc C_θ̇1 (iωI − A)⁻¹ B_T1 of the twin."""
    s = _c(omega) * 1j
    Cm = jnp.stack([plant.C_velocity[0], plant.C[1]])
    Dm = jnp.stack([jnp.zeros(()), plant.D[1, 0]]).reshape(2, 1)
    G = transfer(plant.A, plant.B[:, :1], Cm, Dm, s)[..., 0]
    return Channels(g_x=G[..., 1], g_v=_c(plant.screw_ratio) * G[..., 0])


def frf_channels(H, omega, screw_ratio) -> Channels:
    """Channels from an FRF array H (..., freq, 3, 2): g_v = i_sc iω h_θ1,T1."""
    s = _c(omega) * 1j
    return Channels(g_x=H[..., 1, 0], g_v=_c(screw_ratio) * s * H[..., 0, 0])


class SampledPlant(eqx.Module):
    """The zero-order-hold plant from T1 to (θ1, x2) at period T: (Φ, Γ, C, D)."""

    Phi: Array
    Gam: Array
    C: Array
    D: Array
    screw_ratio: Array
    period: Array

    @classmethod
    def of(cls, parts: SampledParts, plant, period):
        return cls(parts.Phi, parts.Gam[:, :1], plant.C[:2], plant.D[:2, :1], plant.screw_ratio,
                   jnp.asarray(period, jnp.float64))

    def channels(self, z) -> Channels:
        G = transfer_hessenberg(self.Phi, self.Gam, self.C, self.D, z)[..., 0]
        g_v = _c(self.screw_ratio / self.period) * (1.0 - 1.0 / z) * G[..., 0]
        return Channels(g_x=G[..., 1], g_v=g_v)


def open_loops(K, P, ch: Channels, reads_x: bool, reads_v: bool) -> dict[str, Array | None]:
    """L_u, L_v, L_p (module docstring) from the law's responses K (…, 5), the actuator P and
    the channels; None for a loop the law does not close."""
    Kx = K[..., LAW_SIGNALS.index("x2")] if reads_x else 0.0
    Kv = K[..., LAW_SIGNALS.index("v_m")] if reads_v else 0.0
    L_v = -Kv * P * ch.g_v if reads_v else None
    if reads_x:
        L_p = -Kx * P * ch.g_x
        if reads_v:
            L_p = L_p / (1.0 + L_v)
    else:
        L_p = None
    L_u = -P * (Kx * ch.g_x + Kv * ch.g_v)
    return {"plant_input": L_u, "speed": L_v, "position": L_p}


def continuous_open_loops(law: Law, ch: Channels, omega, k_motor, tau, pade_order):
    s = _c(omega) * 1j
    P = _c(k_motor) * delay_frf(tau, omega, pade_order)
    return open_loops(law.transfer(s), P, ch, law.reads("x2"), law.reads("v_m"))


def sampled_open_loops(law_d: SampledLaw, reads, sp: SampledPlant, omega, k_motor, d: int):
    z = jnp.exp(_c(omega * sp.period) * 1j)
    # the current command from each signal: the discrete blocks' responses, path by path
    K = law_d.transfer(z)
    P = _c(k_motor) * z ** (-d)
    return open_loops(K, P, sp.channels(z), *reads)
