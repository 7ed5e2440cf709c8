"""Quickstart: the 3M2S example and the reference ball-screw drive.

Run: python examples/quickstart.py
"""

import jax
import jax.numpy as jnp
import numpy as np

import fdjax  # switches JAX to float64

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
