"""The Table 1 drive's hand-set double loop, for the tests of the loop machinery (margins,
simulations, recompilation) that are pinned to that drive: fdjax.DoubleLoop's defaults before
they were set for the reference drive."""

import math

import fdjax

_J_EQ = 1.2444e-2  # kg·m², the Table 1 drive's reflected inertia
_I_SC = 0.005 / (2 * math.pi)  # m/rad, its 50×5 screw


def table1_loop(**kw) -> fdjax.DoubleLoop:
    """DoubleLoop(k_p = 40 1/s, k_v = 3000 A·s/m, k_i = 60 rad/s), full velocity feed-forward and
    the rigid Table 1 drive's acceleration feed-forward; keyword arguments override."""
    args = dict(kp=40.0, kv=3.0e3, ki=60.0, k_ffv=1.0, k_ffa=_J_EQ / (1.2 * _I_SC))
    args.update(kw)
    return fdjax.DoubleLoop(**args)
