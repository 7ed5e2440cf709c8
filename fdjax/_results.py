"""The toolkit's one result-code type (as diffrax's and optimistix's ``RESULTS``).

Each failure a solve, a simulation or a stability check can end in has its own message, so
under ``jit`` and ``vmap`` (where only static text can be raised) ``RESULTS.error_if`` still says
which check failed; eager calls add the values (the position, the pole, the time).
"""

from __future__ import annotations

import equinox as eqx

__all__ = ["RESULTS"]


class RESULTS(eqx.Enumeration):
    """Result codes of :func:`fdjax.simulate` and :func:`fdjax.check_stability`:
    ``successful``, ``unstable`` (a growing pole), ``diverged`` (a non-finite state or a scale
    error past the bound), ``solver_failed`` (the ODE solver) and ``out_of_travel`` (the motion
    leaves the drive's travel); each member's text is its message."""

    successful = ""
    unstable = (
        "the closed loop is unstable (a pole of the loop is growing; see the result's "
        "growth_rate and position_m)"
    )
    diverged = (
        "the closed-loop run diverged: a state turned non-finite or the scale error passed "
        "`simulate(error_bound=...)`"
    )
    solver_failed = "the ODE solver failed (step size or step budget; see diffrax)"
    out_of_travel = (
        "the reference motion takes the table outside the drive's travel (`simulate(position_m"
        "=...)` plus the reference position r(t) must stay inside `BallScrewDrive.travel_m`)"
    )
