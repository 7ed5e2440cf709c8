r"""Peak and notch filters, the modal characteristic modifier (MCM) and their discrete forms.

The MCM of paper Sec. 4.1 is G_MCM(s) = G_pf(s) · G_nf(s), a peak-filter part (Eq. (3)) that
bends low and middle modes to "in phase" and a notch-filter part (Eq. (4)) that removes high
modes. Every filter is a sum/product of second-order sections,

    G(s) = (1 + Σ_p P_p(s)) · Π_q N_q(s),

peaks in parallel with the direct path 1, notches in series; the discrete filter
(``.discretize(dt)``) keeps that structure section by section.

* ``_sections``: banks of second-order sections in s, their evaluation and realisation.
* ``_discrete``: :class:`DiscreteFilter` and the fitted and Tustin discretisations.
* ``_continuous``: :class:`AbstractFilter`, :class:`PeakFilter` (Eq. (3)),
  :class:`NotchFilter` (Eq. (4)) and :class:`MCM`.

Realisations (``state_space()``) are :class:`fdjax._lti.LTI` systems, continuous for the
continuous filters and with ``dt`` for the discrete one.
"""

from ._continuous import (
    MCM as MCM,
    AbstractFilter as AbstractFilter,
    NotchFilter as NotchFilter,
    PeakFilter as PeakFilter,
)
from ._discrete import DiscreteFilter as DiscreteFilter
