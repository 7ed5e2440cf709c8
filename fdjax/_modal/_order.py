r"""The model order from a stabilisation diagram (paper Sec. 3.2, Table 1).

A measured FRF does not say how many modes it holds. Modal-analysis practice (e.g. the
stabilisation charts of LSCF/PolyMAX, Peeters et al. 2004, Shock Vib. 11) fits it at
increasing orders and keeps the poles that stay put: a physical pole appears at the same
frequency and damping at every order once the order is high enough, while poles that fit
noise, leakage or out-of-band dynamics wander from order to order.

:func:`stabilisation_diagram` fits, for :math:`n = 1, \dots, n_\text{max}` pole pairs (plus
``real_poles`` real ones),

.. math::

    H_k(s) \approx \sum_{j} \frac{r_{jk}}{s-p_j} + \frac{c_{0k}}{s^2} + \frac{c_{1k}}{s} + d_k

by vector fitting (Gustavsen & Semlyen 1999, relaxed form Gustavsen 2006; the same linear
step as stage 1 of :func:`fdjax.identify_modes`), here with a *free* split of the
:math:`2n + n_r` poles into real poles and complex pairs: a relocation keeps a zero of
:math:`\sigma` real when it is real. So the damped rigid body of a drive on damped guideways,
:math:`x_2/T_1 \to i_{sc}/(s(J_\text{eq}s + c_\text{eq}))`, a pole at :math:`s=0` and a real
pole at :math:`-c_\text{eq}/J_\text{eq}`, is fitted as what it is and does not bend a
complex pair (mode 1) into it.

A pole pair of order :math:`n` is *stable* when order :math:`n-1` has a pair within
``freq_tol`` (relative) in natural frequency and ``damping_tol`` (relative) in damping ratio,
and *physical* when it is stable, inside the band and :math:`\zeta < ` ``max_damping``. The
*modes* are the clusters (within ``freq_tol``, one pole per order) of the converged orders'
in-band poles that are stable in frequency, with ``min_orders`` members or more of which one
is physical; the *selected order* is the lowest converged one (fit error within 1.5×
the smallest, or below 1e-3) that holds a pole of every cluster. This is a discrete choice
on concrete data: it runs eagerly in NumPy (each order a different size) and is not
jit-able; the refinement of the selected poles (:func:`fdjax.identify_modes`) is.
"""

from __future__ import annotations

import equinox as eqx
import numpy as np
from jaxtyping import ArrayLike, Complex, Float

from .._checks import static_int
from ._data import _check_inputs, _prepare

# A zero of σ whose imaginary part is below this fraction of its modulus is a real pole.
_REAL_TOL = 1e-6


def _np_basis(s, pr, pc, rigid_body, upper_residual):
    """Columns ψ_a = 1/(s^b (s−a)) (real a, b = rigid_body), the pair columns of each
    complex p, then s⁻², s⁻¹ and 1 (the fixed ones); as ``_linear._basis``."""
    cols = [1.0 / (s[:, None] - pr[None, :]) / s[:, None] ** rigid_body]
    g = 1.0 / (s[:, None] - pc[None, :])
    gc = 1.0 / (s[:, None] - np.conj(pc)[None, :])
    cols.append(np.stack([g + gc, 1j * (g - gc)], axis=-1).reshape(s.shape[0], -1))
    fixed = [s**-2, s**-1][2 - rigid_body:] + ([np.ones_like(s)] if upper_residual else [])
    cols.append(np.stack(fixed, axis=1) if fixed else np.zeros((s.shape[0], 0), complex))
    return np.concatenate(cols, axis=1)


def _ri(x):
    return np.concatenate([x.real, x.imag], axis=0)


def _np_vf_iteration(pr, pc, s, h, w, rigid_body, upper_residual):
    """One relaxed vector-fitting relocation of real poles ``pr`` and pairs ``pc``."""
    n_freq = s.shape[0]
    nr, nc = pr.shape[0], pc.shape[0]
    num = _np_basis(s, pr, pc, rigid_body, upper_residual)
    sig = np.concatenate([1.0 / (s[:, None] - pr[None, :]), num[:, nr : nr + 2 * nc],
                          np.ones((n_freq, 1))], axis=1)
    sig_scale = np.sqrt(np.sum(np.abs(sig) ** 2, axis=0))
    m0 = num.shape[1]
    blocks = []
    for k in range(h.shape[1]):
        a = w[:, k, None] * num
        a = a / np.sqrt(np.sum(np.abs(a) ** 2, axis=0))
        b = -(w[:, k] * h[:, k])[:, None] * sig / sig_scale
        # fast VF (Deschrijver et al. 2008): σ's rows of the QR of [numerator | σ] per channel
        r = np.linalg.qr(_ri(np.concatenate([a, b], axis=1)), mode="r")
        blocks.append(r[m0:, m0:])
    row_w = np.sqrt(np.sum((w * np.abs(h)) ** 2) / h.shape[1]) / n_freq
    con = row_w * np.sum(sig.real, axis=0) / sig_scale
    lhs = np.concatenate(blocks + [con[None]], axis=0)
    rhs = np.zeros(lhs.shape[0])
    rhs[-1] = row_w * n_freq
    c = np.linalg.lstsq(lhs, rhs, rcond=None)[0] / sig_scale
    d = c[-1] if abs(c[-1]) >= 1e-8 else np.copysign(1e-8, c[-1])
    rc = (c[nr : nr + 2 * nc : 2] + 1j * c[nr + 1 : nr + 2 * nc : 2]) / d
    a_all = np.concatenate([pr + 0j, pc, np.conj(pc)])
    r_all = np.concatenate([c[:nr] / d + 0j, rc, np.conj(rc)])
    z = np.linalg.eigvals(np.diag(a_all) - r_all[None, :])
    z = -np.abs(z.real) + 1j * z.imag  # unstable zeros reflected
    real = np.abs(z.imag) <= _REAL_TOL * np.abs(z)
    tiny = 1e-8 * np.max(np.abs(z))
    zr = np.minimum(z[real].real, -tiny)
    zc = z[~real & (z.imag > 0)]
    zc = zc.real.clip(max=-1e-7 * np.abs(zc)) + 1j * zc.imag
    return np.sort(zr)[::-1], zc[np.argsort(np.abs(zc))]


def _np_fit_error(pr, pc, s, h, w, rigid_body, upper_residual):
    """RMS weighted residual of the linear fit for given poles, relative to ‖w h‖."""
    a = _np_basis(s, pr, pc, rigid_body, upper_residual)
    res2 = tot2 = 0.0
    for k in range(h.shape[1]):
        ak, bk = _ri(w[:, k, None] * a), _ri(w[:, k] * h[:, k])
        scale = np.sqrt(np.sum(ak**2, axis=0))
        x = np.linalg.lstsq(ak / scale, bk, rcond=None)[0]
        res2 += np.sum((bk - (ak / scale) @ x) ** 2)
        tot2 += np.sum(bk**2)
    return float(np.sqrt(res2 / tot2))


def _np_real_contributions(pr, pc, s, h, w, rigid_body, upper_residual):
    """‖w Q_j/(s − a_j)‖ summed over channels, for each real pole a_j of a linear fit."""
    a = _np_basis(s, pr, pc, rigid_body, upper_residual)
    out = np.zeros(pr.shape[0])
    for k in range(h.shape[1]):
        ak, bk = _ri(w[:, k, None] * a), _ri(w[:, k] * h[:, k])
        x = np.linalg.lstsq(ak, bk, rcond=None)[0]
        out += np.sqrt(np.sum((ak[:, : pr.shape[0]] * x[None, : pr.shape[0]]) ** 2, axis=0))
    return out


def _np_vector_fit(omega, n_pairs, n_real, s, h, w, iterations, rigid_body, upper_residual):
    lo = np.log(max(omega[0], omega[-1] * 1e-4))
    hi = np.log(omega[-1])
    beta = np.exp(lo + (hi - lo) * (np.arange(n_pairs) + 0.5) / n_pairs)
    pc = -0.01 * beta + 1j * beta
    pr = -omega[0] * 10.0 ** (-0.5 * np.arange(n_real))
    for _ in range(iterations):
        pr, pc = _np_vf_iteration(pr, pc, s, h, w, rigid_body, upper_residual)
    return pr, pc


class StabilisationDiagram(eqx.Module):
    r"""Poles over model orders and the order selected from them (paper Sec. 3.2).

    Returned by :func:`stabilisation_diagram`; :func:`fdjax.plots.stabilisation_diagram`
    draws it. Pole arrays have one row per order, padded with NaN (frequencies in Hz, poles
    in rad/s, complex pairs in the upper half plane only).

    **Fields:**

    - ``freq_hz``, ``frf_magnitude``: the data's grid and the RMS over channels of
      :math:`|H|`, to draw behind the poles.
    - ``orders``: pole pairs of the vector fit at each order, shape ``(n_orders,)``.
    - ``poles``: the complex poles (pairs, upper half plane) of each order,
      ``(n_orders, max_pairs)``.
    - ``frequency_hz``, ``damping_ratio``: :math:`|p|/2\pi` and :math:`-\mathrm{Re}\,p/|p|`.
    - ``stable_frequency``: order n−1 holds a pole within ``freq_tol`` in frequency.
    - ``stable``: … and within ``damping_tol`` in damping ratio.
    - ``physical``: stable, inside the band and :math:`\zeta <` ``max_damping``.
    - ``real_poles``: the real poles of each order (rad/s), ``(n_orders, max_real)``.
    - ``fit_error``: RMS weighted relative residual of each order's fit.
    - ``mode_frequency_hz``, ``mode_damping_ratio``: the modes (clusters of physical poles
      seen at ``min_orders`` orders or more), cluster medians.
    - ``selected``: index into ``orders`` of the selected order.
    - ``selected_poles``: its poles that start the refinement: one per mode (upper half
      plane, rad/s), in the order of ``mode_frequency_hz``.
    - ``background_poles``: its pairs outside the band with :math:`\zeta <` ``max_damping``
      (kept in the refined model, for their influence on the band).
    - ``selected_real_poles``: its real poles (rad/s).
    """

    freq_hz: np.ndarray
    frf_magnitude: np.ndarray
    orders: np.ndarray
    poles: np.ndarray
    frequency_hz: np.ndarray
    damping_ratio: np.ndarray
    stable_frequency: np.ndarray
    stable: np.ndarray
    physical: np.ndarray
    real_poles: np.ndarray
    fit_error: np.ndarray
    mode_frequency_hz: np.ndarray
    mode_damping_ratio: np.ndarray
    selected: int = eqx.field(static=True)
    selected_poles: np.ndarray = None
    background_poles: np.ndarray = None
    selected_real_poles: np.ndarray = None

    @property
    def n_modes(self) -> int:
        """Number of modes found (clusters of physical poles)."""
        return int(self.mode_frequency_hz.shape[0])


def _match(f_a, z_a, f_b, z_b, freq_tol, damping_tol):
    """For each pole a, whether some pole b is within the tolerances (and which)."""
    if f_b.size == 0 or f_a.size == 0:
        return np.zeros(f_a.shape, bool), np.zeros(f_a.shape, int)
    df = np.abs(f_a[:, None] - f_b[None, :]) / f_a[:, None]
    dz = np.abs(z_a[:, None] - z_b[None, :]) / np.maximum(z_a[:, None], 1e-12)
    j = np.argmin(df, axis=1)
    ok_f = df[np.arange(f_a.size), j] <= freq_tol
    ok = ok_f & (dz[np.arange(f_a.size), j] <= damping_tol)
    return ok_f, ok


def _diagram(freq_hz, frf_abs, s, h, w, omega_ref, *, max_modes, real_poles, rigid_body,
             upper_residual, iterations, freq_tol, damping_tol, max_damping, min_orders):
    """The stabilisation diagram of the scaled data (s = iω/ω_ref, as ``_prepare`` makes)."""
    omega = np.imag(s)
    band = (freq_hz[0], freq_hz[-1])  # the whole grid's band, also when s is decimated
    fits = []
    for n in range(1, max_modes + 1):
        try:
            pr, pc = _np_vector_fit(omega, n, real_poles, s, h, w, iterations, rigid_body,
                                    upper_residual)
            err = _np_fit_error(pr, pc, s, h, w, rigid_body, upper_residual)
        except (np.linalg.LinAlgError, FloatingPointError):
            # a relocation that broke down (a singular system): this order has no poles
            pr, pc, err = np.zeros(0), np.zeros(0, complex), np.inf
        fits.append((pr * omega_ref, pc * omega_ref, err))
        # Stop once the last max(min_orders, 2) + 4 orders have all converged (see below):
        # a weak, heavily damped mode (the drive's 49 Hz mode is 8 % of its FRF) settles a
        # few orders after the fit has reached the noise floor.
        e = np.array([f[2] for f in fits])
        n_last = max(min_orders, 2) + 4
        last = e[-n_last:]
        if e.size >= n_last and np.all((last <= 1.5 * e.min()) | (last <= 1e-3)):
            break
    orders = np.arange(1, len(fits) + 1)
    n_o = len(fits)
    max_c = max(1, max(len(p[1]) for p in fits))
    max_r = max(1, max(len(p[0]) for p in fits))
    poles = np.full((n_o, max_c), np.nan + 0j)
    rp = np.full((n_o, max_r), np.nan)
    for i, (pr, pc, _) in enumerate(fits):
        poles[i, : len(pc)] = pc
        rp[i, : len(pr)] = pr
    fhz = np.abs(poles) / (2 * np.pi)
    zeta = -poles.real / np.abs(poles)
    stable_f = np.zeros(poles.shape, bool)
    stable = np.zeros(poles.shape, bool)
    for i in range(1, n_o):
        a, b = ~np.isnan(fhz[i]), ~np.isnan(fhz[i - 1])
        ok_f, ok = _match(fhz[i, a], zeta[i, a], fhz[i - 1, b], zeta[i - 1, b], freq_tol,
                          damping_tol)
        stable_f[i, a], stable[i, a] = ok_f, ok
    in_band = (fhz >= band[0]) & (fhz <= band[1])
    # Orders whose fit has converged: within 1.5× the smallest error (the noise floor), or
    # below 1e-3. Poles of lower orders are biased by the modes still missing.
    err = np.array([e for *_, e in fits])
    converged = (err <= 1.5 * err.min()) | (err <= 1e-3)
    physical = stable & in_band & (zeta < max_damping) & converged[:, None]

    # Clusters over the orders, greedy in frequency (one pole per order), of the converged
    # orders' poles in the band with ζ < max_damping that are stable in frequency; a cluster
    # is a mode when it has min_orders members and one of them is physical (stable in damping
    # too). A heavily damped, weak mode under noise (the drive's 49 Hz mode, 8 % of its FRF,
    # ζ = 0.14, at 1 % noise) keeps its frequency from order to order better than 5 % in ζ.
    # A pole that the next order's stable pole matches starts that stable chain: a member
    # too (under noise, spare poles of higher orders may split a weak mode again).
    starts = np.zeros(poles.shape, bool)
    for i in range(n_o - 1):
        a, b = ~np.isnan(fhz[i]), ~np.isnan(fhz[i + 1])
        ok_f, _ = _match(fhz[i, a], zeta[i, a], fhz[i + 1, b], zeta[i + 1, b], freq_tol,
                         damping_tol)
        starts[i, a] = ok_f
    member = (stable_f | starts) & in_band & (zeta < max_damping) & converged[:, None]
    idx = np.argwhere(member)
    order_f = np.argsort(fhz[member])
    clusters: list[list[tuple[int, int]]] = []
    for i, j in idx[order_f]:
        for c in clusters:
            fc = np.median([fhz[a, b] for a, b in c])
            if abs(fhz[i, j] - fc) <= freq_tol * fc and all(a != i for a, _ in c):
                c.append((i, j))
                break
        else:
            clusters.append([(i, j)])
    clusters = [c for c in clusters if len(c) >= min(min_orders, int(converged.sum()))
                and any(physical[a, b] for a, b in c)]
    # A spare pole placed on a mode (a doublet, one pole with a negligible residue) makes a
    # second cluster at the same frequency and damping: keep the larger one.
    clusters.sort(key=len, reverse=True)
    merged: list[list[tuple[int, int]]] = []
    for c in clusters:
        fc = np.median([fhz[a, b] for a, b in c])
        zc = np.median([zeta[a, b] for a, b in c])
        if not any(abs(np.median([fhz[a, b] for a, b in m]) - fc) <= freq_tol * fc
                   and abs(np.median([zeta[a, b] for a, b in m]) - zc) <= damping_tol * zc
                   for m in merged):
            merged.append(c)
    clusters = merged
    mode_f = np.array([np.median([fhz[a, b] for a, b in c]) for c in clusters])
    mode_z = np.array([np.median([zeta[a, b] for a, b in c]) for c in clusters])
    srt = np.argsort(mode_f)
    clusters = [clusters[k] for k in srt]
    mode_f, mode_z = mode_f[srt], mode_z[srt]

    # The selected order: the lowest converged one with a pole of every cluster.
    # (a pole of the cluster stable against the order before: a chain's first pole is a
    # member but not yet settled)
    has_all = np.array([all(any(a == i and stable_f[a, b] for a, b in c) for c in clusters)
                        for i in range(n_o)])
    cand = np.flatnonzero(has_all & converged)
    if cand.size == 0:
        has_any = np.array([all(any(a == i for a, _ in c) for c in clusters)
                            for i in range(n_o)])
        cand = np.flatnonzero(has_any & converged)
    if cand.size == 0:
        cand = np.flatnonzero(converged)
    sel = int(cand[0])
    chosen = []
    for c in clusters:
        js = sorted((b for a, b in c if a == sel), key=lambda b: not stable_f[sel, b])
        chosen.append(poles[sel, js[0]] if js else poles[c[-1][0], c[-1][1]])
    # Its pairs above the band (not modes, but their influence on the band's upper edge is
    # not a constant) stay in the refined model; below the band the real poles and the
    # rigid-body terms model the background.
    bg = [poles[sel, j] for j in range(max_c)
          if not np.isnan(fhz[sel, j]) and fhz[sel, j] > band[1] and zeta[sel, j] < max_damping]
    # Its real_poles real poles of largest contribution ‖w Q/(s − a)‖ to the fit.
    pr_sel = rp[sel][~np.isnan(rp[sel])] / omega_ref
    pc_sel = poles[sel][~np.isnan(fhz[sel])] / omega_ref
    contrib = _np_real_contributions(pr_sel, pc_sel, s, h, w, rigid_body, upper_residual)
    real_sel = pr_sel[np.argsort(-contrib)[:real_poles]] * omega_ref
    return StabilisationDiagram(
        freq_hz=np.asarray(freq_hz),
        frf_magnitude=np.asarray(frf_abs),
        orders=orders,
        poles=poles,
        frequency_hz=fhz,
        damping_ratio=zeta,
        stable_frequency=stable_f,
        stable=stable,
        physical=physical,
        real_poles=rp,
        fit_error=err,
        mode_frequency_hz=mode_f,
        mode_damping_ratio=mode_z,
        selected=sel,
        selected_poles=np.asarray(chosen, complex),
        background_poles=np.asarray(bg, complex),
        selected_real_poles=real_sel,
    )


def _check_tol(value, name, fn):
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"`{fn}({name}=...)` must be a number, got {value!r}") from None
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"`{fn}({name}=...)` must be finite and positive, got {value}")
    return value


_DEFAULT_MAX_MODES = 16
# Largest grid the diagram's vector fits use (longer ones are decimated).
_DIAGRAM_POINTS = 2500


def _order_options(fn, n_freq, n_fixed, max_modes, vf_iterations, freq_tol, damping_tol,
                   max_damping, min_orders):
    # vector fitting at n pairs solves 2·n_freq equations for 4n + n_r + n_fixed + 1 unknowns
    cap = max(1, (2 * n_freq - n_fixed - 2) // 4 - 1)
    if max_modes is None:
        max_modes = min(_DEFAULT_MAX_MODES, cap)
    max_modes = static_int(max_modes, f"{fn}(max_modes=...)", 1, cap)
    return dict(
        max_modes=max_modes,
        iterations=static_int(vf_iterations, f"{fn}(vf_iterations=...)", 1),
        freq_tol=_check_tol(freq_tol, "freq_tol", fn),
        damping_tol=_check_tol(damping_tol, "damping_tol", fn),
        max_damping=_check_tol(max_damping, "max_damping", fn),
        min_orders=static_int(min_orders, f"{fn}(min_orders=...)", 1),
    )


def stabilisation_diagram(
    freq_hz: Float[ArrayLike, " freq"],
    frf: Complex[ArrayLike, " freq *channel"],
    *,
    max_modes: int | None = None,
    real_poles: int = 1,
    rigid_body: int = 2,
    upper_residual: bool = True,
    weights=None,
    vf_iterations: int = 10,
    freq_tol: float = 0.01,
    damping_tol: float = 0.05,
    max_damping: float = 0.5,
    min_orders: int = 2,
) -> StabilisationDiagram:
    r"""Stabilisation diagram of an FRF: poles fitted at orders 1 … ``max_modes`` pairs.

    At every order :math:`n` vector fitting (``vf_iterations`` relocations from pairs
    spread logarithmically over the band and ``real_poles`` real poles below it) fits

    .. math::

        H_k(s) \approx \sum_{j=1}^{2n+n_r} \frac{r_{jk}}{s-p_j} + \frac{c_{0k}}{s^2}
        + \frac{c_{1k}}{s} + d_k ,

    the :math:`2n + n_r` poles splitting freely into real ones and complex pairs. A pair is
    *stable* when the previous order has one within ``freq_tol`` (relative frequency) and
    ``damping_tol`` (relative damping ratio), *physical* when also inside the band with
    :math:`\zeta <` ``max_damping``; modes are clusters of physical poles seen at
    ``min_orders`` orders or more (see the module docstring; paper
    Sec. 3.2, Table 1). ``freq_hz``, ``frf``, ``weights``, ``rigid_body`` and
    ``upper_residual`` are those of :func:`fdjax.identify_modes`. Eager (NumPy): the order is
    a discrete choice on concrete data. ``max_modes`` defaults to 16 pairs (fewer on short
    grids).

    **Returns:** a :class:`StabilisationDiagram`; draw it with
    :func:`fdjax.plots.stabilisation_diagram`.
    """
    fn = "stabilisation_diagram"
    freq_hz, frf, weights, _, static = _check_inputs(
        fn, 0, freq_hz, frf, 1, rigid_body, upper_residual, weights, None, vf_iterations, 0,
        1, real_poles,
    )
    rigid_body, upper_residual, _, _, _, real_poles = static
    opts = _order_options(fn, freq_hz.shape[0], rigid_body + int(upper_residual) + real_poles,
                          max_modes, vf_iterations, freq_tol, damping_tol, max_damping,
                          min_orders)
    return _diagram_of(freq_hz, frf, weights, real_poles, rigid_body, upper_residual, opts)


def _diagram_of(freq_hz, frf, weights, real_poles, rigid_body, upper_residual, opts):
    s, h, w, _, omega_ref = _prepare(freq_hz, frf, weights)
    n_freq = freq_hz.shape[0]
    frf_abs = np.sqrt(np.mean(np.abs(np.asarray(frf).reshape(n_freq, -1)) ** 2, axis=1))
    # The diagram needs the poles only to start the refinement (which uses every point): on
    # long grids every k-th point keeps its cost bounded (k ≤ 4 at 10 000 points).
    step = -(-n_freq // _DIAGRAM_POINTS)
    keep = np.arange(0, n_freq, step)
    s, h, w = (np.asarray(x)[keep] for x in (s, h, w))
    return _diagram(np.asarray(freq_hz), frf_abs, s, h, w, float(omega_ref),
                    real_poles=real_poles, rigid_body=rigid_body,
                    upper_residual=upper_residual, **opts)
