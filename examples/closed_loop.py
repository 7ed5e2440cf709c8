"""Closed-loop simulation of the reference drive: one run, a sweep over table positions with
``vmap``, the gradient of the RMS tracking error with respect to the controller gains, and a
traverse with the table moving along the screw.

Run: ``python examples/closed_loop.py`` (~30 s, mostly compilation).
"""

import jax
import jax.numpy as jnp
import numpy as np

import fdjax

drive = fdjax.reference_drive()
reference = fdjax.reciprocating(stroke=5e-3, cycles=2)  # 5 mm, 0.1 m/s, 2 m/s², 200 m/s³
servo = fdjax.Servo(period=1.25e-4, delay_samples=2)  # 8 kHz servo, τ = d·T = 250 µs
method = fdjax.SampledData()  # the loop as the servo runs it, at the servo's period
# the twin: modes below 4 kHz (counted once, so vmap/grad over positions compile once)
twin = fdjax.TwinOptions(kept_modes=fdjax.count_modes(drive))

# One run at the paper's position (Figs. 16-17 are at Y_table = 115 mm)
sim = fdjax.simulate(fdjax.reference_controller(), drive, reference, method, servo=servo,
                     position_m=0.115)
print(f"RMS scale error at 115 mm: {float(sim.rms_error()) * 1e6:.2f} µm "
      f"(tool point: {float(sim.rms_error('tool')) * 1e6:.2f} µm)")


def rms(gains, position_m):
    loop = fdjax.DoubleLoop(kp=gains["kp"], kv=gains["kv"], ki=gains["ki"])
    run = fdjax.simulate(loop, drive, reference, method, servo=servo, position_m=position_m,
                         twin=twin, throw=False)
    return run.rms_error()


gains = {"kp": jnp.asarray(40.0), "kv": jnp.asarray(3.0e3), "ki": jnp.asarray(60.0)}
positions = jnp.linspace(0.1, 0.7, 7)

# A sweep over the travel: one compiled program for all positions
errors = jax.jit(jax.vmap(rms, in_axes=(None, 0)))(gains, positions)
for p, e in zip(np.asarray(positions), np.asarray(errors)):
    print(f"  Y_table = {p * 1e3:4.0f} mm: RMS error {e * 1e6:6.2f} µm")

# Gradient of the mean RMS error over the travel with respect to the gains
grad = jax.jit(jax.grad(lambda g: jnp.mean(jax.vmap(rms, in_axes=(None, 0))(g, positions))))
for k, v in grad(gains).items():
    print(f"  d mean RMS / d {k} = {float(v):+.3e}")

# The table moving along the screw (the paper froze each position): a 300 mm traverse from
# 100 mm, the plant rebuilt at every servo sample, against the loop frozen at 100 mm
traverse = fdjax.jerk_limited(0.3, v_max=0.5, a_max=5.0, j_max=500.0)
runs = {
    name: fdjax.simulate(fdjax.reference_controller(), drive, traverse, method, servo=servo,
                         position_m=0.1, moving=name == "moving")
    for name in ("moving", "frozen")
}
for name, run in runs.items():
    err = np.asarray(run.error_scale)
    print(f"  300 mm traverse, {name:6s}: RMS error {float(run.rms_error()) * 1e6:6.2f} µm, "
          f"peak {np.abs(err).max() * 1e6:6.2f} µm, ends at Y = {float(run.position_m[-1]):.3f} m")
