"""Test configuration: float64 and strict dtype promotion for every test."""

import os

# XLA:CPU's concurrency-optimised scheduler has been seen to dead-lock (all threads asleep)
# on loops around LAPACK calls on this 2-core machine; the sequential scheduler avoids it.
# The tests compile thousands of programs and run most of them once or twice, so they compile
# with LLVM's optimisations off (FDJAX_TEST_OPTIMISE=1 keeps XLA's defaults): a third less
# CPU time for the suite, the same XLA graph optimisations, results equal to round-off.
# (XLA:CPU's classic fusion emitters, --xla_cpu_use_fusion_emitters=false, would compile a
# third faster, but they change results: model updating converges to another optimum and the
# coupled FRFs leave round-off.  The tests run the emitters users run.)
_flags = ["--xla_cpu_enable_concurrency_optimized_scheduler=false"]
if os.environ.get("FDJAX_TEST_OPTIMISE", "0") != "1":
    _flags += ["--xla_backend_optimization_level=0", "--xla_llvm_disable_expensive_passes=true"]
for _flag in _flags:
    if _flag.split("=")[0] not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _flag).strip()

import jax  # noqa: E402

import fdjax  # noqa: F401, E402  (importing fdjax switches float64 on)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


# XLA:CPU maps the machine code of every compiled program into memory; a long test session
# compiles thousands of programs and reaches the kernel's limit on memory maps (65530 by
# default), after which the next compilation crashes.  Dropping JAX's caches releases them.
_MAPS = f"/proc/{os.getpid()}/maps"
_MAX_MAPS = 30_000


def _n_maps() -> int:
    try:
        with open(_MAPS) as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux
        return 0


import gc  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _release_compiled_programs():
    yield
    if _n_maps() > _MAX_MAPS:
        jax.clear_caches()
        gc.collect()
