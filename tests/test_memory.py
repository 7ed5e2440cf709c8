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


def test_a_run_is_refused_by_what_its_method_holds_per_sample(monkeypatch):
    """A run of 1 s (8001 samples every 125 µs) is refused when the memory available is below
    its method's bytes per sample: the continuous loop (PadeODE, 520 B: measured 500 B over a
    run of 1.44 million samples, which the sampled loop's 320 B had let through) at 400 B per
    sample available, the sampled loop at 300 B."""
    import fdjax
    from fdjax import _memory

    drive, loop = fdjax.reference_drive(), fdjax.reference_controller()
    ref = fdjax.reciprocating()
    n = 8001
    for method, per_sample in ((fdjax.PadeODE(), 400), (fdjax.SampledData(), 300)):
        monkeypatch.setattr(_memory, "available_bytes", lambda p=per_sample: p * n)
        with pytest.raises(ValueError, match=rf"`simulate\(duration=\.\.\.\)`: 1 s is {n} output "
                                             r"samples .* GiB of memory available"):
            fdjax.simulate(loop, drive, ref, method, position_m=0.3, duration=1.0)
    # the sampled loop's run passes the memory check at 400 B per sample, and stops at the next
    # check (a twin that is not TwinOptions), before anything runs
    monkeypatch.setattr(_memory, "available_bytes", lambda: 400 * n)
    with pytest.raises(TypeError, match=r"`simulate\(twin=\.\.\.\)`"):
        fdjax.simulate(loop, drive, ref, fdjax.SampledData(), position_m=0.3, duration=1.0,
                       twin="none")
