r"""The modal characteristic modifier (MCM): peak and notch filters (paper Sec. 4.1).

An MCM is the product of a *peak-filter* part, which bends low and middle modes to "in phase",
and a *notch-filter* part, which removes high modes (paper Eqs. (3) and (4)):

    G_MCM(s) = G_pf(s) · G_nf(s),

    G_pf(s) = 1 + Σ_i K_i · s (s cos φ_i + ω_i sin φ_i) / (s² + 2 ξ_i ω_i s + ω_i²),     Eq. (3)

    G_nf(s) = Π_j (s² + 2 ζ_nj ω_j s + ω_j²) / (s² + 2 ζ_dj ω_j s + ω_j²).                Eq. (4)

The English text of the paper drops one ``s`` from Eq. (3) (it prints
``s(cos φ + ω sin φ)``, which is dimensionally wrong); the form above is the one of the Chinese
edition and of DESIGN.md §2. Frequencies are in rad/s and phases in rad (SI inside); only
``frf(freq_hz)`` takes Hz.

Every filter is a sum/product of second-order sections ("biquads")

    G(s) = (1 + Σ_p P_p(s)) · Π_q N_q(s),

with the peak sections P_p in parallel (the constant 1 is the direct path) and the notch sections
N_q in series. The continuous filters (``PeakFilter``, ``NotchFilter``, ``MCM``) and the
discrete one (``DiscreteFilter``, from ``.discretize(dt)``) keep exactly this structure, so the
parallel part is never mistaken for a cascade.

**Discretisation.** ``.discretize(dt)`` maps each section on its own. The default
(``method="fitted"``) maps the poles exactly, z = e^{p dt}, and fits the numerator (an FIR
section plus a section over the poles, summed) to the continuous response up to a quarter of the
Nyquist frequency, exact at DC and at the section's own frequency: the discrete MCM is within
1 % of the continuous one there, for notches up to 0.2·fs and peaks up to fs/8. The prewarped
bilinear map (``method="tustin"``, one section each) is exact at the section's frequency but
warps the rest of the band: a broad notch near 1.5 kHz at an 8 kHz servo rate is off by 12 %.

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
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Complex, Float

from ._checks import check, finite, finite_output, frequency_grid, is_concrete, positive

__all__ = [
    "AbstractFilter",
    "DiscreteFilter",
    "FilterStateSpace",
    "MCM",
    "NotchFilter",
    "PeakFilter",
]

# A bank of second-order sections in s: numerator and denominator coefficients of
# (n0 s² + n1 s + n2) / (s² + d1 s + d2), shape (k, 3) each (d0 = 1), and the section's own
# frequency ω0 (rad/s, shape (k,)) used for prewarping and for a balanced realisation.
_Bank = tuple[Float[Array, "k 3"], Float[Array, "k 3"], Float[Array, " k"]]


def _empty_bank() -> _Bank:
    return (
        jnp.zeros((0, 3), jnp.float64),
        jnp.zeros((0, 3), jnp.float64),
        jnp.zeros((0,), jnp.float64),
    )


def _complex(x) -> Array:
    return jnp.asarray(x).astype(jnp.complex128)


def _real_param(value, where: str) -> Array:
    """A real scalar or 1-D parameter as float64 (shape/dtype facts only)."""
    arr = jnp.asarray(value)
    if jnp.issubdtype(arr.dtype, jnp.complexfloating):
        raise ValueError(f"`{where}` must be real, got dtype {arr.dtype}")
    if arr.ndim > 1:
        raise ValueError(
            f"`{where}` must be a scalar or a 1-D array (one entry per filter section), "
            f"got shape {arr.shape}"
        )
    return arr.astype(jnp.float64)


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


def _biquad_s(num: Array, den: Array, x: Array) -> Array:
    """(n0 x² + n1 x + n2)/(d0 x² + d1 x + d2) by Horner, x of shape (..., 1) → (..., k)."""
    n0, n1, n2 = (_complex(num[:, i]) for i in range(3))
    d0, d1, d2 = (_complex(den[:, i]) for i in range(3))
    return ((n0 * x + n1) * x + n2) / ((d0 * x + d1) * x + d2)


class FilterStateSpace(eqx.Module):
    r"""A continuous-time realisation ẋ = A x + B u, y = C x + D u of a SISO filter.

    G(s) = C (sI − A)⁻¹ B + D. Shapes follow python-control (``control.ss(A, B, C, D)`` accepts
    them as they are): A (n, n), B (n, 1), C (1, n), D (1, 1), all float64; n = 2 per section.
    """

    A: Float[Array, "n n"]
    B: Float[Array, "n 1"]
    C: Float[Array, "1 n"]
    D: Float[Array, "1 1"]

    def transfer(self, s: ArrayLike) -> Complex[Array, "*shape"]:
        """C (sI − A)⁻¹ B + D at complex ``s`` of any shape (a direct solve, for checking)."""
        s = _complex(s)
        n = self.A.shape[0]
        eye = jnp.eye(n, dtype=jnp.complex128)
        M = s[..., None, None] * eye - _complex(self.A)
        rhs = jnp.broadcast_to(_complex(self.B), (*s.shape, n, 1))
        x = jnp.linalg.solve(M, rhs)
        return (_complex(self.C) @ x)[..., 0, 0] + _complex(self.D[0, 0])


def _section_ss(num: Array, den: Array, w0: Array):
    """Balanced 2-state realisation of each section, vectorised over k sections.

    A = [[0, ω0], [−ω0, −d1]] has characteristic polynomial s² + d1 s + ω0² (= the denominator,
    d2 = ω0²); with B = [0, 1]ᵀ, (sI − A)⁻¹B = [ω0, s]ᵀ/den, so C = [(n2 − n0 d2)/ω0,
    n1 − n0 d1] and D = n0 reproduce the numerator. Every entry scales like ω0, unlike the
    companion form whose entries scale like ω0².
    """
    zero = jnp.zeros_like(w0)
    A = jnp.stack([jnp.stack([zero, w0], -1), jnp.stack([-w0, -den[:, 1]], -1)], -2)
    B = jnp.stack([zero, jnp.ones_like(w0)], -1)[:, :, None]
    C = jnp.stack([(num[:, 2] - num[:, 0] * den[:, 2]) / w0, num[:, 1] - num[:, 0] * den[:, 1]], -1)
    return A, B, C[:, None, :], num[:, 0]


def _parallel_ss(A, B, C, D) -> FilterStateSpace:
    """1 + Σ_k G_k: block-diagonal A, stacked B, concatenated C, D = 1 + Σ D_k."""
    k = A.shape[0]
    eye = jnp.eye(k, dtype=jnp.float64)
    A_full = (eye[:, None, :, None] * A[:, :, None, :]).reshape(2 * k, 2 * k)
    return FilterStateSpace(
        A=A_full,
        B=B.reshape(2 * k, 1),
        C=jnp.transpose(C, (1, 0, 2)).reshape(1, 2 * k),
        D=(1 + jnp.sum(D)).reshape(1, 1),
    )


def _series_ss(first: FilterStateSpace, A2, B2, C2, D2) -> FilterStateSpace:
    """``first`` followed by (A2, B2, C2, D2): u → G1 → G2 → y."""
    n1 = first.A.shape[0]
    top = jnp.concatenate([first.A, jnp.zeros((n1, 2), jnp.float64)], axis=1)
    bottom = jnp.concatenate([B2 @ first.C, A2], axis=1)
    return FilterStateSpace(
        A=jnp.concatenate([top, bottom], axis=0),
        B=jnp.concatenate([first.B, B2 * first.D[0, 0]], axis=0),
        C=jnp.concatenate([D2 * first.C, C2], axis=1),
        D=first.D * D2,
    )


def _tustin_prewarped(num: Array, den: Array, w0: Array, dt: Array) -> Float[Array, "k 6"]:
    r"""Bilinear transform of each section, prewarped at its own ω0, in scipy's sos layout.

    s = c (z − 1)/(z + 1) with c = ω0 / tan(ω0 dt/2), so that s = iω0 exactly at
    z = e^{iω0 dt}. Multiplying (n0 s² + n1 s + n2) by (z + 1)² gives the z², z¹, z⁰ coefficients
    n0c² + n1c + n2, 2(n2 − n0c²), n0c² − n1c + n2 (same for the denominator); dividing by
    z² and by the leading denominator coefficient gives [b0, b1, b2, 1, a1, a2] in z⁻¹.
    """
    c = w0 / jnp.tan(w0 * dt / 2)
    c2 = c * c

    def coeffs(p):
        return jnp.stack(
            [
                p[:, 0] * c2 + p[:, 1] * c + p[:, 2],
                2 * (p[:, 2] - p[:, 0] * c2),
                p[:, 0] * c2 - p[:, 1] * c + p[:, 2],
            ],
            -1,
        )

    b, a = coeffs(num), coeffs(den)
    a0 = a[:, :1]
    return jnp.concatenate([b / a0, a / a0], axis=-1)


# The fitted discretisation (``discretize(dt, method="fitted")``): fit band θ = ω·dt ∈ [0, π/4]
# (up to a quarter of the Nyquist frequency), sampled uniformly and, around each section's own
# frequency, on a local grid ω0(1 + 2ζ·u), u ∈ [−4, 4] (so that a sharp section is resolved).
_FIT_BAND = math.pi / 4
_FIT_UNIFORM = 64
_FIT_LOCAL = 64
_FIT_LOCAL_SPAN = 4.0
_FIT_MIN_ZETA = 0.005
_FIT_LAWSON = 8


def _matched_denominator(den: Array, dt: Array) -> tuple[Array, Array]:
    r"""a1, a2 of 1 + a1 z⁻¹ + a2 z⁻² whose roots are z = e^{p dt}, p the roots of s² + d1 s + d2.

    With σ = d1/2 and ω_d² = d2 − σ²: a1 = −2 e^{−σ dt} cos(ω_d dt), a2 = e^{−2σ dt}; cos
    becomes cosh for real poles (ω_d² < 0). Near ω_d = 0 the Taylor series keeps the gradient
    finite.
    """
    sigma = den[:, 1] / 2
    u = (den[:, 2] - sigma * sigma) * dt * dt
    small = jnp.abs(u) < 1e-6
    safe = jnp.where(small, 1.0, u)
    root = jnp.sqrt(jnp.abs(safe))
    c = jnp.where(small, 1 - u / 2 + u * u / 24, jnp.where(safe > 0, jnp.cos(root), jnp.cosh(root)))
    e = jnp.exp(-sigma * dt)
    return -2 * e * c, e * e


@functools.partial(jax.jit, static_argnames="parallel")
def _fitted_sections(
    num: Array, den: Array, w0: Array, dt: Array, parallel: bool
) -> tuple[Float[Array, "k 6"], Float[Array, "k 6"]]:
    r"""Pole-matched, fitted-numerator discretisation of each section (method="fitted").

    Each section H(s) = (n0 s² + n1 s + n2)/(s² + d1 s + d2) becomes

        H_d(z) = c0 + c1 z⁻¹ + c2 z⁻² + (c3 + c4 z⁻¹)/(1 + a1 z⁻¹ + a2 z⁻²),

    with the poles mapped exactly (z = e^{p dt}, ``_matched_denominator``). Three of the five
    c are fixed by exact agreement at DC (z = 1: the static gain is kept) and at the section's
    own frequency ω0 (a complex equation: a notch keeps its depth ζ_n/ζ_d there, a peak lobe
    its height and phase); the other two minimise the largest relative error
    |H_d(e^{iωdt}) − H(iω)|/|ref| over 0 ≤ ω dt ≤ π/4, by Lawson's iteratively reweighted
    least squares. ref = H for a series (notch) section and 1 + H for a parallel (peak) one,
    whose error adds to the direct path 1. Returns the FIR rows [c0, c1, c2, 1, 0, 0] and the
    IIR rows [c3, c4, 0, 1, a1, a2], both (k, 6).
    """
    k = w0.shape[0]
    a1, a2 = _matched_denominator(den, dt)
    th0 = w0 * dt
    zeta = jnp.maximum(den[:, 1] / (2 * w0), _FIT_MIN_ZETA)
    u = jnp.linspace(-_FIT_LOCAL_SPAN, _FIT_LOCAL_SPAN, _FIT_LOCAL)
    # Grid: the uniform band, the local points around ω0, then the two constraint points.
    theta = jnp.concatenate(
        [
            jnp.broadcast_to(jnp.linspace(0.0, _FIT_BAND, _FIT_UNIFORM), (k, _FIT_UNIFORM)),
            th0[:, None] * (1 + 2 * zeta[:, None] * u),
            jnp.zeros((k, 1)),
            th0[:, None],
        ],
        axis=1,
    )
    x = jnp.exp(-1j * _complex(theta))
    A = 1 + _complex(a1)[:, None] * x + _complex(a2)[:, None] * x * x
    basis = jnp.stack([jnp.ones_like(x), x, x * x, 1 / A, x / A], -1)  # (k, n, 5)
    s = 1j * _complex(theta / dt)
    n0, n1, n2, d1, d2 = (_complex(c)[:, None] for c in (*num.T, den[:, 1], den[:, 2]))
    H = ((n0 * s + n1) * s + n2) / ((s + d1) * s + d2)
    ref = 1 + H if parallel else H
    fit = theta[:, :-2]
    in_band = (fit >= 0) & (fit <= _FIT_BAND)
    wt = jnp.where(in_band, 1 / jnp.abs(ref[:, :-2]), 0.0)
    elim, free = jnp.array([0, 3, 4]), jnp.array([1, 2])

    def solve(basis_k, H_k, wt_k):
        # Constraints E c = e (DC real part; ω0 real and imaginary parts) fix c0, c3, c4.
        b_dc, b_w0 = basis_k[-2], basis_k[-1]
        E = jnp.stack([jnp.real(b_dc), jnp.real(b_w0), jnp.imag(b_w0)])
        e = jnp.stack([jnp.real(H_k[-2]), jnp.real(H_k[-1]), jnp.imag(H_k[-1])])
        G = jnp.linalg.solve(E[:, elim], jnp.concatenate([e[:, None], E[:, free]], axis=1))
        g0, G1 = G[:, 0], -G[:, 1:]  # c_elim = g0 + G1 c_free
        g0c, G1c, wc = _complex(g0), _complex(G1), _complex(wt_k)[:, None]
        M = basis_k[:-2]
        Mf = (M[:, free] + M[:, elim] @ G1c) * wc
        y = (H_k[:-2] - M[:, elim] @ g0c) * wc[:, 0]
        Mr = jnp.concatenate([jnp.real(Mf), jnp.imag(Mf)])
        yr = jnp.concatenate([jnp.real(y), jnp.imag(y)])

        def lstsq(sw):
            # sw: square roots of the Lawson weights, one per complex row.
            sw2 = jnp.concatenate([sw, sw])[:, None]
            Q, R = jnp.linalg.qr(Mr * sw2)
            return jax.scipy.linalg.solve_triangular(R, Q.T @ (yr * sw2[:, 0]))

        def safe_sqrt(v):  # √v with a finite gradient at 0 (rows off the band have v = 0)
            return jnp.where(v > 0, jnp.sqrt(jnp.where(v > 0, v, 1.0)), 0.0)

        def reweight(_, sw):
            res = Mf @ _complex(lstsq(sw)) - y
            new = sw * safe_sqrt(safe_sqrt(jnp.real(res) ** 2 + jnp.imag(res) ** 2))
            total = jnp.sum(new * new)  # 0 only for an exact fit (e.g. K = 0): keep the weights
            return jnp.where(total > 0, new / safe_sqrt(jnp.where(total > 0, total, 1.0)), sw)

        sw0 = jnp.full(y.shape, 1.0 / math.sqrt(y.shape[0]))
        c_free = lstsq(jax.lax.fori_loop(0, _FIT_LAWSON, reweight, sw0))
        c = jnp.zeros(5).at[free].set(c_free).at[elim].set(g0 + G1 @ c_free)
        return c

    c = jax.vmap(solve)(basis, H, wt)
    zero, one = jnp.zeros_like(a1), jnp.ones_like(a1)
    fir = jnp.stack([c[:, 0], c[:, 1], c[:, 2], one, zero, zero], -1)
    iir = jnp.stack([c[:, 3], c[:, 4], zero, one, a1, a2], -1)
    return fir, iir


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

    def transfer(self, s: ArrayLike) -> Complex[Array, "*shape"]:
        """G(s) at complex ``s`` of any shape (real input is promoted to complex128)."""
        s = _complex(s)
        (pn, pd, _), (sn, sd, _) = self._banks()
        x = s[..., None]
        parallel = 1 + jnp.sum(_biquad_s(pn, pd, x), axis=-1)
        series = jnp.prod(_biquad_s(sn, sd, x), axis=-1)
        return parallel * series

    def frf(self, freq_hz: ArrayLike) -> Complex[Array, " freq"]:
        """Frequency response G(i 2π f) on a positive, increasing grid ``freq_hz`` (Hz)."""
        name = type(self).__name__
        f = frequency_grid(freq_hz, f"{name}.frf(freq_hz=...)")
        s = _complex(2 * jnp.pi * f) * 1j
        return finite_output(self.transfer(s), f"{name}.frf(...)")

    def state_space(self) -> FilterStateSpace:
        """A real, minimal (order 2 per section) realisation: parallel peak part, then notches.

        Each section is realised as in ``_section_ss``; the peak sections sit side by side with
        the direct path 1 (D = 1 + Σ K_i cos φ_i), and each notch section is cascaded after.
        """
        (pn, pd, pw), (sn, sd, sw) = self._banks()
        sys = _parallel_ss(*_section_ss(pn, pd, pw))
        A2, B2, C2, D2 = _section_ss(sn, sd, sw)
        for q in range(A2.shape[0]):
            sys = _series_ss(sys, A2[q], B2[q], C2[q], D2[q])
        return sys

    def discretize(self, dt: ArrayLike, method: str = "fitted") -> DiscreteFilter:
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
        error can pass 1 %: 1.4 % for a ζ_n/ζ_d = 3/8 notch at 1.5 kHz, 8 kHz.)

        ``method="tustin"``: the bilinear map s = c_k (z − 1)/(z + 1), c_k = ω_k/tan(ω_k dt/2),
        i.e. prewarped at the section's own ω_k, one second-order section each, what most
        drives implement. Exact at ω_k; elsewhere G_d(e^{iωdt}) = G(i c_k tan(ωdt/2)) section
        by section, a frequency warp that moves a broad filter near the band edge by several
        per cent (a 1508 Hz, ζ 0.05/0.5 notch at 8 kHz: 12 % below 1 kHz).

        Every ω_k must lie below the Nyquist frequency, ω_k dt < π. See ``DiscreteFilter`` for
        the structure.
        """
        name = type(self).__name__
        where = f"{name}.discretize(dt=...)"
        if method not in ("fitted", "tustin"):
            raise ValueError(
                f"`{name}.discretize(method=...)` must be 'fitted' or 'tustin', got {method!r}"
            )
        dt = jnp.asarray(dt)
        if dt.ndim != 0 or jnp.issubdtype(dt.dtype, jnp.complexfloating):
            raise ValueError(f"`{where}` must be a real scalar, got {dt.dtype} of shape {dt.shape}")
        dt = positive(dt.astype(jnp.float64), where)
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
                    "(ω·dt < π)",
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
        pf, pi = _fitted_sections(pn, pd, pw, dt, parallel=True)
        sf, si = _fitted_sections(sn, sd, sw, dt, parallel=False)
        return DiscreteFilter(
            parallel_sos=jnp.concatenate([pf, pi], axis=0),
            series_sos=jnp.stack([sf, si], axis=1),
            dt=dt,
        )


class PeakFilter(AbstractFilter):
    r"""Peak filter(s), paper Eq. (3) (corrected, DESIGN.md §2):

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

    def __init__(self, K: ArrayLike, omega: ArrayLike, xi: ArrayLike, phi: ArrayLike):
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
        cls, K: ArrayLike, log_omega: ArrayLike, log_xi: ArrayLike, phi: ArrayLike
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

    def __init__(self, omega: ArrayLike, zeta_n: ArrayLike, zeta_d: ArrayLike):
        raw = {"omega": omega, "zeta_n": zeta_n, "zeta_d": zeta_d}
        p = {k: _real_param(v, f"NotchFilter({k}=...)") for k, v in raw.items()}
        p = {k: positive(v, f"NotchFilter({k}=...)") for k, v in p.items()}
        p = _broadcast_params("NotchFilter", p)
        self.log_omega = jnp.log(p["omega"])
        self.log_zeta_n = jnp.log(p["zeta_n"])
        self.log_zeta_d = jnp.log(p["zeta_d"])

    @classmethod
    def from_unconstrained(
        cls, log_omega: ArrayLike, log_zeta_n: ArrayLike, log_zeta_d: ArrayLike
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


def _sos_array(value, where: str, stages: bool = False) -> Array:
    arr = jnp.asarray(value)
    if stages and arr.ndim == 2:
        arr = arr[:, None, :]
    ndim, shape = (3, "(n_stages, n_sections, 6)") if stages else (2, "(n_sections, 6)")
    if arr.ndim != ndim or arr.shape[-1] != 6 or jnp.issubdtype(arr.dtype, jnp.complexfloating):
        extra = " or (n_stages, 6)" if stages else ""
        raise ValueError(
            f"`{where}` must be a real {shape}{extra} array of rows [b0, b1, b2, 1, a1, a2], "
            f"got {arr.dtype} of shape {arr.shape}"
        )
    return arr.astype(jnp.float64)


def _section_response(sos: Array, zi: Array) -> Array:
    """(b0 + b1 z⁻¹ + b2 z⁻²)/(a0 + a1 z⁻¹ + a2 z⁻²) of rows ``sos`` (..., 6) at zi = z⁻¹."""
    b0, b1, b2, a0, a1, a2 = (_complex(sos[..., i]) for i in range(6))
    return ((b2 * zi + b1) * zi + b0) / ((a2 * zi + a1) * zi + a0)


def _sos_step(sos: Array, z: Array, u: Array) -> tuple[Array, Array]:
    """Direct form II transposed, rows ``sos`` (k, 6) with states ``z`` (k, 2), input ``u``:
    y = b0 u + z0, z0' = b1 u − a1 y + z1, z1' = b2 u − a2 y."""
    y = sos[:, 0] * u + z[:, 0]
    z_next = jnp.stack([sos[:, 1] * u - sos[:, 4] * y + z[:, 1], sos[:, 2] * u - sos[:, 5] * y], -1)
    return z_next, y


def _sos_block_ss(sos: Array):
    """(A, B, C, D) of the sum of the rows ``sos`` (k, 6) in their DF2T states, 2 per row:
    per row y = b0 u + s1, s1' = −a1 s1 + s2 + (b1 − a1 b0) u, s2' = −a2 s1 + (b2 − a2 b0) u."""
    k = sos.shape[0]
    b0, b1, b2, a1, a2 = sos[:, 0], sos[:, 1], sos[:, 2], sos[:, 4], sos[:, 5]
    blocks = jnp.stack(
        [jnp.stack([-a1, jnp.ones_like(a1)], -1), jnp.stack([-a2, jnp.zeros_like(a2)], -1)], -2
    )
    eye = jnp.eye(k, dtype=jnp.float64)
    A = (eye[:, None, :, None] * blocks[:, :, None, :]).reshape(2 * k, 2 * k)
    B = jnp.stack([b1 - a1 * b0, b2 - a2 * b0], -1).reshape(2 * k)
    C = jnp.tile(jnp.array([1.0, 0.0]), k)
    return A, B, C, jnp.sum(b0)


class DiscreteFilter(eqx.Module):
    r"""A discrete filter of second-order sections: a parallel bank, then series stages,

        G(z) = (1 + Σ_p P_p(z)) · Π_q (Σ_k S_qk(z)),
        P, S = (b0 + b1 z⁻¹ + b2 z⁻²)/(1 + a1 z⁻¹ + a2 z⁻²).

    ``parallel_sos`` (p, 6) holds the peak filters' sections (Eq. (3)), each filtered on its
    own and summed with the input; ``series_sos`` (q, k, 6) the notches (Eq. (4)), stage q being
    the sum of its k sections: k = 1 for a Tustin design (``series_sos[:, 0]`` is then exactly
    what ``scipy.signal.sosfilt`` expects) and k = 2 for the fitted one (an FIR section plus a
    first-order-over-poles section, see ``AbstractFilter.discretize``). Rows are in scipy's sos
    layout [b0, b1, b2, 1, a1, a2] (rows with a0 ≠ 1 are normalised; a (q, 6) ``series_sos`` is
    read as q one-section stages). ``dt`` is the sample period (s). Usually made by
    ``PeakFilter/NotchFilter/MCM.discretize(dt)``.

    Each section is a direct form II transposed (scipy's convention), so the state is a
    (n_sections, 2) array, parallel rows first, then the stages in order: ``init_state()`` gives
    zeros, ``step(state, u_k)`` advances one sample, ``apply(u)`` runs ``lax.scan`` over a
    signal, and ``state_space()`` gives the same recursion as matrices.
    """

    parallel_sos: Float[Array, "p 6"]
    series_sos: Float[Array, "q k 6"]
    dt: Float[Array, ""]

    def __init__(self, parallel_sos: ArrayLike, series_sos: ArrayLike, dt: ArrayLike):
        par = _sos_array(parallel_sos, "DiscreteFilter(parallel_sos=...)")
        ser = _sos_array(series_sos, "DiscreteFilter(series_sos=...)", stages=True)
        dt = jnp.asarray(dt)
        if dt.ndim != 0 or jnp.issubdtype(dt.dtype, jnp.complexfloating):
            raise ValueError(
                "`DiscreteFilter(dt=...)` must be a real scalar, "
                f"got {dt.dtype} of shape {dt.shape}"
            )
        self.dt = positive(dt.astype(jnp.float64), "DiscreteFilter(dt=...)")
        self.parallel_sos = par / par[:, 3:4]
        self.series_sos = ser / ser[..., 3:4]

    @property
    def n_sections(self) -> int:
        """Number of second-order sections (rows of the state)."""
        q, k, _ = self.series_sos.shape
        return self.parallel_sos.shape[-2] + q * k

    def transfer(self, z: ArrayLike) -> Complex[Array, "*shape"]:
        """G(z) at complex ``z`` of any shape."""
        zi = 1 / _complex(z)
        parallel = 1 + jnp.sum(_section_response(self.parallel_sos, zi[..., None]), axis=-1)
        stages = jnp.sum(_section_response(self.series_sos, zi[..., None, None]), axis=-1)
        return parallel * jnp.prod(stages, axis=-1)

    def frf(self, freq_hz: ArrayLike) -> Complex[Array, " freq"]:
        """Frequency response G(e^{i 2π f dt}) on a positive, increasing grid ``freq_hz`` (Hz)."""
        f = frequency_grid(freq_hz, "DiscreteFilter.frf(freq_hz=...)")
        z = jnp.exp(_complex(2 * jnp.pi * f * self.dt) * 1j)
        return finite_output(self.transfer(z), "DiscreteFilter.frf(...)")

    def state_space(
        self,
    ) -> tuple[Float[Array, "n n"], Float[Array, " n"], Float[Array, " n"], Float[Array, ""]]:
        """(A, B, C, D) with s_{k+1} = A s_k + B u_k, y_k = C s_k + D u_k, in the DF2T states of
        ``step`` (flattened row by row): the same recursion as matrices, for a closed loop."""
        A, B, C, D = _sos_block_ss(self.parallel_sos)
        D = 1 + D
        for q in range(self.series_sos.shape[0]):
            A2, B2, C2, D2 = _sos_block_ss(self.series_sos[q])
            n, m = A.shape[0], A2.shape[0]
            A = jnp.block([[A, jnp.zeros((n, m))], [B2[:, None] * C[None, :], A2]])
            B = jnp.concatenate([B, B2 * D])
            C = jnp.concatenate([D2 * C, C2])
            D = D2 * D
        return A, B, C, D

    def init_state(self) -> Float[Array, "sections 2"]:
        """The zero initial state, shape (n_sections, 2), parallel sections first."""
        return jnp.zeros((self.n_sections, 2), jnp.float64)

    def step(
        self, state: Float[Array, "sections 2"], u_k: ArrayLike
    ) -> tuple[Float[Array, "sections 2"], Float[Array, ""]]:
        """One sample: (state, u_k) → (next state, y_k), for a closed loop run step by step.

        Direct form II transposed per section: y = b0 u + z0, z0' = b1 u − a1 y + z1,
        z1' = b2 u − a2 y. The parallel sections all see u_k and their outputs are added to u_k;
        the sum then passes through the series stages in order, each stage's sections seeing
        the stage input and their outputs summed.
        """
        u = jnp.asarray(u_k).astype(jnp.float64)
        P, S = self.parallel_sos, self.series_sos
        p = P.shape[0]
        zp, yp = _sos_step(P, state[:p], u)
        new = [zp]
        y = u + jnp.sum(yp)
        q, k, _ = S.shape
        for i in range(q):
            zq, yq = _sos_step(S[i], state[p + i * k : p + (i + 1) * k], y)
            new.append(zq)
            y = jnp.sum(yq)
        return jnp.concatenate(new, axis=0), y

    def apply(
        self, u: ArrayLike, state: Float[Array, "sections 2"] | None = None
    ) -> Float[Array, " time"]:
        """Filter a sampled signal ``u`` (1-D, period ``dt``) from ``state`` (zero by default).

        A ``lax.scan`` of ``step``: differentiable w.r.t. the filter and the signal.
        """
        u = jnp.asarray(u)
        if u.ndim != 1 or jnp.issubdtype(u.dtype, jnp.complexfloating):
            raise ValueError(
                f"`DiscreteFilter.apply(u=...)` must be a real 1-D signal, got {u.dtype} of "
                f"shape {u.shape}"
            )
        u = finite(u.astype(jnp.float64), "DiscreteFilter.apply(u=...)")
        if state is None:
            state = self.init_state()
        elif jnp.shape(state) != (self.n_sections, 2):
            raise ValueError(
                f"`DiscreteFilter.apply(state=...)` must have shape ({self.n_sections}, 2), "
                f"got {jnp.shape(state)}"
            )
        _, y = jax.lax.scan(lambda st, u_k: self.step(st, u_k), state, u)
        return y
