r"""A controller at a table position as the python-control object a control engineer checks it
with: the law from w = (r, ṙ, r̈, x2, v_m) (:data:`fdjax.LAW_SIGNALS`) to the current command u,

    u_k = C x_k + D w_k,   x_{k+1} = A x_k + B w_k   (sampled, dt = T: what the servo runs),
    u = (C (sI − A)⁻¹ B + D) w                      (continuous, ``discrete=False``),

the same realisation the closed loops, margins and simulations of fdjax use.
"""

from __future__ import annotations

import math

import numpy as np
from jaxtyping import ArrayLike, Float

from .._checks import LONGEST_TRAVEL_M, concrete_float, instance, static_bool
from ._blocks import FILTER_METHODS
from ._controllers import LAW_SIGNALS, AbstractController
from ._interconnect import realise_law
from ._servo import Servo

__all__ = ["to_python_control"]



def to_python_control(controller: AbstractController,
                      position_m: Float[ArrayLike, ""] | None = None, *,
                      servo: Servo = Servo(), discrete: bool = True,
                      filter_method: str = "fitted", form: str = "ss"):
    """The law of ``controller`` at ``position_m`` (m; needed by a scheduled controller) as a
    python-control ``StateSpace`` (``form="ss"``) or ``TransferFunction`` (``form="tf"``),
    sampled at the servo period (module docstring) or continuous.  Inputs named after
    :data:`fdjax.LAW_SIGNALS`, output ``u`` (A).  Needs the ``control`` package."""
    fn = "to_python_control"
    instance(controller, AbstractController, f"{fn}(controller=...)", "an fdjax controller")
    if form not in ("ss", "tf"):
        raise ValueError(f"`{fn}(form=...)` must be 'ss' or 'tf', got {form!r}")
    if filter_method not in FILTER_METHODS:
        raise ValueError(f"`{fn}(filter_method=...)` must be one of {FILTER_METHODS}, got "
                         f"{filter_method!r}")
    discrete = static_bool(discrete, f"{fn}(discrete=...)")
    instance(servo, Servo, f"{fn}(servo=...)")
    if position_m is not None:
        where = f"{fn}(position_m=...)"
        position_m = concrete_float(position_m, where)
        if not (math.isfinite(position_m) and abs(position_m) <= LONGEST_TRAVEL_M):
            mm = (f"; table positions are in metres: {position_m:.6g} mm is "
                  f"{position_m * 1e-3:.6g} m" if math.isfinite(position_m) else "")
            raise ValueError(f"`{where}` must be a finite table position in metres (at most "
                             f"{LONGEST_TRAVEL_M:g} m), got {position_m:.6g}{mm}")
    try:
        import control
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(f"`{fn}` needs python-control: pip install control") from exc
    position_m = controller.check_position(position_m, f"{fn}(position_m=...)")
    law = controller.law(position_m)
    period = float(servo.period) if discrete else None
    try:
        lti = realise_law(law, period=period, filter_method=filter_method)
    except ValueError as err:  # a filter the servo cannot sample: named for the caller
        if period is None:
            raise
        raise ValueError(f"`{fn}(controller=...)` cannot be run by the servo (period {period:g} "
                         f"s, Nyquist frequency {0.5 / period:g} Hz): {err}") from err
    A, B, C, D = (np.array(x, np.float64) for x in (lti.A, lti.B, lti.C, lti.D))
    sys = control.ss(A, B, C, D, period if discrete else 0, inputs=list(LAW_SIGNALS),
                     outputs=["u"])
    return control.ss2tf(sys) if form == "tf" else sys
