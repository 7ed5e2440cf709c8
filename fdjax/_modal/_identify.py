r"""Modal identification from an FRF, at one position or over a sweep (paper Sec. 3.2).

:func:`identify_modes` fits

.. math::

    H_k(i\omega) \approx \sum_{r=1}^{n} \Big(\frac{R_{rk}}{i\omega-\lambda_r}
    + \frac{R_{rk}^*}{i\omega-\lambda_r^*}\Big) + \frac{c_{0k}}{(i\omega)^2}
    + \frac{c_{1k}}{i\omega} + d_k

by minimising :math:`\sum_{f,k} |w_{fk}(H^\text{fit}_k - H_k)(f)|^2`: the data are scaled
(:math:`\tilde s = i\omega/\omega_\text{ref}`, channels and weights at unit RMS, which leaves
the minimiser unchanged), vector fitting gives the start (``_vector_fit``), the
variable-projection Levenberg–Marquardt refinement the optimum (``_solver``), and the modal
quantities are returned in SI units as a :class:`ModalFit`. :func:`identify_modes_batched`
runs the same over a sweep of table positions in one jitted program.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import ArrayLike, Complex, Float

from .._checks import (
    is_concrete,
    static_bool,
    static_int,
    to_complex,
)
from .._sweep import map_positions
from ._data import _check_inputs, _prepare
from ._fit import _TWO_PI, ModalFit, _wrap_phase_deg
from ._linear import _cplx, _linear_fit, _real_residues
from ._order import StabilisationDiagram, _diagram_of, _order_options
from ._solver import (
    _DEFAULT_SOLVER,
    _poles_from_params,
    _real_from_params,
    _scaled_residual,
    _varpro_jacobian,
)
from ._vector_fit import (
    _real_start,
    _select_modes,
    _starting_poles,
    _upper_poles,
    _vector_fit,
)

# Vector-fitting relocations with the selected n_modes poles, after the over-sized stage.
_VF_FINAL_ITERATIONS = 5


class _Model(eqx.Module):
    n_modes: int = eqx.field(static=True)
    rigid_body: int = eqx.field(static=True)
    upper_residual: bool = eqx.field(static=True)
    channel_shape: tuple[int, ...] = eqx.field(static=True)
    real_poles: int = eqx.field(static=True, default=0)


# The work is split into three jitted stages (the data's scaling, ``_data._prepare``, then
# ``_start`` and ``_finish``) so that calls that differ only in the start (vector fitting or
# ``initial=``) or in ``refine`` share compiled code; under a user's jit/vmap/grad they trace
# into one program as usual.


@eqx.filter_jit
def _start(s, h, w, model: _Model, iterations: int, extra: int):
    """Vector fitting with n_modes + extra pairs, backward elimination to n_modes, and a
    few relocations of the kept poles alone (which settle what the removed ones shared)."""
    rb, ur = model.rigid_body, model.upper_residual
    p0 = (_starting_poles(jnp.imag(s), model.n_modes + extra),
          _real_start(jnp.imag(s), model.real_poles))
    p0 = _vector_fit(p0, s, h, w, iterations, rb, ur)
    p0 = _select_modes(p0, s, h, w, model.n_modes, rb, ur)
    return _vector_fit(p0, s, h, w, _VF_FINAL_ITERATIONS, rb, ur)


@eqx.filter_jit
def _finish(s, h, w, h_scale, omega_ref, p0, solver, model: _Model, refine: bool,
            max_steps: int, throw: bool) -> ModalFit:
    """Refinement from the scaled start poles p0, then the modal quantities in SI units."""
    n, n_r = model.n_modes, model.real_poles
    rb, ur = model.rigid_body, model.upper_residual
    p0, r0 = p0
    p0 = jax.lax.stop_gradient(_upper_poles(p0, n))
    r0 = jax.lax.stop_gradient(-jnp.maximum(jnp.abs(r0), 1e-8))
    if refine:
        args = ((p0, r0), s, h, w, rb, ur)
        u0 = (jnp.zeros((n, 2)), jnp.zeros((n_r,)))
        # Marquardt scaling (as MINPACK's): parameters in units of the start Jacobian's column
        # norms, so that the damping μI of LM is isotropic; a fixed gain on the residual makes
        # μ = 1 (optimistix's first trust-region step) small against JᵀJ, so that the first
        # steps from the (already close) vector-fitting start are Gauss–Newton steps.
        _, (ju0, jv0) = _varpro_jacobian(u0, (p0, r0), *jax.lax.stop_gradient((s, h, w)), rb,
                                         ur)
        du = jnp.sqrt(jnp.sum(ju0**2, axis=(0, 1)))
        dv = jnp.sqrt(jnp.sum(jv0**2, axis=(0, 1)))
        top = jnp.maximum(jnp.max(du), jnp.max(dv, initial=0.0))
        d = (jnp.maximum(du, 1e-12 * top), jnp.maximum(dv, 1e-12 * top))
        sol = optx.least_squares(
            _scaled_residual,
            solver,
            u0,
            (d, args),
            max_steps=max_steps,
            throw=throw,
        )
        poles = _poles_from_params(sol.value[0] / d[0], p0)
        rpoles = _real_from_params(sol.value[1] / d[1], r0)
        num_steps = sol.stats["num_steps"]
        result = sol.result
    else:
        poles, rpoles = p0, r0
        num_steps = jnp.array(0)
        result = optx.RESULTS.successful

    poles = poles[jnp.argsort(jnp.abs(poles))]
    rpoles = jnp.sort(rpoles)[::-1]
    x, res = _linear_fit(poles, s, h, w, rb, ur, rpoles)
    nc = h.shape[1]
    # Undo the scalings: R̃/(s̃−λ̃) = ω_ref R̃/(s−λ), c̃₀/s̃² = ω_ref² c̃₀/s², c̃₁/s̃ = ω_ref c̃₁/s.
    residues = _cplx(x[0 : 2 * n : 2], x[1 : 2 * n : 2]) * to_complex(h_scale * omega_ref)[None]
    fixed = x[2 * n + n_r :]
    real_residues, rigid_rows = _real_residues(x[2 * n : 2 * n + n_r], rpoles, fixed[:rb], rb)
    real_residues = real_residues * (h_scale * omega_ref)[None]
    rigid = jnp.zeros((2, nc))
    for k, j in enumerate(range(2 - rb, 2)):
        rigid = rigid.at[j].set(rigid_rows[k] * h_scale * omega_ref ** (2 - j))
    upper = fixed[rb] * h_scale if ur else jnp.zeros(nc)
    poles = poles * to_complex(omega_ref)

    wn = jnp.abs(poles)
    zeta = -jnp.real(poles) / wn
    s_n = to_complex(wn) * 1j
    term = residues / (s_n - poles)[:, None] + jnp.conj(residues) / (s_n - jnp.conj(poles))[:, None]

    wh2 = jnp.sum((w * jnp.abs(h)) ** 2, axis=0)
    res2 = jnp.sum(res**2, axis=1)
    ch = model.channel_shape
    # a refinement that ends on a degenerate model (e.g. a spare pole on the real axis, whose
    # residues are not defined) gives a non-finite fit: reported as such, never as a success
    total = jnp.sqrt(jnp.sum(res2) / jnp.sum(wh2))
    result = optx.RESULTS.where(jnp.isfinite(total), result, optx.RESULTS.nonfinite)
    if throw:
        total = result.error_if(total, result != optx.RESULTS.successful)
    return ModalFit(
        frequency_hz=wn / _TWO_PI,
        damping_ratio=zeta,
        phase_deg=_wrap_phase_deg(term).reshape(n, *ch),
        residues=residues.reshape(n, *ch),
        poles=poles,
        real_poles=rpoles * omega_ref,
        real_residues=real_residues.reshape(n_r, *ch),
        rigid_body=rigid.reshape(2, *ch),
        upper_residual=upper.reshape(ch),
        fit_error=jnp.sqrt(res2 / wh2).reshape(ch),
        fit_error_total=total,
        num_steps=jnp.asarray(num_steps),
        result=result,
    )


def identify_modes(
    freq_hz: Float[ArrayLike, " freq"],
    frf: Complex[ArrayLike, " freq *channel"],
    n_modes: int | None = None,
    *,
    rigid_body: int = 2,
    real_poles: int | None = None,
    upper_residual: bool = True,
    weights: Float[ArrayLike, " freq *channel"] | None = None,
    initial: ModalFit | StabilisationDiagram | None = None,
    max_modes: int | None = None,
    refine: bool = True,
    vf_iterations: int = 10,
    vf_extra_modes: int = 3,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 256,
    throw: bool = True,
) -> ModalFit:
    r"""Identify natural frequencies, damping ratios and resonant phases from an FRF.

    Fits (paper Sec. 3.2; the modal data of Table 1)

    .. math::

        H_k(i\omega) \approx \sum_{r=1}^{n} \Big(\frac{R_{rk}}{i\omega-\lambda_r}
        + \frac{R_{rk}^*}{i\omega-\lambda_r^*}\Big) + \sum_{j=1}^{n_r}
        \frac{Q_{jk}}{i\omega-a_j} + \frac{c_{0k}}{(i\omega)^2}
        + \frac{c_{1k}}{i\omega} + d_k

    by minimising :math:`\sum_{f,k} |w_{fk}(H^\text{fit}_k - H_k)(f)|^2`: vector fitting for
    the start, then a variable-projection Levenberg–Marquardt refinement of the poles with
    the residues solved exactly (see the ``fdjax._modal`` docstring for the reasons). Returns
    the modes sorted by frequency with :math:`f_r = |\lambda_r|/2\pi`,
    :math:`\zeta_r = -\mathrm{Re}\lambda_r/|\lambda_r|` and the resonant phase
    :math:`\arg T_r(\omega_r)` of each mode's own term :math:`T_r(i\omega) = R_r/(i\omega -
    \lambda_r) + \bar R_r/(i\omega - \bar\lambda_r)` (paper Table 1), in (-360°, 0°].

    Jit-able and vmap-able over positions (fixed sizes; ``n_modes`` and the options are
    static): ``jax.vmap(lambda h: identify_modes(freq_hz, h, 5))(frf_batch)``, or
    :func:`identify_modes_batched` (faster on CPU). Differentiable with respect to ``frf``
    (and ``weights``) through the refinement, by the implicit function theorem.
    Needs ``2·n_freq ≥ 4(n_modes + vf_extra_modes) + n_fixed + 2`` (n_fixed: rigid-body and
    residual terms).

    **Arguments:**

    - ``freq_hz``: frequency grid in Hz, positive and strictly increasing, shape ``(freq,)``.
    - ``frf``: complex FRF with frequency on the first axis, shape ``(freq,)``,
      ``(freq, n_out)`` or ``(freq, n_out, n_in)``; all channels share the poles.
    - ``n_modes``: number of complex-conjugate mode pairs in the band; ``None`` (the default)
      chooses the order from a stabilisation diagram (below).
    - ``rigid_body``: number of poles at :math:`s=0`: 2 fits :math:`c_0/s^2 + c_1/s` (a
      free axis such as a ball-screw drive), 1 only :math:`c_1/s`, 0 none.
    - ``real_poles``: number of real poles :math:`Q_{jk}/(s-a_j)`, :math:`a_j<0`, in the
      model (not modes: reported as ``ModalFit.real_poles``). A ball-screw drive on damped
      guideways has the rigid body :math:`i_{sc}/(s(J_\text{eq}s+c_\text{eq}))`, a pole at
      0 and one at :math:`-c_\text{eq}/J_\text{eq}` (a few rad/s, below the band), which
      without a real pole bends a complex pair (mode 1) into it. Default: 1 without
      ``n_modes``, 0 with it.
    - ``upper_residual``: fit the constant :math:`d_k` for modes above the band.
    - ``weights``: positive weights :math:`w`, broadcastable to ``frf``; default
      :math:`1/|H|` (relative error).
    - ``initial``: a previous ``ModalFit`` (e.g. the neighbouring position) whose poles start
      the refinement instead of vector fitting (with ``n_modes`` None, its order and real
      poles are the fit's); or a :class:`StabilisationDiagram` of the
      same data (from :func:`stabilisation_diagram`, with its own tolerances), whose
      selected poles start it (then ``n_modes`` is None).
    - ``max_modes``: without ``n_modes``, the highest order (pole pairs) of the diagram
      (default 16, fewer on short grids; it stops earlier once the fit has converged).
    - ``refine``: ``False`` returns the vector-fitting estimate (residues solved for its
      poles; without ``n_modes``, the stabilisation diagram's) without the nonlinear
      refinement.  That estimate has no derivative: differentiating it raises.
    - ``vf_iterations``: number of vector-fitting pole relocations (with the spare pairs).
    - ``vf_extra_modes``: spare pole pairs of the vector-fitting stage (see the
      ``fdjax._modal`` docstring); 0 fits exactly ``n_modes`` pairs.  Without ``n_modes``
      the diagram's orders take their part, and it does not enter (it is still checked).
    - ``solver``: an ``optimistix`` least-squares solver, applied to the residual in
      Marquardt-scaled pole parameters (unit: one column norm of the start Jacobian). The
      default is Levenberg–Marquardt (``optx.AbstractGaussNewton`` with a damped Newton
      descent solved by Cholesky and a classical trust region that also accepts steps at the
      round-off of the loss), ``rtol = atol = 1e-8``: frequencies within ~1e-13 and damping
      ratios within ~1e-11 (relative) of the converged optimum, in ~6 steps from the
      vector-fitting start.
    - ``max_steps``, ``throw``: passed to ``optimistix.least_squares``; with
      ``throw=False`` a failed refinement is reported in ``ModalFit.result``.

    **Without an order** (``n_modes=None``): :func:`stabilisation_diagram` fits orders
    1, 2, … pole pairs by vector fitting (with ``real_poles`` real poles free to split
    off), marks a pole *stable* when the previous order has one within 1 % in frequency and
    5 % in damping ratio and *physical* when also in the band with ζ < 0.5, and takes as
    modes the clusters of physical poles seen at two orders or more; the lowest converged
    order holding all of them is selected. Its poles of those modes, its pairs above the
    band (whose influence on the band's top is not a constant) and its ``real_poles``
    largest real poles start the variable-projection refinement above, which is then
    jit/vmap/grad-capable as with ``n_modes``. Returned modes include those pairs above the
    band (``frequency_hz > freq_hz[-1]``: background, not identified modes). Should the
    refinement fail or lose a mode (a pole leaving the band or reaching ζ ≥ 1), the
    selected order's vector-fitting estimate is returned instead (``num_steps`` 0): a
    reasonable measurement never ends in a solver error. Eager (the order is a discrete
    choice on concrete data): not inside ``jit``; there, start from an eager fit, e.g.
    ``fit = identify_modes(f, H)`` and then, jitted, vmapped or differentiated,
    ``identify_modes(f, H2, initial=fit)`` (the fit's order and real poles).

    **Returns:** a :class:`ModalFit`.
    """
    if isinstance(initial, ModalFit):
        for name in ("poles", "real_poles"):
            v = getattr(initial, name)
            if is_concrete(v) and not np.all(np.isfinite(np.asarray(v))):
                raise ValueError(f"`identify_modes(initial=...)` must be a fit with finite "
                                 f"poles, got {name} {np.asarray(v)}")
    if n_modes is None and isinstance(initial, ModalFit):
        # refining a fit: its order (and its real poles, unless given) is the one to refine
        n_modes = int(initial.poles.shape[-1])
        if real_poles is None:
            real_poles = int(initial.real_poles.shape[-1])
    refine = static_bool(refine, "identify_modes(refine=...)")
    throw = static_bool(throw, "identify_modes(throw=...)")
    if n_modes is None or isinstance(initial, StabilisationDiagram):
        if not all(is_concrete(x) for x in (freq_hz, frf, weights) if x is not None):
            raise ValueError(
                "`identify_modes(n_modes=...)` is required inside jit, vmap or grad: choosing "
                "the model order (the stabilisation diagram) runs eagerly, on concrete data"
            )
        return _identify_auto(
            freq_hz, frf, n_modes, rigid_body=rigid_body,
            real_poles=1 if real_poles is None else real_poles, upper_residual=upper_residual,
            weights=weights, initial=initial, max_modes=max_modes, vf_iterations=vf_iterations,
            vf_extra_modes=vf_extra_modes, refine=refine, solver=solver, max_steps=max_steps,
            throw=throw,
        )
    real_poles = 0 if real_poles is None else real_poles
    freq_hz, frf, weights, n_modes, static = _check_inputs(
        "identify_modes", 0, freq_hz, frf, n_modes, rigid_body, upper_residual, weights,
        initial, vf_iterations, vf_extra_modes, max_steps, real_poles,
    )
    rigid_body, upper_residual, vf_iterations, vf_extra_modes, max_steps, real_poles = static
    if solver is None:
        solver = _DEFAULT_SOLVER
    model = _Model(
        n_modes=n_modes,
        rigid_body=rigid_body,
        upper_residual=upper_residual,
        channel_shape=tuple(frf.shape[1:]),
        real_poles=real_poles,
    )
    if not refine:  # the estimate's poles are not differentiated: refused, not zero
        frf, weights = _refined_only(frf), None if weights is None else _refined_only(weights)
    s, h, w, h_scale, omega_ref = _prepare(freq_hz, frf, weights)
    if initial is None:
        data = jax.lax.stop_gradient((s, h, w))
        p0 = _start(*data, model, vf_iterations, vf_extra_modes)
    else:
        r0 = (jnp.zeros((0,)) if initial.real_poles is None
              else initial.real_poles.astype(jnp.float64) / omega_ref)
        p0 = jax.lax.stop_gradient(
            (initial.poles.astype(jnp.complex128) / to_complex(omega_ref), r0))
    return _finish(s, h, w, h_scale, omega_ref, p0, solver, model, bool(refine), max_steps,
                   bool(throw))




def identify_modes_batched(
    freq_hz: Float[ArrayLike, " freq"],
    frf: Complex[ArrayLike, "position freq *channel"],
    n_modes: int | None = None,
    *,
    batch_size: int = 1,
    rigid_body: int = 2,
    real_poles: int | None = None,
    upper_residual: bool = True,
    weights: Float[ArrayLike, "position freq *channel"] | None = None,
    initial: ModalFit | None = None,
    refine: bool = True,
    vf_iterations: int = 10,
    vf_extra_modes: int = 3,
    max_modes: int | None = None,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 256,
    throw: bool = True,
) -> ModalFit:
    r""":func:`identify_modes` at every position of a sweep (paper Sec. 3.2, Figs. 10–12).

    ``frf`` carries a leading position axis, shape ``(n_positions, freq, *channel)``;
    ``weights`` broadcasts to it and ``initial`` is a batched :class:`ModalFit` (e.g. the
    previous sweep). Returns a :class:`ModalFit` whose arrays have a leading position axis,
    ready for :func:`track_modes`.

    One jitted program runs ``jax.lax.map`` over the positions, ``jax.vmap``-ing chunks of
    ``batch_size`` positions. On CPU ``batch_size=1`` (a loop inside the program) is the
    fastest: batched small linear algebra does not vectorise there, and a vmapped
    refinement iterates until its slowest position has converged. On a GPU use a large
    ``batch_size`` (``n_positions`` is the same as ``jax.vmap(identify_modes)``).
    The other arguments are those of :func:`identify_modes`.

    Without ``n_modes`` every position chooses its own order from its stabilisation
    diagram (:func:`identify_modes` with ``n_modes=None``, eagerly, one position after the
    other; ``batch_size``, ``initial`` and ``vf_extra_modes`` do not enter) and
    the modes *inside the band* are returned, padded with NaN to the largest count over the
    positions (a mode not found at a position); :func:`track_modes` pairs them.
    """
    if n_modes is None:
        return _identify_sweep(
            freq_hz, frf, weights, rigid_body=rigid_body,
            real_poles=1 if real_poles is None else real_poles, upper_residual=upper_residual,
            max_modes=max_modes, vf_iterations=vf_iterations, vf_extra_modes=vf_extra_modes,
            refine=refine, solver=solver, max_steps=max_steps, throw=throw,
        )
    real_poles = 0 if real_poles is None else real_poles
    freq_hz, frf, weights, n_modes, static = _check_inputs(
        "identify_modes_batched", 1, freq_hz, frf, n_modes, rigid_body, upper_residual,
        weights, initial, vf_iterations, vf_extra_modes, max_steps, real_poles,
    )
    if frf.shape[0] == 0:
        raise ValueError("`identify_modes_batched(frf=...)` must hold at least one position, "
                         f"got shape {frf.shape}")
    batch_size = static_int(batch_size, "identify_modes_batched(batch_size=...)", 1)
    rigid_body, upper_residual, vf_iterations, vf_extra_modes, max_steps, real_poles = static
    options = dict(
        rigid_body=rigid_body, real_poles=real_poles, upper_residual=upper_residual,
        refine=bool(refine),
        vf_iterations=vf_iterations, vf_extra_modes=vf_extra_modes,
        solver=_DEFAULT_SOLVER if solver is None else solver, max_steps=max_steps,
        throw=bool(throw),
    )
    return _identify_positions(freq_hz, frf, weights, initial, n_modes, batch_size, options)


@eqx.filter_jit
def _identify_positions(freq_hz, frf, weights, initial, n_modes, batch_size, options):
    n_real = options["real_poles"]

    def one(args):
        h, w, init = args
        fit = identify_modes(freq_hz, h, n_modes, weights=w, initial=init, **options)
        if n_real == 0:  # lax.map's chunking cannot reshape zero-size outputs
            fit = eqx.tree_at(lambda m: (m.real_poles, m.real_residues), fit, (None, None),
                              is_leaf=lambda x: x is None)
        return fit

    # A loop over the positions in chunks of batch_size; batch_size=1 maps without vmap (a
    # batched non-symmetric eig, the vector-fitting zeros, has been seen to dead-lock on
    # XLA:CPU).
    fits = map_positions(one, (frf, weights, initial), has_eig=False, batch_size=batch_size)
    if n_real == 0:
        n_pos = frf.shape[0]
        empty = (jnp.zeros((n_pos, 0)), jnp.zeros((n_pos, 0, *frf.shape[2:])))
        fits = eqx.tree_at(lambda m: (m.real_poles, m.real_residues), fits, empty,
                           is_leaf=lambda x: x is None)
    return fits


def _identify_auto(freq_hz, frf, n_modes, *, rigid_body, real_poles, upper_residual, weights,
                   initial, max_modes, vf_iterations, vf_extra_modes, refine, solver, max_steps,
                   throw) -> ModalFit:
    """identify_modes without an order: the stabilisation diagram's selected poles, refined.

    The refinement is tried from the selected order's poles; should it fail (or lose a mode:
    a pole leaving the band or reaching ζ ≥ 1), the diagram's order-selection poles with
    their linear residues (the vector-fitting estimate, ``refine=False``) are returned: for
    a reasonable measurement the result is never a solver error.
    """
    fn = "identify_modes"
    if n_modes is not None and not isinstance(initial, StabilisationDiagram):
        raise ValueError(f"`{fn}(n_modes=...)` must be None here, got {n_modes!r}")
    if n_modes is not None:
        raise ValueError(
            f"`{fn}(initial=...)` is a StabilisationDiagram, which chooses the order itself: "
            f"`{fn}(n_modes=...)` must be None, got {n_modes!r}"
        )
    freq_hz, frf, weights, _, static = _check_inputs(
        fn, 0, freq_hz, frf, 1, rigid_body, upper_residual, weights, None, vf_iterations,
        vf_extra_modes, max_steps, real_poles,
    )
    rigid_body, upper_residual, vf_iterations, _, max_steps, real_poles = static
    if isinstance(initial, StabilisationDiagram):
        diagram = initial
        if diagram.freq_hz.shape != freq_hz.shape or not np.allclose(diagram.freq_hz,
                                                                      np.asarray(freq_hz)):
            raise ValueError(
                f"`{fn}(initial=...)` is a StabilisationDiagram of another frequency grid "
                f"({diagram.freq_hz.shape[0]} points, expected freq_hz's {freq_hz.shape[0]})"
            )
    else:
        n_fixed = rigid_body + int(upper_residual) + real_poles
        opts = _order_options(fn, freq_hz.shape[0], n_fixed, max_modes, vf_iterations, 0.01,
                              0.05, 0.5, 2)
        diagram = _diagram_of(freq_hz, frf, weights, real_poles, rigid_body, upper_residual,
                              opts)
    if diagram.n_modes == 0:
        raise ValueError(
            f"`{fn}(frf=...)` shows no stable physical mode in its stabilisation diagram "
            f"(orders 1–{int(diagram.orders[-1])}); give `{fn}(n_modes=...)` or inspect "
            f"`stabilisation_diagram(freq_hz, frf)`"
        )
    pairs = np.concatenate([diagram.selected_poles, diagram.background_poles])
    rpoles = diagram.selected_real_poles
    if rpoles.size < real_poles:
        rpoles = np.concatenate([rpoles, -2 * np.pi * float(freq_hz[0]) *
                                 10.0 ** (-0.5 * np.arange(real_poles - rpoles.size))])
    model = _Model(n_modes=int(pairs.size), rigid_body=rigid_body, upper_residual=upper_residual,
                   channel_shape=tuple(frf.shape[1:]), real_poles=int(rpoles.size))
    solver = _DEFAULT_SOLVER if solver is None else solver
    s, h, w, h_scale, omega_ref = _prepare(freq_hz, frf, weights)
    p0 = (jnp.asarray(pairs / float(omega_ref)), jnp.asarray(rpoles / float(omega_ref)))
    fit = _finish(s, h, w, h_scale, omega_ref, p0, solver, model, refine, max_steps, False)
    band = (float(freq_hz[0]), float(freq_hz[-1]))
    if refine and not _refined_ok(fit, diagram, band):
        fit = _finish(s, h, w, h_scale, omega_ref, p0, solver, model, False, max_steps, False)
    return _without_cancelled_poles(fit)


@jax.custom_jvp
def _refined_only(x):
    """``x``; differentiating through it raises: with ``refine=False`` the vector-fitting
    estimate's poles carry no derivative (a gradient would be silently zero in frequency and
    damping)."""
    return x


@_refined_only.defjvp
def _refined_only_jvp(primals, tangents):
    raise ValueError("`identify_modes(refine=False)` has no derivative: the vector-fitting "
                     "estimate's poles are not differentiated (its gradient in frequency and "
                     "damping would be zero); differentiate the refined fit, refine=True")


# A mode's own term below this share of the fitted response at its natural frequency (every
# channel) is a spare pole that the fit has cancelled by a vanishing residue, not a mode.
_CANCELLED = 1e-6


def _without_cancelled_poles(fit: ModalFit) -> ModalFit:
    """``fit`` without the pole pairs whose residues vanish (|own term| < 1e-6 |H| at ω_r).

    Noise-free data fitted at a higher order than it needs can keep a spare pole at the same
    place from order to order (here 12.9 Hz, ζ ≈ 1e-5, residue 1e-13 of the modes'); it is
    stable in the diagram but contributes nothing, and dropping it leaves the fit unchanged."""
    f = np.asarray(fit.frequency_hz)
    if f.size == 0 or not np.all(np.isfinite(f)) or np.any(f <= 0):
        return fit
    order = np.argsort(f)
    fs = f[order]
    if np.any(np.diff(fs) <= 0):
        return fit
    own = np.abs(np.asarray(fit.mode_frf(fs)))  # (freq, mode, *channel)
    total = np.abs(np.asarray(fit.frf(fs)))  # (freq, *channel)
    k = np.arange(f.size)
    share = own[np.argsort(order)[k], k] / np.maximum(total[np.argsort(order)], 1e-300)
    share = share.reshape(f.size, -1).max(axis=1)
    keep = np.flatnonzero(share >= _CANCELLED)
    if keep.size == f.size:
        return fit
    return eqx.tree_at(
        lambda m: (m.frequency_hz, m.damping_ratio, m.phase_deg, m.residues, m.poles),
        fit,
        tuple(x[keep] for x in (fit.frequency_hz, fit.damping_ratio, fit.phase_deg,
                                 fit.residues, fit.poles)),
    )


def _refined_ok(fit: ModalFit, diagram: StabilisationDiagram, band) -> bool:
    """The refinement converged and kept every mode of the diagram: each one's refined pole
    still in the band, within 5 % of its start frequency, and ζ < 1."""
    if fit.result != optx.RESULTS.successful:
        return False
    f = np.asarray(fit.frequency_hz)
    z = np.asarray(fit.damping_ratio)
    if not (np.all(np.isfinite(f)) and np.all(np.isfinite(z))):
        return False
    for fm in diagram.mode_frequency_hz:
        k = np.argmin(np.abs(f - fm))
        if abs(f[k] - fm) > 0.05 * fm or z[k] >= 1.0 or not band[0] <= f[k] <= band[1]:
            return False
    return True


def _identify_sweep(freq_hz, frf, weights, *, rigid_body, real_poles, upper_residual,
                    max_modes, vf_iterations, vf_extra_modes, refine, solver, max_steps,
                    throw) -> ModalFit:
    """identify_modes_batched without an order: each position's order chosen by its own
    stabilisation diagram (eagerly, position by position); the modes inside the band are
    returned, NaN-padded to the largest count over the positions."""
    fn = "identify_modes_batched"
    frf = jnp.asarray(frf)
    if frf.ndim < 2:
        raise ValueError(f"`{fn}(frf=...)` must have a leading position axis, got shape "
                         f"{frf.shape}")
    # the whole sweep checked as given, with this function's name and its shapes
    freq_hz, frf, weights, _, _ = _check_inputs(
        fn, 1, freq_hz, frf, 1, rigid_body, upper_residual, weights, None, vf_iterations,
        vf_extra_modes, max_steps, real_poles)
    refine = static_bool(refine, f"{fn}(refine=...)")
    freq_np = np.asarray(freq_hz, dtype=np.float64)
    fits = []
    for p in range(frf.shape[0]):
        w = None if weights is None else jnp.broadcast_to(jnp.asarray(weights), frf.shape)[p]
        fit = identify_modes(freq_hz, frf[p], rigid_body=rigid_body, real_poles=real_poles,
                             upper_residual=upper_residual, weights=w, max_modes=max_modes,
                             vf_iterations=vf_iterations, refine=refine, solver=solver,
                             max_steps=max_steps, throw=throw)
        f = np.asarray(fit.frequency_hz)
        fits.append((fit, np.flatnonzero((f >= freq_np[0]) & (f <= freq_np[-1]))))
    n = max(k.size for _, k in fits)

    def take(fit, k):
        def pad(x):
            x = np.asarray(x)[k]
            fill = np.full((n - k.size, *x.shape[1:]), np.nan, dtype=x.dtype)
            return np.concatenate([x, fill], axis=0)

        return eqx.tree_at(
            lambda m: (m.frequency_hz, m.damping_ratio, m.phase_deg, m.residues, m.poles),
            fit, tuple(jnp.asarray(pad(x)) for x in (fit.frequency_hz, fit.damping_ratio,
                                                      fit.phase_deg, fit.residues, fit.poles)),
        )

    fits = [take(fit, k) for fit, k in fits]
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *fits)
