r"""Modal identification from frequency response functions (paper Sec. 3.2, Table 1).

The paper reads natural frequency, damping ratio and *resonant phase* of each mode of the
drive's FRF h21 (Table 1) and follows them over the table position (Fig. 12). Here that is
a multi-mode rational fit of the whole band, never a peak pick: the first three modes of
Table 1 (49/95/130 Hz, ζ = 0.09–0.17) overlap so much that the phase at a magnitude peak
is not the phase of any one mode.

**Model.** With :math:`s = i\omega`, every channel :math:`k` of the FRF is fitted by

.. math::

    H_k(s) = \sum_{r=1}^{n} \Big(\frac{R_{rk}}{s-\lambda_r}
             + \frac{R_{rk}^*}{s-\lambda_r^*}\Big)
             + \sum_{j=1}^{n_r} \frac{Q_{jk}}{s-a_j}
             + \frac{c_{0k}}{s^2} + \frac{c_{1k}}{s} + d_k ,

poles :math:`\lambda_r = -\zeta_r\omega_r + i\omega_r\sqrt{1-\zeta_r^2}` shared by all
channels, complex residues (complex modes allowed), a rigid-body double pole at
:math:`s = 0` (a ball-screw receptance falls as :math:`1/\omega^2`), optional real poles
:math:`a_j < 0` (the damped rigid body :math:`i_{sc}/(s(J_\text{eq}s + c_\text{eq}))` of a
drive on damped guideways has one at :math:`-c_\text{eq}/J_\text{eq}`; they are not modes)
and a real upper residual :math:`d_k` for the modes above the band.

**The order.** Without ``n_modes`` a stabilisation diagram (``_order``) chooses it: vector
fits at increasing orders, poles stable across orders (1 % in frequency, 5 % in damping)
inside the band with ζ < 0.5 grouped into modes, the lowest converged order holding them all
selected; its poles start stage 2 below, with a real pole for the rigid body's damping.

**Method, in two stages.**

1. *Vector fitting* (Gustavsen & Semlyen 1999, IEEE Trans. Power Delivery 14(3); relaxed
   form, Gustavsen 2006, ibid. 21(3)) gives the start without any peak picking. From
   ``n + vf_extra_modes`` lightly damped pole pairs spread logarithmically over the band,
   each iteration solves one *linear* least-squares problem
   :math:`\sigma(s)H_k(s) \approx N_k(s)` for all channels with a shared
   :math:`\sigma(s) = \tilde d + \sum_j \tilde c_j/(s-a_j)` (constrained by
   :math:`\mathrm{Re}\sum_i\sigma(s_i) = N`), and moves the poles to the zeros of
   :math:`\sigma`, the eigenvalues of :math:`\mathrm{diag}(a) - \mathbf 1\tilde c^T/\tilde d`.
   The poles at :math:`s = 0` enter only the numerator, so they stay there. The spare
   pairs then absorb noise and out-of-band dynamics (with exactly ``n`` pairs a pole can
   lock onto noise and leave a mode unfitted); backward elimination keeps the ``n`` pairs
   whose removal would raise the residual most, and a few relocations of those alone
   settle the rest. Robust over a wide band with overlapping, heavily damped modes beside
   lightly damped ones, where peak picking and circle fitting fail; fixed iteration
   counts, so it jits and vmaps.
2. *Variable-projection Levenberg–Marquardt refinement* (Golub & Pereyra 1973) of the
   weighted complex residual :math:`w\,(H_\text{fit}-H)`, real and imaginary parts, with
   ``optimistix.least_squares``. The residues, rigid-body and residual terms enter
   linearly, so for given poles they are the exact linear least-squares solution (one
   m×m Cholesky per channel); only the :math:`2n` pole parameters are iterated, with the
   Jacobian in closed form. The minimiser is that of the joint pole-and-residue problem
   (vector fitting's is not: it minimises a linearised, σ-weighted residual), but the
   iteration is small and needs no scaling of residues. Each pole is parametrised as
   :math:`\lambda = -\sigma_0 e^{v} + i\omega_{d0} e^{\zeta_0 u}` about its start (a unit
   of u is one relative half-power bandwidth), and the parameters are scaled by the
   start Jacobian's column norms (Marquardt scaling, as in MINPACK), so lightly
   (ζ = 0.003) and heavily (ζ = 0.17) damped modes are equally well conditioned. From the
   vector-fitting start it converges in about six Gauss–Newton-like steps.

The default weight :math:`w = 1/|H|` makes every point count by its *relative* error, the
maximum-likelihood weight for noise proportional to the response (as in measured and in
FBS-predicted FRFs); the magnitudes of ~1e-9 m/N and the 1/ω² fall of the rigid body then
do not matter, and each channel is normalised internally. Gradients of the identified
quantities with respect to the data pass through the refinement by the implicit function
theorem (``optimistix.ImplicitAdjoint``); the vector-fitting start carries no gradient,
which is exact because the minimiser does not depend on where the iteration starts.

**Resonant phase** (paper Table 1, Fig. 12). For the term of mode :math:`r`,
:math:`T_r(\omega) = R_r/(i\omega-\lambda_r) + R_r^*/(i\omega-\lambda_r^*)
= (2\,\mathrm{Re}R_r\,i\omega - 2\,\mathrm{Re}(R_r\lambda_r^*)) /
(\omega_r^2-\omega^2+2i\zeta_r\omega_r\omega)`, the resonant phase is
:math:`\arg T_r(\omega_r)`, wrapped to :math:`(-360°, 0°]`. For a term written as
:math:`A_r e^{i\alpha_r}/(\omega_r^2-\omega^2+2i\zeta_r\omega_r\omega)` this is
:math:`\alpha_r - 90°`.

``identify_modes_batched`` runs the identification over a sweep of table positions in one
jitted program, and ``track_modes`` re-orders the modes of such a batch so that each index
follows one physical mode, by frequency proximity and mode-shape correlation (MAC).

* ``_data``: the checks of the FRF data and their scaling, shared by the order and the fit.
* ``_linear``: the rational basis and the linear least-squares sub-problem for given poles.
* ``_vector_fit``: stage 1, vector fitting and the backward elimination of spare pairs.
* ``_solver``: stage 2, the variable-projection residual and the Levenberg–Marquardt solver.
* ``_order``: :func:`stabilisation_diagram`, the order selection (eager, NumPy).
* ``_fit``: :class:`ModalFit`, the identified model and its FRF.
* ``_identify``: :func:`identify_modes` and :func:`identify_modes_batched`.
* ``_tracking``: :func:`track_modes` (MAC and the assignment over positions).
"""

from ._fit import ModalFit as ModalFit
from ._identify import (
    identify_modes as identify_modes,
    identify_modes_batched as identify_modes_batched,
)
from ._order import (
    StabilisationDiagram as StabilisationDiagram,
    stabilisation_diagram as stabilisation_diagram,
)
from ._tracking import (
    _track as _track,  # the permutations alone, for fdjax._drive._modes' drive-mode tracking
    track_modes as track_modes,
)
