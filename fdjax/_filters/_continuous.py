r"""The continuous filters of the modal characteristic modifier (MCM, paper Sec. 4.1).

An MCM is the product of a *peak-filter* part, which bends low and middle modes to "in phase",
and a *notch-filter* part, which removes high modes (paper Eqs. (3) and (4)):

    G_MCM(s) = G_pf(s) · G_nf(s),

    G_pf(s) = 1 + Σ_i K_i · s (s cos φ_i + ω_i sin φ_i) / (s² + 2 ξ_i ω_i s + ω_i²),     Eq. (3)

    G_nf(s) = Π_j (s² + 2 ζ_nj ω_j s + ω_j²) / (s² + 2 ζ_dj ω_j s + ω_j²).                Eq. (4)

The English text of the paper drops one ``s`` from Eq. (3) (it prints
``s(cos φ + ω sin φ)``, which is dimensionally wrong); the form above is the one of the Chinese
edition. Frequencies are in rad/s and phases in rad (SI inside); only
``frf(freq_hz)`` takes Hz.

Each filter says which of its second-order sections are in parallel (the peaks) and which in
series (the notches); :class:`AbstractFilter` evaluates any such filter, realises it
(``state_space()``, an :class:`fdjax._lti.LTI`) and discretises it (``discretize(dt)``, a
:class:`DiscreteFilter`).

**Positivity by parameterisation.** ω, ξ, ζ_n and ζ_d are stored as their logarithms
(``log_omega``, ``log_xi``, ``log_zeta_n``, ``log_zeta_d``); the physical values are properties
(``omega = exp(log_omega)``), so any gradient step on the leaves keeps them positive — nothing is
clipped. K and φ are unconstrained and stored as they are. Two ways to differentiate:

* w.r.t. the Module, e.g. ``eqx.filter_grad(loss)(peak)``: the gradient lives on the stored
  leaves, ``g.log_omega = ω ∂loss/∂ω`` (relative sensitivity), ``g.K = ∂loss/∂K``; this is what
  an optimiser (optax) should update;
* w.r.t. the physical values: differentiate through the constructor,
  ``jax.grad(lambda p: loss(PeakFilter(**p)))(peak.params())``.

``PeakFilter.from_unconstrained(K, log_omega, log_xi, phi)`` (and the notch's) build a filter from
unconstrained reals, e.g. the outputs of the adaptive-tuning network.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float, Inexact

from .._checks import (
    check,
    finite,
    finite_output,
    frequency_grid,
    is_concrete,
    positive,
    real_array,
    real_scalar,
    to_complex,
)
from .._lti import LTI, series
from ._discrete import DiscreteFilter, _fitted_sections, _tustin_prewarped
from ._sections import (
    _Bank,
    _biquad_s,
    _empty_bank,
    _parallel_ss,
    _section_ss,
)


def _real_param(value, where: str) -> Array:
    """A real scalar or 1-D parameter as float64 (shape/dtype facts only)."""
    arr = real_array(value, where)
    if arr.ndim > 1:
        raise ValueError(
            f"`{where}` must be a scalar or a 1-D array (one entry per filter section), "
            f"got shape {arr.shape}"
        )
    return arr


def _broadcast_params(cls_name: str, params: dict[str, Array]) -> dict[str, Array]:
    """Broadcast scalar / 1-D parameters to one common length m ≥ 1."""
    m = None
    first = None
    for name, arr in params.items():
        if arr.ndim == 1:
            if m is None:
                m, first = arr.shape[0], name
            elif arr.shape[0] != m:
                raise ValueError(
                    f"`{cls_name}({name}=...)` must be a scalar or have the same length as "
                    f"`{first}` ({m}, one entry per filter section), got shape {arr.shape}"
                )
    if m == 0:
        raise ValueError(f"`{cls_name}({first}=...)` must hold at least one filter, got shape (0,)")
    m = 1 if m is None else m
    return {name: jnp.broadcast_to(arr, (m,)) for name, arr in params.items()}


class AbstractFilter(eqx.Module):
    r"""A continuous filter G(s) = (1 + Σ_p P_p(s)) · Π_q N_q(s) of second-order sections.

    Subclasses say which sections are in parallel (peak filters) and which in series (notch
    filters); everything else — ``transfer``, ``frf``, ``state_space``, ``discretize`` — is shared.
    """

    @abc.abstractmethod
    def _banks(self) -> tuple[_Bank, _Bank]:
        """(parallel bank, series bank) of second-order sections."""

    @property
    def n_sections(self) -> int:
        """Number of second-order sections (state dimension / 2)."""
        (pn, _, _), (sn, _, _) = self._banks()
        return pn.shape[-2] + sn.shape[-2]

    def transfer(self, s: Inexact[ArrayLike, "*shape"]) -> Complex[Array, "*shape"]:
        """G(s) at complex ``s`` of any shape (real input is promoted to complex128)."""
        s = to_complex(s)
        (pn, pd, _), (sn, sd, _) = self._banks()
        x = s[..., None]
        parallel = 1 + jnp.sum(_biquad_s(pn, pd, x), axis=-1)
        series = jnp.prod(_biquad_s(sn, sd, x), axis=-1)
        return parallel * series

    def frf(self, freq_hz: Float[ArrayLike, " freq"]) -> Complex[Array, " freq"]:
        """Frequency response G(i 2π f) on a positive, increasing grid ``freq_hz`` (Hz)."""
        name = type(self).__name__
        f = frequency_grid(freq_hz, f"{name}.frf(freq_hz=...)")
        s = to_complex(2 * jnp.pi * f) * 1j
        return finite_output(self.transfer(s), f"{name}.frf(...)")

    def state_space(self) -> LTI:
        """A real, minimal (order 2 per section) realisation: parallel peak part, then notches.

        A continuous ``LTI`` with A (n, n), B (n, 1), C (1, n), D (1, 1), n = 2 per section.
        Each section is realised as in ``_section_ss``; the peak sections sit side by side with
        the direct path 1 (D = 1 + Σ K_i cos φ_i), and each notch section is cascaded after.
        """
        (pn, pd, pw), (sn, sd, sw) = self._banks()
        sys = _parallel_ss(*_section_ss(pn, pd, pw))
        A2, B2, C2, D2 = _section_ss(sn, sd, sw)
        for q in range(A2.shape[0]):
            sys = series(sys, LTI(A2[q], B2[q], C2[q], D2[q].reshape(1, 1)))
        return sys

    def discretize(self, dt: Float[ArrayLike, ""], method: str = "fitted") -> DiscreteFilter:
        r"""Discrete filter (paper Eqs. (3)–(4)) for servo period ``dt`` (s), section by
        section, structure kept.

        ``method="fitted"`` (default): each section's poles are mapped exactly, z = e^{p dt}
        (so every mode of the filter decays as in continuous time), and its numerator — a
        second-order FIR part plus a first-order part over the poles,

            H_d(z) = c0 + c1 z⁻¹ + c2 z⁻² + (c3 + c4 z⁻¹)/(1 + a1 z⁻¹ + a2 z⁻²),

        two second-order sections in parallel — is fitted to the continuous response up to a
        quarter of the Nyquist frequency (ω dt ≤ π/4), minimising the largest relative error
        (Lawson's reweighted least squares), and made exact at DC and at the section's own
        frequency ω_k (a notch keeps its depth
        ζ_n/ζ_d there, a peak lobe its height and phase). Within that band the discrete MCM is
        within 1 % of the continuous one: ``benchmarks/filter_accuracy.py`` measures at most
        0.85 % over 1500 random notches (up to fs/4, ζ ≤ 1), peaks (up to fs/8, |K| ≤ 2,
        ξ ≤ 1) and their products at 8 and 16 kHz, where prewarped Tustin is off by up to 33 %.
        (Relative error is meaningless where a peak filter's response nearly vanishes; outside
        that range — sections damped beyond ζ = 1, or close to the Nyquist frequency — the
        error can pass 1 %: 1.4 % for a ζ_n/ζ_d = 3/8 notch at 1.5 kHz, 8 kHz.  Peaks above
        fs/8 can be far off over the band up to fs/8: at 8 kHz the worst seen (|K| ≤ 2,
        ξ ≤ 1, any φ; K = −2, ξ = 1, φ = 0) is off by 11 % at 3.5 kHz, 47 % at 3.9 kHz and
        437 % at 3.99 kHz, where prewarped Tustin is off by up to about 50 %; a peak of
        K = 0.3, ξ = 0.2 stays within 1 % up to 3.5 kHz.)

        ``method="tustin"``: the bilinear map s = c_k (z − 1)/(z + 1), c_k = ω_k/tan(ω_k dt/2),
        i.e. prewarped at the section's own ω_k, one second-order section each, what most
        drives implement. Exact at ω_k; elsewhere G_d(e^{iωdt}) = G(i c_k tan(ωdt/2)) section
        by section, a frequency warp that moves a broad filter near the band edge by several
        per cent (a 1508 Hz, ζ 0.05/0.5 notch at 8 kHz: 12 % below 1 kHz).

        Every ω_k must lie below the Nyquist frequency, ω_k dt < π. See ``DiscreteFilter`` for
        the structure.
        """
        return self._discretize(dt, method, "discretize", "dt")

    def _discretize(self, dt, method, fn, arg) -> DiscreteFilter:
        """:meth:`discretize`, its errors naming the method ``fn`` and its argument ``arg``."""
        name = type(self).__name__
        where = f"{name}.{fn}({arg}=...)"
        if method not in ("fitted", "tustin"):
            raise ValueError(
                f"`{name}.{fn}(method=...)` must be 'fitted' or 'tustin', got {method!r}"
            )
        dt = positive(real_scalar(dt, where), where)
        rate = ""  # a rate given for the period: the period it likely meant
        if is_concrete(dt) and float(dt) >= 1:
            rate = f"; a period in seconds: if {float(dt):g} is a rate in Hz, {1 / float(dt):.6g} s"
        (pn, pd, pw), (sn, sd, sw) = self._banks()
        w0 = jnp.concatenate([pw, sw])
        if w0.shape[0] > 0:
            if is_concrete(w0):
                w_max = float(np.max(np.asarray(w0)))
                dt = check(
                    dt,
                    lambda d: d * w_max < math.pi,
                    where,
                    f"below π/ω_max = {math.pi / w_max:.6g} s so that every filter frequency "
                    f"(up to {w_max / (2 * math.pi):.6g} Hz) lies below the Nyquist frequency "
                    f"(ω·dt < π){rate}",
                )
            else:
                dt = eqx.error_if(
                    dt,
                    jnp.any(w0 * dt >= jnp.pi),
                    f"`{where}` must be below π/ω_max so that every filter frequency lies below "
                    "the Nyquist frequency (ω·dt < π)",
                )
        if method == "tustin":
            return DiscreteFilter(
                parallel_sos=_tustin_prewarped(pn, pd, pw, dt),
                series_sos=_tustin_prewarped(sn, sd, sw, dt)[:, None, :],
                dt=dt,
            )
        # both banks in one fit (one program for the peaks and the notches)
        p = pw.shape[0]
        fir, iir = _fitted_sections(
            jnp.concatenate([pn, sn]), jnp.concatenate([pd, sd]), w0, dt,
            jnp.arange(w0.shape[0]) < p,
        )
        pf, pi, sf, si = fir[:p], iir[:p], fir[p:], iir[p:]
        return DiscreteFilter(
            parallel_sos=jnp.concatenate([pf, pi], axis=0),
            series_sos=jnp.stack([sf, si], axis=1),
            dt=dt,
        )


    def to_sos(self, period: Float[ArrayLike, ""], method: str = "fitted") -> np.ndarray:
        r"""The discrete filter a servo drive loads for period ``period`` (s): a cascade of
        standard biquads, rows [b0, b1, b2, 1, a1, a2] in ``scipy.signal.sosfilt``'s convention
        (a new, writable float64 NumPy array), equal to what the sampled loop runs:
        ``self.discretize(period, method).to_sos()`` (see :meth:`DiscreteFilter.to_sos`).
        Needs concrete values (not under ``jit``)."""
        if not all(is_concrete(x) for x in jax.tree_util.tree_leaves((self, period))):
            raise TypeError(f"`{type(self).__name__}.to_sos()` needs concrete values; call it "
                            f"outside `jax.jit`/`vmap`/`grad`")
        return self._discretize(period, method, "to_sos", "period").to_sos()

class PeakFilter(AbstractFilter):
    r"""Peak filter(s), paper Eq. (3) (as corrected below):

        G_pf(s) = 1 + Σ_{i=1}^{m} K_i · s (s cos φ_i + ω_i sin φ_i) / (s² + 2 ξ_i ω_i s + ω_i²).

    (The English text of the paper drops the first ``s`` of the numerator; the Chinese edition
    has it.) At s = iω_i the i-th term is (K_i / 2ξ_i) e^{i(π/2 − φ_i)}: the filter adds a
    resonant lobe of height K_i/(2ξ_i) whose phase is set by φ_i.

    Arguments (physical values; scalars for one filter or 1-D arrays of one common length m,
    scalars broadcast): ``K`` gain (real), ``omega`` centre frequency in rad/s (> 0), ``xi``
    damping ratio (> 0), ``phi`` shift phase in rad (real).

    Stored leaves: ``K``, ``phi`` and ``log_omega``, ``log_xi`` (shape (m,)); ``omega`` and ``xi``
    are properties, positive for any value of the leaves.
    """

    K: Float[Array, " m"]
    log_omega: Float[Array, " m"]
    log_xi: Float[Array, " m"]
    phi: Float[Array, " m"]

    def __init__(self, K: Float[ArrayLike, "*k"], omega: Float[ArrayLike, "*k"],
                 xi: Float[ArrayLike, "*k"], phi: Float[ArrayLike, "*k"]):
        raw = {"K": K, "omega": omega, "xi": xi, "phi": phi}
        p = {k: _real_param(v, f"PeakFilter({k}=...)") for k, v in raw.items()}
        p["K"] = finite(p["K"], "PeakFilter(K=...)")
        p["omega"] = positive(p["omega"], "PeakFilter(omega=...)")
        p["xi"] = positive(p["xi"], "PeakFilter(xi=...)")
        p["phi"] = finite(p["phi"], "PeakFilter(phi=...)")
        p = _broadcast_params("PeakFilter", p)
        self.K = p["K"]
        self.log_omega = jnp.log(p["omega"])
        self.log_xi = jnp.log(p["xi"])
        self.phi = p["phi"]

    @classmethod
    def from_unconstrained(
        cls, K: Float[ArrayLike, "*k"], log_omega: Float[ArrayLike, "*k"],
        log_xi: Float[ArrayLike, "*k"], phi: Float[ArrayLike, "*k"]
    ) -> PeakFilter:
        """Build from unconstrained reals: ω = exp(log_omega), ξ = exp(log_xi)."""
        return cls(K, jnp.exp(jnp.asarray(log_omega)), jnp.exp(jnp.asarray(log_xi)), phi)

    @property
    def omega(self) -> Float[Array, " m"]:
        """Centre frequencies ω_i (rad/s)."""
        return jnp.exp(self.log_omega)

    @property
    def xi(self) -> Float[Array, " m"]:
        """Damping ratios ξ_i."""
        return jnp.exp(self.log_xi)

    def params(self) -> dict[str, Float[Array, " m"]]:
        """Physical parameters; ``PeakFilter(**f.params())`` rebuilds ``f``."""
        return {"K": self.K, "omega": self.omega, "xi": self.xi, "phi": self.phi}

    def _banks(self) -> tuple[_Bank, _Bank]:
        w, xi, K, phi = self.omega, self.xi, self.K, self.phi
        num = jnp.stack([K * jnp.cos(phi), K * w * jnp.sin(phi), jnp.zeros_like(w)], -1)
        den = jnp.stack([jnp.ones_like(w), 2 * xi * w, w * w], -1)
        return (num, den, w), _empty_bank()


class NotchFilter(AbstractFilter):
    r"""Second-order notch filter(s) in series, paper Eq. (4):

        G_nf(s) = Π_{j=1}^{n} (s² + 2 ζ_nj ω_j s + ω_j²) / (s² + 2 ζ_dj ω_j s + ω_j²).

    At s = iω_j the j-th factor is exactly ζ_nj/ζ_dj (real, phase 0): the notch depth.

    Arguments (scalars or 1-D arrays of one common length n, scalars broadcast): ``omega`` notch
    frequency in rad/s, ``zeta_n`` numerator and ``zeta_d`` denominator damping ratios, all > 0.
    Stored as ``log_omega``, ``log_zeta_n``, ``log_zeta_d``; the physical values are properties.
    """

    log_omega: Float[Array, " n"]
    log_zeta_n: Float[Array, " n"]
    log_zeta_d: Float[Array, " n"]

    def __init__(self, omega: Float[ArrayLike, "*k"], zeta_n: Float[ArrayLike, "*k"],
                 zeta_d: Float[ArrayLike, "*k"]):
        raw = {"omega": omega, "zeta_n": zeta_n, "zeta_d": zeta_d}
        p = {k: _real_param(v, f"NotchFilter({k}=...)") for k, v in raw.items()}
        p = {k: positive(v, f"NotchFilter({k}=...)") for k, v in p.items()}
        p = _broadcast_params("NotchFilter", p)
        self.log_omega = jnp.log(p["omega"])
        self.log_zeta_n = jnp.log(p["zeta_n"])
        self.log_zeta_d = jnp.log(p["zeta_d"])

    @classmethod
    def from_unconstrained(
        cls, log_omega: Float[ArrayLike, "*k"], log_zeta_n: Float[ArrayLike, "*k"],
        log_zeta_d: Float[ArrayLike, "*k"]
    ) -> NotchFilter:
        """Build from unconstrained reals: ω = exp(log_omega), ζ = exp(log_zeta)."""
        e = lambda x: jnp.exp(jnp.asarray(x))
        return cls(e(log_omega), e(log_zeta_n), e(log_zeta_d))

    @property
    def omega(self) -> Float[Array, " n"]:
        """Notch frequencies ω_j (rad/s)."""
        return jnp.exp(self.log_omega)

    @property
    def zeta_n(self) -> Float[Array, " n"]:
        """Numerator damping ratios ζ_nj."""
        return jnp.exp(self.log_zeta_n)

    @property
    def zeta_d(self) -> Float[Array, " n"]:
        """Denominator damping ratios ζ_dj."""
        return jnp.exp(self.log_zeta_d)

    def params(self) -> dict[str, Float[Array, " n"]]:
        """Physical parameters; ``NotchFilter(**f.params())`` rebuilds ``f``."""
        return {"omega": self.omega, "zeta_n": self.zeta_n, "zeta_d": self.zeta_d}

    def _banks(self) -> tuple[_Bank, _Bank]:
        w = self.omega
        one = jnp.ones_like(w)
        num = jnp.stack([one, 2 * self.zeta_n * w, w * w], -1)
        den = jnp.stack([one, 2 * self.zeta_d * w, w * w], -1)
        return _empty_bank(), (num, den, w)


class MCM(AbstractFilter):
    r"""Modal characteristic modifier, paper Sec. 4.1: G_MCM(s) = G_pf(s) · G_nf(s).

    G_pf is Eq. (3) (``PeakFilter``), G_nf Eq. (4) (``NotchFilter``). Either part may be
    ``None`` (its factor is then 1); ``MCM()`` is the identity, the "no modifier" baseline.
    """

    peak: PeakFilter | None
    notch: NotchFilter | None

    def __init__(self, peak: PeakFilter | None = None, notch: NotchFilter | None = None):
        if peak is not None and not isinstance(peak, PeakFilter):
            raise TypeError(f"`MCM(peak=...)` must be a PeakFilter or None, got {type(peak)}")
        if notch is not None and not isinstance(notch, NotchFilter):
            raise TypeError(f"`MCM(notch=...)` must be a NotchFilter or None, got {type(notch)}")
        self.peak = peak
        self.notch = notch

    def _banks(self) -> tuple[_Bank, _Bank]:
        parallel = _empty_bank() if self.peak is None else self.peak._banks()[0]
        series = _empty_bank() if self.notch is None else self.notch._banks()[1]
        return parallel, series
