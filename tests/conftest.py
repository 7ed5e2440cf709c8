"""Test configuration: float64 and strict dtype promotion for every test."""

import os

# XLA:CPU's concurrency-optimised scheduler has been seen to dead-lock (all threads asleep)
# on loops around LAPACK calls on this 2-core machine; the sequential scheduler avoids it.
_flag = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
if _flag not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _flag).strip()

import jax  # noqa: E402

import fdjax  # noqa: F401, E402  (importing fdjax switches float64 on)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
