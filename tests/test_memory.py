"""Releasing compiled programs: the memory maps of a compiled program go with JAX's caches."""

import sys

import jax
import jax.numpy as jnp
import pytest

from fdjax._memory import memory_maps, release


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_release_drops_the_maps_of_compiled_programs():
    f = jax.jit(lambda x: jnp.sin(x) @ jnp.cos(x).T + jnp.linalg.inv(x))
    release(threshold=0)
    before = memory_maps()
    f(jnp.eye(3) * 2.0).block_until_ready()
    compiled = memory_maps()
    assert compiled > before  # the program's machine code is mapped
    assert release(threshold=10**9) is False and memory_maps() >= compiled - 5
    assert release(threshold=0) is True
    assert memory_maps() < compiled
