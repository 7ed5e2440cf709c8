"""Quickstart: the 3M2S example and the reference ball-screw drive.

Run: python examples/quickstart.py
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

import fdjax  # switches JAX to float64

# no options: --help describes the script, anything else is refused
argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False).parse_args()

# The paper's three-mass two-spring system (Sec. 2): H[f, i, j] = x_i / F_j in m/N
model = fdjax.three_mass()
freq_hz, _ = model.modes()
print("3M2S natural frequencies (Hz):", np.round(np.asarray(freq_hz)[1:], 1))
H3 = model.frf(jnp.linspace(10.0, 300.0, 2000))  # (2000, 3, 3)

# The reference drive: H_M(Y_table, f), outputs (θ1, x2, x3), inputs (T1, F3)
drive = fdjax.reference_drive()
positions = jnp.linspace(0.1, 0.7, 7)  # table position Y_table in m
freq = jnp.geomspace(5.0, 3000.0, 2048)  # Hz
H = drive.frf(positions, freq)  # (7, 2048, 3, 2), complex128
h21 = H[:, :, 1, 0]  # linear scale x2 per motor torque T1, m/(N·m)
print("H_M:", H.shape, H.dtype)


# Everything is differentiable: sensitivity of |h21| at 150 Hz to the nut stiffness
def magnitude(d):
    return jnp.abs(d.receptance(0.4, 2 * jnp.pi * 150.0)[1, 0])


grads = jax.grad(magnitude)(drive)
print("d|h21(150 Hz)|/dk_ja =", float(grads.nut.stiffness), "m/(N·m) per N/m")

# ... and vectorised: one FRF per nut stiffness, batched with vmap
ks = jnp.linspace(3e8, 8e8, 4)
import equinox as eqx  # noqa: E402

batch = jax.vmap(lambda k: eqx.tree_at(lambda d: d.nut.stiffness, drive, k).receptance(
    0.4, 2 * jnp.pi * freq))(ks)
print("batched over nut stiffness:", batch.shape)

# The closed loop of paper Fig. 13 on a short-stroke reciprocating motion, as the servo runs it
loop = fdjax.reference_controller()  # P position / PI speed loop with MCM, feed-forward
servo = fdjax.Servo()  # hardware: 8 kHz, delay 2 periods, k_i·k_T
sim = fdjax.simulate(loop, drive, fdjax.reciprocating(), fdjax.SampledData(), servo=servo,
                     position_m=0.115)
print(f"RMS scale error {float(sim.rms_error()) * 1e6:.2f} µm;", sim.message)

# Margins of the sampled loop, broken at the plant input, the speed feedback and the scale
m = fdjax.loop_margins(loop, drive, jnp.geomspace(1.0, 3900.0, 2000), position_m=0.115)
print(f"speed loop GM {float(m.speed.gain_margin_db):.1f} dB, "
      f"position loop PM {float(m.position.phase_margin_deg):.1f}°")


# A controller is one class: its law, from (r, ṙ, r̈, x2, v_m) to the current command
class PP(fdjax.AbstractController):  # P position loop over a P speed loop
    kp: jax.Array  # 1/s
    kv: jax.Array  # A·s/m

    def law(self, position_m):  # u = k_v (k_p (r − x2) − v_m)
        kv, kp = self.kv, self.kp
        return fdjax.Law((fdjax.Path({"r": kv * kp, "x2": -kv * kp, "v_m": -kv}),))


st = fdjax.check_stability(PP(jnp.array(10.0), jnp.array(150.0)), drive, position_m=0.4)
print(st.message)
