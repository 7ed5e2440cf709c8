"""Test configuration: float64 and strict dtype promotion for every test."""

import jax

import fdjax  # noqa: F401  (importing fdjax switches float64 on)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
