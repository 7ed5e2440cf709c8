"""Closed-loop simulation of the reference drive: stability checked first at every position
simulated, one run, a sweep over table positions with ``vmap``, the gradient of the RMS tracking
error with respect to the controller gains, and a traverse with the table moving along the screw.

The loop is the shipped ``"mcm_fixed"`` design (``fdjax.load_designs()``: gains and one MCM
tuned by ``fdjax tune`` at 115 mm, stable over the whole travel) with full feed-forward
added; feed-forward acts on the reference only, so it leaves the closed loop's poles where
they were.  Stability is
checked before anything is simulated: ``fdjax.reference_controller()`` (tuned at 115 mm) is
unstable from about 0.5 m, and a ``DoubleLoop`` with no notch and a k_v above ~375 A·s/m is
unstable at every position (its 1260 Hz torsional mode grows), so the simulations, and the
gradient, of such a loop mean nothing.  Under ``vmap`` and ``grad`` the simulation cannot
raise, so it runs with ``throw=False`` and its ``result`` is read back and checked.

Run: ``python examples/closed_loop.py`` (≈ 30 s on 2 CPU cores, mostly compilation).
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

import fdjax

# no options: --help describes the script, anything else is refused
argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False).parse_args()

drive = fdjax.reference_drive()
reference = fdjax.reciprocating(stroke=5e-3, cycles=2)  # 5 mm, 0.1 m/s, 2 m/s², 200 m/s³
servo = fdjax.Servo(period=1.25e-4, delay_samples=2)  # 8 kHz servo, τ = d·T = 250 µs
method = fdjax.SampledData()  # the loop as the servo runs it, at the servo's period
# the twin: modes below 4 kHz (counted once, so vmap/grad over positions compile once)
twin = fdjax.TwinOptions(kept_modes=fdjax.count_modes(drive))

design = fdjax.load_designs()[0]["mcm_fixed"]
# its feedback (gains and MCM) with DoubleLoop's default full feed-forward
loop = fdjax.DoubleLoop(design.kp, design.kv, design.ki, mcm=design.mcm)
print(f"loop: k_p = {float(loop.kp):.0f} 1/s, k_v = {float(loop.kv):.0f} A·s/m, "
      f"k_i = {float(loop.ki):.1f} rad/s, MCM (peak filter + notch)")

# Stability first, at every position the runs below visit: the whole travel on a 5 mm grid
grid = np.linspace(0.1, 0.7, 121)
stability = fdjax.check_stability(loop, drive, servo=servo, method=method, position_m=grid,
                                  twin=twin)
stable = np.asarray(stability.stable)
print(f"stable at {int(stable.sum())} of {grid.size} positions 0.1–0.7 m: slowest pole decays "
      f"at {-float(np.max(stability.growth_rate)):.1f} 1/s, "
      f"least damping ratio {float(np.min(stability.min_damping)):.4f}")
if not stable.all():
    raise SystemExit(stability.message)
# the contrast: the paper's controller, tuned at 115 mm, held over the travel
ref = fdjax.check_stability(fdjax.reference_controller(), drive, servo=servo, method=method,
                            position_m=grid, twin=twin)
bad = np.flatnonzero(~np.asarray(ref.stable))
print(f"(reference_controller() for comparison: unstable at {bad.size} of {grid.size}, first "
      f"{float(grid[bad[0]]):.3g} m, growing at {float(ref.growth_rate[bad[0]]):.2f} 1/s)")

# One run at the paper's position (Figs. 16-17 are at Y_table = 115 mm); throw=True (the
# default) raises if the run is not successful
sim = fdjax.simulate(loop, drive, reference, method, servo=servo, position_m=0.115, twin=twin)
print(f"RMS scale error at 115 mm: {float(sim.rms_error()) * 1e6:.2f} µm "
      f"(tool point: {float(sim.rms_error('tool')) * 1e6:.2f} µm); {sim.message}")


def rms(gains, position_m):
    """RMS scale error (m) and the run's result code, for vmap and grad (which cannot raise)."""
    trial = fdjax.DoubleLoop(gains["kp"], gains["kv"], gains["ki"], mcm=loop.mcm)
    run = fdjax.simulate(trial, drive, reference, method, servo=servo, position_m=position_m,
                         twin=twin, throw=False)
    return run.rms_error(), run.result


def check(result, what):
    ok = np.asarray(result == fdjax.RESULTS.successful)
    if not ok.all():
        raise SystemExit(f"{what}: {int((~ok).sum())} run(s) not successful")


gains = {"kp": loop.kp, "kv": loop.kv, "ki": loop.ki}
# Y₀ + r(t) must stay inside the travel (0.1–0.7 m): the last start is 10 mm from the end
positions = jnp.asarray([0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.69])

# A sweep over the travel: one compiled program for all positions
errors, results = jax.jit(jax.vmap(rms, in_axes=(None, 0)))(gains, positions)
check(results, "sweep")
for p, e in zip(np.asarray(positions), np.asarray(errors)):
    print(f"  Y_table = {p * 1e3:4.0f} mm: RMS error {e * 1e6:6.2f} µm")


# Gradient of the mean RMS error over the travel with respect to the gains
def mean_rms(g):
    e, result = jax.vmap(rms, in_axes=(None, 0))(g, positions)
    return jnp.mean(e), result


grad, results = jax.jit(jax.grad(mean_rms, has_aux=True))(gains)
check(results, "gradient")
units = {"kp": "1/s", "kv": "A·s/m", "ki": "rad/s"}
for k, v in grad.items():
    print(f"  d mean RMS / d {k} = {float(v):+.3e} m per {units[k]}")

# The table moving along the screw (the paper froze each position): a 300 mm traverse from
# 100 mm, the plant rebuilt at every servo sample, against the loop frozen at 100 mm
traverse = fdjax.jerk_limited(0.3, v_max=0.5, a_max=5.0, j_max=500.0)
runs = {
    name: fdjax.simulate(loop, drive, traverse, method, servo=servo, position_m=0.1,
                         moving=name == "moving")
    for name in ("moving", "frozen")
}
for name, run in runs.items():
    err = np.asarray(run.error_scale)
    print(f"  300 mm traverse, {name:6s}: RMS error {float(run.rms_error()) * 1e6:6.2f} µm, "
          f"peak {np.abs(err).max() * 1e6:6.2f} µm, ends at Y = {float(run.position_m[-1]):.3f} m"
          f"; {run.message}")
