"""The paper's figures, each a function of results computed by fdjax (matplotlib, edge module).

Every function takes data (arrays and models), draws on a new figure and returns it, so the
numbers a figure shows are the numbers the caller computed.  Frequencies are shown in Hz and
positions in mm, as a dynamics engineer reads them.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")  # headless by default; figures are written to files

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402

from . import _checks  # noqa: E402
from ._drive._model import INPUTS, OUTPUTS  # noqa: E402
from ._results import RESULTS  # noqa: E402
from ._simulation import Simulation  # noqa: E402

__all__ = [
    "plot_three_mass_frf",
    "plot_deflection_shapes",
    "plot_velocity_nyquist",
    "plot_frf_family",
    "plot_frf_cloud",
    "plot_resonant_phase",
    "plot_peak_filter_effect",
    "plot_tracking",
    "stabilisation_diagram",
    "plot_rms_over_travel",
    "plot_convergence",
]

_OUT_LABEL = {"theta1": r"$\theta_1$", "x2": r"$x_2$", "x3": r"$x_3$"}
_IN_LABEL = {"T1": r"$T_1$", "F3": r"$F_3$"}
_UNITS = {
    ("theta1", "T1"): "rad/(N·m)", ("theta1", "F3"): "rad/N",
    ("x2", "T1"): "m/(N·m)", ("x2", "F3"): "m/N",
    ("x3", "T1"): "m/(N·m)", ("x3", "F3"): "m/N",
}


# -- the figures' arguments: checked before anything is drawn, named as the user called them --


def _vector(value, where: str, what: str) -> np.ndarray:
    """A 1-D, non-empty, finite real array (a scalar becomes one entry)."""
    arr = np.atleast_1d(np.asarray(_checks.numeric(value, where), dtype=float))
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"`{where}` must be {what}: a 1-D array of at least one value, got "
                         f"shape {arr.shape}")
    return _checks.check(arr, np.isfinite, where, f"{what}, finite")


def _frequencies(value, fn: str, name: str = "freq_hz") -> np.ndarray:
    """A frequency grid (Hz): 1-D, finite and positive."""
    f = _vector(value, f"{fn}({name}=...)", "frequencies in Hz")
    return _checks.check(f, lambda v: v > 0, f"{fn}({name}=...)", "positive (Hz)")


def _positions_m(value, fn: str, name: str = "position_m") -> np.ndarray:
    """Table positions (m): 1-D and finite; a value past the longest travel was given in mm
    and the message says so."""
    pos = _vector(value, f"{fn}({name}=...)", "table positions in m")
    _checks.at_most(pos, _checks.LONGEST_TRAVEL_M, f"{fn}({name}=...)",
                    "no ball-screw axis is longer")
    return pos


def _positions_mm(value, fn: str, name: str = "positions_mm") -> np.ndarray:
    """Table positions (mm): 1-D and finite; all within ±2 mm is a travel given in metres."""
    pos = _vector(value, f"{fn}({name}=...)", "table positions in mm")
    if pos.size > 1 and np.max(np.abs(pos)) <= 2.0:
        raise ValueError(f"`{fn}({name}=...)` must be table positions in mm, got values from "
                         f"{pos.min():.6g} to {pos.max():.6g}: positions in metres? "
                         f"{pos.max():.6g} m is {pos.max() * 1e3:.6g} mm")
    return pos


def _shaped(value, shape: tuple, where: str, names: str) -> np.ndarray:
    """An array of exactly ``shape`` (``names`` spells its axes, e.g. "(n_pos, n_freq)")."""
    arr = np.asarray(value)
    if arr.shape != tuple(shape):
        raise ValueError(f"`{where}` must have shape {names} = {tuple(shape)}, got {arr.shape}")
    return arr


def _response(value, shape: tuple, where: str, names: str) -> np.ndarray:
    """A frequency response of exactly ``shape``: numbers, finite and, as it is drawn on a log
    scale, non-zero (a NaN would be a gap in the curve, a zero −∞ dB)."""
    arr = _shaped(np.asarray(_checks.numeric(value, where)), shape, where, names)
    return _checks.check(arr, lambda v: np.isfinite(v) & (v != 0), where, "finite and non-zero")


def _band(value, fn: str):
    """An optional frequency band (f_lo, f_hi) in Hz, 0 < f_lo < f_hi."""
    if value is None:
        return None
    band = _vector(value, f"{fn}(band_hz=...)", "a band (f_lo, f_hi) in Hz")
    if band.size != 2 or not 0 < band[0] < band[1]:
        raise ValueError(f"`{fn}(band_hz=...)` must be (f_lo, f_hi) in Hz with 0 < f_lo < f_hi, "
                         f"got {_checks.fmt(band)}")
    return band


def plot_three_mass_frf(freq_hz, H, natural_hz=None):
    """Paper Fig. 2: magnitude and phase of h11, h21, h31 of the 3M2S system.

    Args:
        freq_hz: frequency grid (Hz).
        H: receptance (n_freq, 3, 3) from ``three_mass().frf``.
        natural_hz: optional natural frequencies to mark (Hz).
    """
    fn = "plot_three_mass_frf"
    f = _frequencies(freq_hz, fn)
    H = _response(H, (f.size, 3, 3), f"{fn}(H=...)", "(n_freq, 3, 3)")
    if natural_hz is not None:
        natural_hz = _vector(natural_hz, f"{fn}(natural_hz=...)", "natural frequencies in Hz")
    fig, axes = plt.subplots(2, 3, figsize=(12, 5.5), sharex=True)
    for k in range(3):
        h = H[:, k, 0]
        axes[0, k].loglog(f, np.abs(h), color="C0")
        axes[0, k].set_title(rf"$h_{{{k + 1}1}} = x_{k + 1}/F_1$")
        phase = np.degrees(np.unwrap(np.angle(h)))
        phase -= 360.0 * np.round((phase[0] + 180.0) / 360.0)  # rigid body at −180°
        axes[1, k].semilogx(f, phase, color="C1")
        axes[1, k].set_xlabel("frequency (Hz)")
        for ax in axes[:, k]:
            ax.grid(True, which="both", alpha=0.3)
            if natural_hz is not None:
                for fn in np.atleast_1d(natural_hz):
                    if fn > 0:
                        ax.axvline(fn, color="k", lw=0.6, ls=":")
    axes[0, 0].set_ylabel("|h| (m/N)")
    axes[1, 0].set_ylabel("phase (°)")
    fig.suptitle("3M2S receptances: collocated h11, non-collocated h21 and h31 (paper Fig. 2)")
    fig.tight_layout()
    return fig


def plot_deflection_shapes(shapes, labels):
    """Paper Fig. 3: operating deflection shapes of the 3M2S (one panel per shape).

    Args:
        shapes: real array (n_shapes, n_coordinates), each row one deflection shape (any scale;
            normalised here to unit peak so that signs and relative amplitudes show).
        labels: one title per shape, e.g. ``["rigid body", "103.7 Hz", "154.5 Hz"]``.
    """
    fn = "plot_deflection_shapes"
    shapes = np.asarray(_checks.numeric(shapes, f"{fn}(shapes=...)"))
    if np.iscomplexobj(shapes):
        raise ValueError(f"`{fn}(shapes=...)` must be real, got dtype {shapes.dtype}: a column "
                         "of the receptance at a resonance draws as its imaginary part (.imag), "
                         "below the first mode as its real part (.real)")
    shapes = shapes.astype(float)
    if shapes.ndim != 2 or shapes.size == 0:
        raise ValueError(f"`{fn}(shapes=...)` must have shape (n_shapes, n_coordinates), got "
                         f"{shapes.shape}")
    _checks.check(shapes, np.isfinite, f"{fn}(shapes=...)", "finite")
    peak = np.max(np.abs(shapes), axis=1)
    if np.any(peak == 0):
        raise ValueError(f"`{fn}(shapes=...)` must have a non-zero entry in every shape, got "
                         f"an all-zero row {int(np.argmin(peak))}")
    n, m = shapes.shape
    labels = list(labels)
    if len(labels) != n:
        raise ValueError(f"`{fn}(labels=...)` must hold one title per shape ({n}), got "
                         f"{len(labels)}")
    fig, axes = plt.subplots(1, n, figsize=(3.6 * n, 3.4), sharey=True)
    for k, ax in enumerate(np.atleast_1d(axes)):
        v = shapes[k] / np.max(np.abs(shapes[k]))
        v = v * (np.sign(v[0]) or 1.0)  # coordinate 1 (the actuator) drawn positive
        colors = ["C0" if x >= 0 else "C3" for x in v]
        ax.bar(np.arange(1, m + 1), v, color=colors)
        ax.axhline(0, color="k", lw=0.8)
        ax.set_xticks(np.arange(1, m + 1), [f"coord. {i}" for i in range(1, m + 1)])
        ax.set_title(labels[k])
        ax.grid(True, axis="y", alpha=0.3)
    np.atleast_1d(axes)[0].set_ylabel("normalised deflection (–)")
    fig.suptitle("Operating deflection shapes (paper Fig. 3): red = opposite sign to coordinate 1")
    fig.tight_layout()
    return fig


def plot_velocity_nyquist(freq_hz, h_collocated, h_noncollocated, *, labels=("v1/F1", "v2/F1")):
    """Paper Fig. 5: Nyquist plots of a collocated and a non-collocated velocity receptance.

    Velocity receptance is ``iω h``.  Collocated modes all draw their circles on one side;
    a non-collocated pair has circles on opposite sides.

    Args:
        freq_hz: frequency grid (Hz).
        h_collocated, h_noncollocated: displacement receptances on that grid (complex),
            shape (n_freq,).
        labels: the two panels' titles.
    """
    fn = "plot_velocity_nyquist"
    f = _frequencies(freq_hz, fn)
    h_collocated = _response(h_collocated, f.shape, f"{fn}(h_collocated=...)", "(n_freq,)")
    h_noncollocated = _response(h_noncollocated, f.shape, f"{fn}(h_noncollocated=...)",
                                "(n_freq,)")
    labels = list(labels) if not isinstance(labels, str) else [labels]
    if len(labels) != 2:
        raise ValueError(f"`{fn}(labels=...)` must hold two titles (collocated, "
                         f"non-collocated), got {len(labels)}")
    iw = 2j * np.pi * f
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6))
    for ax, h, lab in zip(axes, (h_collocated, h_noncollocated), labels):
        v = iw * np.asarray(h)
        ax.plot(v.real, v.imag, color="C0")
        ax.plot(v.real[0], v.imag[0], "o", color="C2", label=f"{f[0]:.0f} Hz")
        ax.plot(v.real[-1], v.imag[-1], "s", color="C3", label=f"{f[-1]:.0f} Hz")
        ax.axhline(0, color="k", lw=0.6)
        ax.axvline(0, color="k", lw=0.6)
        ax.set_aspect("equal", adjustable="datalim")
        ax.ticklabel_format(style="sci", scilimits=(0, 0))
        ax.set_xlabel("real (m/(N·s))")
        ax.set_ylabel("imaginary (m/(N·s))")
        ax.set_title(lab)
        ax.legend(fontsize=8)
        ax.grid(True, alpha=0.3)
    fig.suptitle("Velocity receptances: collocated vs non-collocated (paper Fig. 5)")
    fig.tight_layout()
    return fig


def plot_frf_family(position_m, freq_hz, H):
    """Paper Fig. 10: families of |H_M| for all six entries, one curve per table position.

    Args:
        position_m: table positions (m), shape (n_pos,).
        freq_hz: frequency grid (Hz), shape (n_freq,).
        H: ``drive.frf(position_m, freq_hz)``, shape (n_pos, n_freq, 3, 2).
    """
    fn = "plot_frf_family"
    pos, f, H = _positions_m(position_m, fn), _frequencies(freq_hz, fn), np.asarray(H)
    if H.ndim == 3:  # one position: drive.frf(0.3, f)[0]
        H = H[None]
    if H.shape != (pos.size, f.size, 3, 2):
        raise ValueError(f"`plot_frf_family(H=...)` must have shape (n_pos, n_freq, 3, 2) = "
                         f"({pos.size}, {f.size}, 3, 2), got {H.shape}")
    fig, axes = plt.subplots(3, 2, figsize=(11, 10), sharex=True)
    colors = plt.cm.viridis(np.linspace(0, 1, pos.size))
    for i, out in enumerate(OUTPUTS):
        for j, inp in enumerate(INPUTS):
            ax = axes[i, j]
            for p in range(pos.size):
                ax.loglog(f, np.abs(H[p, :, i, j]), color=colors[p], lw=0.9,
                          label=f"{pos[p] * 1e3:.0f} mm")
            ax.set_title(f"{_IN_LABEL[inp]} in, {_OUT_LABEL[out]} out")
            ax.set_ylabel(f"|h| ({_UNITS[(out, inp)]})")
            ax.grid(True, which="both", alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("frequency (Hz)")
    axes[0, 1].legend(title=r"$Y_{table}$", fontsize=7, ncol=2)
    fig.suptitle("Position-dependent dynamics H_M(Y_table, f) (paper Fig. 10)")
    fig.tight_layout()
    return fig


def plot_frf_cloud(
    position_m, freq_hz, h, *, title=None, units=None, accelerance=True, decades=5.0,
):
    """Paper Fig. 11: cloud image of one FRF magnitude over frequency × table position.

    By default the accelerance ``|ω² h|`` is shown: it removes the rigid-body 1/ω² slope so the
    modes at every frequency share one colour scale.

    Args:
        position_m: table positions (m), shape (n_pos,).
        freq_hz: frequency grid (Hz), shape (n_freq,).
        h: complex FRF entry, shape (n_pos, n_freq), e.g. ``drive.frf(...)[:, :, 1, 0]``.
        title: what is shown, for the title and the colour bar (default: h21's accelerance
            |ω² h21| = |ẍ2/T1|, or its receptance |h21| = |x2/T1| with ``accelerance=False``).
        units: its units (default: those of the default title).
        accelerance: multiply by ω² before plotting.
        decades: colour range below the maximum, in decades.
    """
    fn = "plot_frf_cloud"
    pos, f = _positions_m(position_m, fn), _frequencies(freq_hz, fn)
    if np.ndim(h) == 1 and pos.size == 1:  # one position: drive.frf(0.3, f)[0, :, 1, 0]
        h = np.asarray(h)[None]
    a = np.abs(_shaped(h, (pos.size, f.size), f"{fn}(h=...)", "(n_pos, n_freq)"))
    if title is None:
        title = "|ω² h21| = |ẍ2/T1|" if accelerance else "|h21| = |x2/T1|"
        units = units or ("m/(s²·N·m)" if accelerance else "m/(N·m)")
    if units is None:
        raise ValueError(f"`{fn}(units=...)` must be given with a title of your own, got None")
    if accelerance:
        a = a * (2 * np.pi * f[None, :]) ** 2
    top = np.nanmax(a) if np.any(np.isfinite(a)) else np.nan
    if not (np.isfinite(top) and top > 0):
        raise ValueError("`plot_frf_cloud(h=...)` must have a finite, non-zero entry to scale "
                         "the colours by")
    fig, ax = plt.subplots(figsize=(9, 5))
    norm = LogNorm(vmin=top * 10.0**-decades, vmax=top)
    mesh = ax.pcolormesh(f, pos * 1e3, a, norm=norm, shading="auto", cmap="magma")
    ax.set_xscale("log")
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel(r"table position $Y_{table}$ (mm)")
    fig.colorbar(mesh, ax=ax, label=f"{title} ({units})")
    ax.set_title(f"{title} over position and frequency (paper Fig. 11)")
    fig.tight_layout()
    return fig


def plot_resonant_phase(position_m, frequency_hz, phase_deg, *, title="h21 = x2/T1"):
    """Paper Fig. 12: resonant phase of tracked modes against table position.

    Args:
        position_m: table positions (m), shape (n_pos,).
        frequency_hz: tracked natural frequencies (n_pos, n_modes), used for the legend and a
            second panel showing how each mode's frequency moves.
        phase_deg: tracked resonant phases (n_pos, n_modes), degrees in (−360, 0].
    """
    fn = "plot_resonant_phase"
    pos = _positions_m(position_m, fn) * 1e3
    f = np.asarray(frequency_hz, float)
    if f.ndim == 1:  # one position's modes, or one mode at every position
        f = f[None] if pos.size == 1 else f[:, None]
    if f.ndim != 2 or f.shape[0] != pos.size or f.shape[1] == 0:
        raise ValueError(f"`{fn}(frequency_hz=...)` must have shape (n_pos, n_modes) with "
                         f"n_pos = {pos.size}, got {np.shape(frequency_hz)}")
    _checks.check(f, lambda v: np.isnan(v) | (np.isfinite(v) & (v > 0)),
                  f"{fn}(frequency_hz=...)", "positive and finite (Hz; NaN marks a mode "
                  "missing at a position)")
    ph = np.array(phase_deg, float)
    if ph.ndim == 1:
        ph = ph[None] if pos.size == 1 else ph[:, None]
    _shaped(ph, f.shape, f"{fn}(phase_deg=...)", "(n_pos, n_modes), as frequency_hz's")
    if not np.any(np.isfinite(ph)):
        raise ValueError("`plot_resonant_phase(phase_deg=...)` has no finite phase to plot")
    # phases are defined modulo 360°: unwrap along the position so curves do not jump (each
    # mode over the positions where it was found; NaN marks a mode missing there)
    for k in range(ph.shape[1]):
        ok = np.isfinite(ph[:, k])
        ph[ok, k] = np.unwrap(ph[ok, k], period=360.0)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.8))
    for k in range(f.shape[1]):
        label = f"mode {k + 1} ({np.nanmedian(f[:, k]):.0f} Hz)"
        ax1.plot(pos, ph[:, k], "o-", ms=3, label=label)
        ax2.semilogy(pos, f[:, k], "o-", ms=3, label=label)
    lo, hi = 45 * np.floor(np.nanmin(ph) / 45), 45 * np.ceil(np.nanmax(ph) / 45)
    ax1.set_ylim(lo - 10, hi + 10)
    ax1.set_yticks(np.arange(lo, hi + 1, 45))
    for ref in np.arange(-90 - 360 * 2, hi + 1, 180):
        if lo <= ref <= hi:
            ax1.axhline(ref, color="k", lw=0.6, ls=":")
    ax1.set_xlabel(r"table position $Y_{table}$ (mm)")
    ax1.set_ylabel("resonant phase (°)")
    ax1.set_title(f"Resonant phase of {title} (paper Fig. 12)\n"
                  "dotted: −90° (in phase) and −270° (out of phase), modulo 360°", fontsize=10)
    ax2.set_xlabel(r"table position $Y_{table}$ (mm)")
    ax2.set_ylabel("natural frequency (Hz)")
    ax2.set_title("Natural frequencies of the same modes")
    for ax in (ax1, ax2):
        ax.grid(True, which="both", alpha=0.3)
    ax1.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    return fig


def plot_peak_filter_effect(
    freq_hz, position_m, L_without, L_with, *, loop_label="speed loop $L_v$",
    radius=3.0, band_hz=None, filter_label="peak filter",
):
    """Paper Fig. 14: an open loop without and with a peak filter on the target mode, over
    several table positions ("with variation"): Nyquist plots and Bode magnitude and phase.

    The Nyquist panels (positive frequencies) are zoomed on the critical point −1, ``radius``
    around the origin, with the unit circle; the locus beyond is clipped.  The gain margin is
    read where the locus crosses the negative real axis, the phase margin where it crosses the
    unit circle, the modulus margin as its distance to −1.  The phase is unwrapped from the
    lowest frequency (shifted into (−270°, 90°] there).

    Args:
        freq_hz: frequency grid (Hz), shape (n_freq,).
        position_m: table positions (m), shape (n_pos,).
        L_without, L_with: the open loop on that grid without / with the peak filter,
            shape (n_pos, n_freq), e.g. the ``speed`` (or ``position``, ``plant_input``) loop
            of ``fdjax.open_loop(loop, H, freq_hz, method=fdjax.Continuous(),
            screw_ratio=drive.screw.ratio)`` on an FRF, or of ``fdjax.open_loop(loop, drive,
            freq_hz, position_m=...)`` (the sampled loop, below Nyquist).
        loop_label: which loop, for the title.
        radius: half-width of the Nyquist window.
        band_hz: optional (f_lo, f_hi) of the target mode's band, shaded on the Bode plots.
        filter_label: what the two cases differ by, for the titles ("peak filter", "MCM").
    """
    fn = "plot_peak_filter_effect"
    f, pos = _frequencies(freq_hz, fn), _positions_m(position_m, fn)
    Ls = [_response(np.atleast_2d(np.asarray(L)), (pos.size, f.size), f"{fn}({name}=...)",
                    "(n_pos, n_freq)") for L, name in ((L_without, "L_without"),
                                                       (L_with, "L_with"))]
    radius = float(_checks.positive(_checks.real_scalar(radius, f"{fn}(radius=...)"),
                                    f"{fn}(radius=...)"))
    band_hz = _band(band_hz, fn)
    if not isinstance(filter_label, str) or not filter_label:
        raise ValueError(f"`{fn}(filter_label=...)` must be a non-empty string, got "
                         f"{filter_label!r}")
    colors = plt.cm.viridis(np.linspace(0, 0.9, pos.size))
    fig = plt.figure(figsize=(12, 10))
    grid = fig.add_gridspec(3, 2, height_ratios=[2.2, 1.0, 1.0])
    nyq = [fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[0, 1])]
    mag = fig.add_subplot(grid[1, :])
    pha = fig.add_subplot(grid[2, :], sharex=mag)
    circle = np.exp(1j * np.linspace(0, 2 * np.pi, 361))
    titles = [f"without {filter_label}", f"with {filter_label}"]
    for ax, L, title in zip(nyq, Ls, titles):
        for p in range(pos.size):
            ax.plot(L[p].real, L[p].imag, color=colors[p], lw=1.1)
        ax.plot(circle.real, circle.imag, color="0.4", lw=0.8, ls="--", label="unit circle")
        ax.plot([-1], [0], "r+", ms=14, mew=2, label="critical point −1")
        ax.axhline(0, color="k", lw=0.5)
        ax.axvline(0, color="k", lw=0.5)
        ax.set_xlim(-radius, radius)
        ax.set_ylim(-radius, radius)
        ax.set_aspect("equal")
        ax.set_xlabel("Re L (–)")
        ax.set_ylabel("Im L (–)")
        ax.set_title(f"Nyquist, {title} (f > 0)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    for p in range(pos.size):
        for L, ls in zip(Ls, ("--", "-")):
            phase = np.degrees(np.unwrap(np.angle(L[p])))
            phase -= 360.0 * np.ceil((phase[0] - 90.0) / 360.0)
            mag.semilogx(f, 20 * np.log10(np.abs(L[p])), color=colors[p], ls=ls, lw=1.0)
            pha.semilogx(f, phase, color=colors[p], ls=ls, lw=1.0)
    mag.axhline(0, color="k", lw=0.8)
    lo, hi = pha.get_ylim()
    for k in range(int(np.floor((lo - 180) / 360)), int(np.ceil((hi - 180) / 360)) + 1):
        pha.axhline(180 + 360 * k, color="r", lw=0.8)  # −180° (mod 360°): phase crossover
    pha.set_ylim(lo, hi)
    if band_hz is not None:
        for ax in (mag, pha):
            ax.axvspan(*band_hz, color="orange", alpha=0.15, lw=0, label="target mode band")
    handles = [plt.Line2D([], [], color=colors[p], label=f"{pos[p] * 1e3:.0f} mm")
               for p in range(pos.size)]
    handles += [plt.Line2D([], [], color="k", ls="--", label=f"without {filter_label}"),
                plt.Line2D([], [], color="k", ls="-", label=f"with {filter_label}")]
    mag.legend(handles=handles, title=r"$Y_{table}$", fontsize=7, ncol=3, loc="lower left")
    mag.set_ylabel("|L| (dB)")
    pha.set_ylabel("arg L (°)")
    span = hi - lo
    pha.yaxis.set_major_locator(plt.MultipleLocator(90 if span <= 540 else 180 if span <= 1080
                                                    else 360))
    pha.set_xlabel("frequency (Hz)")
    for ax in (mag, pha):
        ax.grid(True, which="both", alpha=0.3)
    plt.setp(mag.get_xticklabels(), visible=False)
    what = filter_label[0].upper() + filter_label[1:]
    fig.suptitle(f"{what} on the target modes, {loop_label}, over the table travel "
                 "(paper Fig. 14)")
    fig.tight_layout()
    return fig


def plot_tracking(runs, *, title, tool=False):
    """Paper Figs. 16–17: tracking responses and errors of simulated runs.

    Top: the reference r and the scale position x2 (mm) over time.  Below, one panel per run
    with its own scale (the errors of different controllers differ by orders of magnitude):
    the scale error e2 = r − x2 (µm), its RMS in the legend, and the tool-point error
    e3 = r − x3 dashed when ``tool``.

    Args:
        runs: ``{label: Simulation}`` — results of :func:`fdjax.simulate` on the same reference,
            one run each.  A run that failed is drawn up to where it stopped, its title in red
            saying why (:attr:`fdjax.Simulation.message`), without an RMS.
        title: figure title (controller, position).
        tool: also draw the tool-point error.
    """
    fn = "plot_tracking"
    if not isinstance(runs, dict):
        raise TypeError(f"`{fn}(runs=...)` must be a dict {{label: Simulation}}, got "
                        f"{type(runs).__name__}")
    n = len(runs)
    if n == 0:
        raise ValueError("`plot_tracking(runs=...)` must hold at least one simulation")
    for label, sim in runs.items():
        if not isinstance(sim, Simulation):
            raise TypeError(f"`{fn}(runs=...)` must map labels to fdjax.simulate's results, "
                            f"got {type(sim).__name__} for {label!r}")
        if np.ndim(sim.t) != 1:
            raise ValueError(f"`{fn}(runs=...)` must hold one run per label, got a batch of "
                             f"shape {np.shape(sim.t)[:-1]} for {label!r}: index it, e.g. "
                             "jax.tree_util.tree_map(lambda x: x[i], runs)")
    fig, axes = plt.subplots(1 + n, 1, figsize=(10, 3.2 + 2.3 * n), sharex=True,
                             gridspec_kw=dict(height_ratios=[1.3] + [1.0] * n))
    ax_r = axes[0]
    colors = plt.cm.tab10(np.arange(n))
    first = next(iter(runs.values()))
    ax_r.plot(np.asarray(first.t), 1e3 * np.asarray(first.reference)[:, 0], color="k", lw=2.4,
              alpha=0.3, label="reference r")
    for ax_e, (label, sim), c in zip(axes[1:], runs.items(), colors):
        # a run stopped early (diverged, out of travel) is drawn up to where it stopped: its
        # outputs are held after; a failed run's RMS is not a tracking error, its title says why
        ok = bool(np.asarray(sim.result == RESULTS.successful))
        k = min(int(np.asarray(sim.failed_at)) + 1, np.size(sim.t))
        t = np.asarray(sim.t)[:k]
        e2 = np.asarray(sim.error_scale)[:k]
        rms = float(np.sqrt(np.mean(np.square(e2))))
        ax_r.plot(t, 1e3 * np.asarray(sim.x2)[:k], color=c, lw=1.0, label=f"{label}: $x_2$")
        ax_e.plot(t, 1e6 * e2, color=c, lw=1.0,
                  label=f"$e_2 = r - x_2$, RMS {rms * 1e6:.3g} µm" if ok else "$e_2 = r - x_2$")
        if tool:
            ax_e.plot(t, 1e6 * np.asarray(sim.error_tool)[:k], color=c, lw=0.8, ls="--",
                      label="$e_3 = r - x_3$")
        ax_e.axhline(0, color="k", lw=0.6)
        ax_e.set_ylabel("error (µm)")
        if ok:
            ax_e.set_title(label, fontsize=9, loc="left")
        else:
            ax_e.set_title(f"{label}: {sim.message}", fontsize=9, loc="left", color="C3")
        ax_e.legend(fontsize=8, loc="upper right")
    ax_r.set_ylabel("position (mm)")
    ax_r.legend(fontsize=8, loc="upper right")
    axes[-1].set_xlabel("time (s)")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def stabilisation_diagram(diagram, *, title="h21 = x2/T1"):
    """Stabilisation diagram (paper Sec. 3.2): poles over model orders, the FRF behind.

    Frequency on x (log), model order (pole pairs) on y; per pole a marker: ``+`` new or
    unstable, ``f`` stable in frequency only, ``o`` stable in frequency and damping (filled
    when also physical: inside the band, ζ below ``max_damping``). Vertical lines mark the
    modes selected (clusters of physical poles); a star marks the selected order's poles.
    The FRF magnitude (RMS over channels) is drawn on a twin axis behind.

    Args:
        diagram: a :class:`fdjax.StabilisationDiagram` from
            :func:`fdjax.stabilisation_diagram`.
        title: what the FRF is, for the title.
    """
    d = diagram
    f = np.asarray(d.frequency_hz)
    orders = np.asarray(d.orders)
    fig, ax = plt.subplots(figsize=(10, 5.5))
    ax_h = ax.twinx()
    ax_h.loglog(d.freq_hz, d.frf_magnitude, color="0.75", lw=1.2, zorder=0)
    ax_h.set_ylabel("|H| (RMS over channels)", color="0.5")
    ax.set_zorder(ax_h.get_zorder() + 1)
    ax.patch.set_visible(False)
    y = np.broadcast_to(orders[:, None], f.shape)
    ok = ~np.isnan(f)
    unstable = ok & ~np.asarray(d.stable_frequency)
    only_f = ok & np.asarray(d.stable_frequency) & ~np.asarray(d.stable)
    stable = ok & np.asarray(d.stable) & ~np.asarray(d.physical)
    phys = np.asarray(d.physical)
    ax.plot(f[unstable], y[unstable], "+", color="C3", ms=5, label="new / unstable")
    ax.plot(f[only_f], y[only_f], "x", color="C1", ms=4, label="stable frequency")
    ax.plot(f[stable], y[stable], "o", mfc="none", color="C0", ms=5,
            label="stable frequency and damping")
    ax.plot(f[phys], y[phys], "o", color="C0", ms=5, label="physical (in band, stable)")
    sel = d.selected_poles
    if sel is not None and len(sel):
        ax.plot(np.abs(sel) / (2 * np.pi), np.full(len(sel), orders[d.selected]), "*",
                color="k", ms=11, label=f"selected (order {orders[d.selected]})")
    for fm in np.asarray(d.mode_frequency_hz):
        ax.axvline(fm, color="k", lw=0.5, ls=":")
    ax.set_xscale("log")
    ax.set_xlim(d.freq_hz[0], d.freq_hz[-1])
    ax.set_ylim(0, orders[-1] + 1)
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("model order (pole pairs)")
    ax.set_title(f"Stabilisation diagram of {title}: {d.n_modes} modes "
                 f"(dotted), selected order {orders[d.selected]}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    return fig


def plot_rms_over_travel(positions_mm, results, *, labels=None, design_mm=(),
                         modulus_margin=0.5, title="RMS tracking error over the travel"):
    """Paper Fig. 18: RMS tracking error of each controller over the table position, and below
    its modulus margin (the sampled loop's least over the break points) against the
    requirement.  Unstable positions are marked × on the top edge of the RMS panel.

    Args:
        positions_mm: the positions (mm).
        results: ``{name: {"rms_error_um": [...], "stable": [...], "modulus_margin": [...]}}``
            (:func:`fdjax.evaluate`); RMS None where unstable.
        labels: ``{name: legend label}``.
        design_mm: the design positions of the local tunings (mm), drawn as dotted lines.
        modulus_margin: the requirement line.
    """
    fn = "plot_rms_over_travel"
    y = _positions_mm(positions_mm, fn)
    if not results:
        raise ValueError(f"`{fn}(results=...)` must hold at least one controller")
    for name, r in results.items():
        for key in ("rms_error_um", "stable", "modulus_margin"):
            if key not in r:
                raise ValueError(f"`{fn}(results=...)` must give {key!r} for every "
                                 f"controller, got none for {name!r}")
            if len(r[key]) != y.size:
                raise ValueError(f"`{fn}(results=...)` must give one {key!r} per position "
                                 f"({y.size}), got {len(r[key])} for {name!r}")
        if np.asarray(r["stable"]).dtype != bool:
            raise ValueError(f"`{fn}(results=...)` must give 'stable' as booleans, got "
                             f"{np.asarray(r['stable']).dtype} for {name!r}")
        rms = np.asarray([np.nan if v is None else v for v in r["rms_error_um"]], float)
        _checks.check(rms, lambda v: np.isnan(v) | (np.isfinite(v) & (v >= 0)),
                      f"{fn}(results=...)[{name!r}]['rms_error_um']",
                      "finite and non-negative (µm; None or NaN where unstable)")
    design_mm = _positions_mm(design_mm, fn, "design_mm") if len(design_mm) else ()
    fig, (ax, ax_m) = plt.subplots(2, 1, figsize=(10, 7.5), sharex=True,
                                   gridspec_kw=dict(height_ratios=[2.0, 1.0]))
    colors = plt.cm.tab10(np.arange(len(results)))
    values = np.concatenate([np.asarray([np.nan if v is None else v for v in r["rms_error_um"]],
                                        float) for r in results.values()])
    # every position unstable: no error to scale by, the × marks alone
    top = float(np.nanmax(values)) if np.any(np.isfinite(values)) else 1.0
    for (name, r), c in zip(results.items(), colors):
        label = (labels or {}).get(name, name)
        rms = np.asarray([np.nan if v is None else v for v in r["rms_error_um"]], float)
        ax.plot(y, rms, color=c, lw=1.6, label=label)
        bad = ~np.asarray(r["stable"], bool)
        if np.any(bad):
            ax.plot(y[bad], np.full(bad.sum(), 1.04 * top), "x", color=c, ms=6, clip_on=False)
        ax_m.plot(y, np.asarray(r["modulus_margin"], float), color=c, lw=1.3)
    for d in design_mm:
        for a in (ax, ax_m):
            a.axvline(d, color="k", lw=0.6, ls=":")
    ax_m.axhline(modulus_margin, color="r", lw=1.0, ls="--",
                 label=f"requirement {modulus_margin:g}")
    ax.set_ylabel("RMS error at the scale (µm)")
    ax.set_ylim(0, 1.08 * top)
    ax.legend(fontsize=8, loc="upper left")
    ax_m.set_ylabel("modulus margin")
    ax_m.set_xlabel("table position (mm)")
    ax_m.legend(fontsize=8, loc="lower left")
    for a in (ax, ax_m):
        a.grid(True, alpha=0.3)
    ax.set_title(title + " (× unstable; dotted: design positions)", fontsize=10)
    fig.tight_layout()
    return fig


def plot_convergence(curves, *, title="Convergence of the tunings"):
    """The objective against the optimiser step, one panel per tuning, one line per position
    (log scale).

    Args:
        curves: ``{label: (history, line labels or None)}``, history (steps,) or (steps, n).
    """
    fn = "plot_convergence"
    n = len(curves)
    if n == 0:
        raise ValueError(f"`{fn}(curves=...)` must hold at least one tuning")
    for label, (h, names) in curves.items():
        h = np.asarray(h, float)
        if h.ndim not in (1, 2) or h.shape[0] == 0:
            raise ValueError(f"`{fn}(curves=...)` must give a history of shape (steps,) or "
                             f"(steps, n), got {h.shape} for {label!r}")
        lines = 1 if h.ndim == 1 else h.shape[1]
        if names is not None and len(names) != lines:
            raise ValueError(f"`{fn}(curves=...)` must give one line label per column of the "
                             f"history ({lines}), got {len(names)} for {label!r}")
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.8), squeeze=False)
    for ax, (label, (h, names)) in zip(axes[0], curves.items()):
        h = np.asarray(h, float)
        h = h[:, None] if h.ndim == 1 else h
        for k in range(h.shape[1]):
            ax.semilogy(np.arange(1, h.shape[0] + 1), h[:, k], lw=1.0,
                        label=None if names is None else names[k])
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("step")
        ax.grid(True, which="both", alpha=0.3)
        if names is not None:
            ax.legend(fontsize=7)
    axes[0][0].set_ylabel("objective J")
    fig.suptitle(title)
    fig.tight_layout()
    return fig
