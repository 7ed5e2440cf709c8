"""fdjax: differentiable design of ball-screw feed-drive controllers in JAX.

Importing fdjax switches JAX to float64 (``jax_enable_x64``): receptances of a machine-tool
axis are ~1e-9 m/N and float32 loses them. Set it yourself before creating arrays if you
import JAX first.
"""

import jax

jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"
