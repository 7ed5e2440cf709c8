r"""The dynamic elements a controller's law is built from: SISO blocks, continuous and
discretisable.

A block is a single-input single-output LTI element with

* ``continuous()``: its realisation in s (an :class:`fdjax.LTI`, B (n, 1), C (1, n), D (1, 1));
* ``discrete(period, filter_method)``: what the servo runs at period T (default: Tustin's rule
  of the continuous realisation; a filter uses its own discretisation, paper Eqs. 3–4);
* ``discretised(period, filter_method)``: that discrete element, holding both its
  realisation (``state_space()``) and its response (``transfer(z)``, a closed form where the
  block has one, e.g. a filter's second-order sections);
* ``transfer(s)`` and ``discrete_transfer(z, period, filter_method)``: its response, exact
  (from the realisation unless a block knows a closed form).

A user's own element (a lead filter, a low-pass) is one subclass with ``continuous()``.
Also here: the control delay e^{−sτ} and its [n/n] Padé approximant.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from .. import _checks
from .._filters import AbstractFilter
from .._lti import LTI, tustin

__all__ = ["AbstractBlock", "DiscreteBlock", "PI", "PID", "FilterBlock", "pade",
           "DEFAULT_PADE_ORDER"]

DEFAULT_PADE_ORDER = 6
"""Default order n of the [n/n] Padé delay of the continuous closed loop.  The approximant is
all-pass; its phase error grows as (ωτ)^{2n+1}: at n = 6 it is 1.3e-9 rad at ωτ = 2 (1.3 kHz at
τ = 250 µs), 2.3e-7 rad at ωτ = 3 and 1.9e-3 rad (0.11°) at ωτ = 6.3, i.e. at 4 kHz, the top of
the twin's default band."""

FILTER_METHODS = ("fitted", "tustin")


def _c(x) -> Array:
    return jnp.asarray(x).astype(jnp.complex128)


def _siso(A, B, C, D, dt=None) -> LTI:
    f = lambda x: jnp.asarray(x, jnp.float64)
    n = jnp.shape(A)[0]
    return LTI(
        f(A).reshape(n, n), f(B).reshape(n, 1), f(C).reshape(1, n), f(D).reshape(1, 1), dt
    )


class DiscreteBlock(eqx.Module):
    """A block as the servo runs it, by its discrete realisation: ``state_space()`` and the
    response ``transfer(z)`` from it (a filter's discrete element is its
    :class:`fdjax.DiscreteFilter`, with the same two methods)."""

    lti: LTI

    def state_space(self) -> LTI:
        """The discrete realisation (A, B (n, 1), C (1, n), D (1, 1), dt)."""
        return self.lti

    def transfer(self, z: Complex[ArrayLike, "*shape"]) -> Complex[Array, "*shape"]:
        """C (zI − A)⁻¹ B + D at complex z of any shape."""
        return self.lti.transfer(z)[..., 0, 0]


class AbstractBlock(eqx.Module):
    """A SISO LTI element of a controller's law (module docstring)."""

    @abc.abstractmethod
    def continuous(self) -> LTI:
        """The realisation in s: B (n, 1), C (1, n), D (1, 1)."""

    def discrete(self, period: Float[Array, ""], filter_method: str = "fitted") -> LTI:
        """The element as the servo runs it at period T: Tustin's rule by default."""
        del filter_method
        return tustin(self.continuous(), period)

    def transfer(self, s: Complex[ArrayLike, "*shape"]) -> Complex[Array, "*shape"]:
        """The response at complex s."""
        return self.continuous().transfer(s)[..., 0, 0]

    def discretised(self, period: Float[Array, ""], filter_method: str = "fitted"):
        """The discrete element (:meth:`discrete`) with its response: an object with
        ``state_space()`` and ``transfer(z)``; what a sampled law is built from (its
        realisation and its open loops' response come from the same discretisation)."""
        return DiscreteBlock(self.discrete(period, filter_method))

    def discrete_transfer(
        self, z: Complex[ArrayLike, "*shape"], period, filter_method: str = "fitted"
    ) -> Complex[Array, "*shape"]:
        """The discrete element's response at complex z."""
        return self.discretised(period, filter_method).transfer(z)


class PI(AbstractBlock):
    r"""C(s) = k_v (1 + k_i/s): a PI speed controller (paper Fig. 13), k_i the corner (rad/s),
    k_v in the units of its output per input (A·s/m in :class:`fdjax.DoubleLoop`: current per
    speed error)."""

    kv: Float[Array, ""] = _checks.finite_scalar_field("PI(kv=...)")
    ki: Float[Array, ""] = _checks.finite_scalar_field("PI(ki=...)")

    def continuous(self) -> LTI:
        return _siso(jnp.zeros((1, 1)), jnp.ones((1, 1)), self.kv * self.ki, self.kv)

    def transfer(self, s):
        s = _c(s)
        return (s + _c(self.ki)) / s * _c(self.kv)


class PID(AbstractBlock):
    r"""C(s) = k_p + k_i/s + k_d s/(1 + s/ω_d): a PID with a first-order derivative filter,
    ω_d > 0 its corner (rad/s); the gains in the units of the output per input (A/m, A/(m·s),
    A·s/m in :class:`fdjax.PIDLoop`: current per position error).

    Realised with the integrator z and the derivative filter's state x_d
    (ẋ_d = −ω_d x_d + e): k_d s/(1 + s/ω_d) = k_d ω_d (1 − ω_d/(s + ω_d))."""

    kp: Float[Array, ""] = _checks.finite_scalar_field("PID(kp=...)")
    ki: Float[Array, ""] = _checks.finite_scalar_field("PID(ki=...)")
    kd: Float[Array, ""] = _checks.finite_scalar_field("PID(kd=...)")
    wd: Float[Array, ""] = _checks.finite_scalar_field("PID(wd=...)")

    def __check_init__(self):
        # the derivative filter's corner: its pole −ω_d must be stable
        if _checks.is_concrete(self.wd) and not float(self.wd) > 0:
            raise ValueError(f"`PID(wd=...)` must be positive (the derivative filter's corner, "
                             f"rad/s), got {float(self.wd):.6g}")

    @property
    def _corner(self):
        """ω_d, checked positive also where it is traced (a law built inside ``jit`` from a
        controller's leaves, where the constructor's check cannot run)."""
        return eqx.error_if(self.wd, ~(self.wd > 0), "`PID(wd=...)` must be positive (the "
                            "derivative filter's corner, rad/s)")

    def continuous(self) -> LTI:
        kd, wd = self.kd, self._corner
        return _siso(
            jnp.diag(jnp.stack([jnp.zeros(()), -wd])),
            jnp.ones((2, 1)),
            jnp.stack([self.ki, -kd * wd * wd]),
            self.kp + kd * wd,
        )

    def transfer(self, s):
        s = _c(s)
        return _c(self.kp) + _c(self.ki) / s + _c(self.kd) * s / (1.0 + s / _c(self._corner))


class FilterBlock(AbstractBlock):
    """A filter of paper Eqs. (3)–(4) (:class:`fdjax.MCM`, peak or notch) as a block: its own
    realisation, its exact response, and its discretisation (:meth:`fdjax.MCM.discretize`)."""

    filter: AbstractFilter

    def continuous(self) -> LTI:
        return self.filter.state_space()

    def discrete(self, period, filter_method: str = "fitted") -> LTI:
        return self.discretised(period, filter_method).state_space()

    def discretised(self, period, filter_method: str = "fitted"):
        # the discrete filter itself: its response is its sections' closed form
        return self.filter.discretize(period, filter_method)

    def transfer(self, s):
        return self.filter.transfer(s)


def as_block(x, where: str) -> AbstractBlock:
    """A block, or a filter wrapped as one."""
    if isinstance(x, AbstractBlock):
        return x
    if isinstance(x, AbstractFilter):
        return FilterBlock(x)
    raise TypeError(
        f"`{where}` must hold fdjax blocks (AbstractBlock) or filters (MCM, PeakFilter, "
        f"NotchFilter), got {type(x).__name__}"
    )


# ------------------------------------------------------------------------------------ delay
def _pade_coefficients(order: int) -> np.ndarray:
    """c_k = (2n − k)! n! / ((2n)! k! (n − k)!), k = 0 … n: Q_n(x) = Σ c_k x^k."""
    n = order
    f = math.factorial
    return np.array([f(2 * n - k) * f(n) / (f(2 * n) * f(k) * f(n - k)) for k in range(n + 1)])


def delay_frf(tau, omega, pade_order: int | None):
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


def pade_order(order, where: str) -> int:
    """Validate a static Padé order in [1, 16]."""
    return _checks.static_int(order, where, 1, 16)


def pade(tau: Float[ArrayLike, ""], order: int) -> LTI:
    r"""State-space realisation of the [n/n] Padé approximant of the delay e^{−sτ}.

        e^{−x} ≈ Q_n(−x)/Q_n(x),   Q_n(x) = Σ_{k=0}^{n} (2n−k)! n! / ((2n)! k! (n−k)!) x^k,
        x = sτ,

    the same approximant as ``control.pade(tau, n)``.  Realised in controllable canonical form
    in the scaled variable y = sτ/ρ with ρ = (c_0/c_n)^{1/n} (the geometric mean of the pole
    magnitudes of Q_n in x), which keeps the companion coefficients O(1) and the realisation
    well conditioned up to order ~12; then A = (ρ/τ)A_y, B = (ρ/τ)B_y, D = (−1)^n.

    Args:
        tau: the delay τ (s), positive.
        order: n in [1, 16] (static).
    """
    n = pade_order(order, "pade(order=...)")
    where = "pade(tau=...)"
    tau = _checks.positive(_checks.real_scalar(tau, where), where)
    if not _checks.is_concrete(tau):  # a servo's delay is micro- to milliseconds
        tau = eqx.error_if(tau, tau > 1.0, f"`{where}` must be a delay in seconds of at most 1 s")
    elif float(tau) > 1.0:
        raise ValueError(f"`{where}` must be a delay in seconds of at most 1 s, got "
                         f"{float(tau):.6g}: in µs? {float(tau):.6g} µs is "
                         f"{float(tau) * 1e-6:.6g} s")
    return pade_ss(tau, n)


def pade_ss(tau, n: int) -> LTI:
    c = _pade_coefficients(n)
    rho = (c[0] / c[n]) ** (1.0 / n)
    a = c * rho ** np.arange(n + 1) / (c[n] * rho**n)  # monic in y: a_n = 1, a_0 = 1
    sign = (-1.0) ** np.arange(n + 1)
    r = a * (sign - (-1.0) ** n)  # numerator minus D·denominator, coefficients of y^k
    A_y = np.zeros((n, n))
    A_y[0, :] = -a[n - 1 :: -1][:n]  # −a_{n−1}, …, −a_0
    A_y[1:, :-1] = np.eye(n - 1)
    scale = rho / tau
    return LTI(
        A=scale * jnp.asarray(A_y),
        B=scale * jnp.asarray(np.eye(n)[:, :1]),
        C=jnp.asarray(r[n - 1 :: -1][:n][None, :]),
        D=jnp.full((1, 1), (-1.0) ** n),
    )
