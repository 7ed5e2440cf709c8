"""Test configuration: float64 and strict dtype promotion for every test."""

import os

# XLA:CPU's concurrency-optimised scheduler has been seen to dead-lock (all threads asleep)
# on loops around LAPACK calls on this 2-core machine; the sequential scheduler avoids it.
# The tests compile thousands of programs and run most of them once or twice (compilation is
# two thirds of the suite's CPU time), so unless FDJAX_TEST_OPTIMISE=1 they compile
# * with LLVM's optimisations off: a third less CPU time, the same XLA graph optimisations;
# * with XLA:CPU's classic fusion emitters (--xla_cpu_use_fusion_emitters=false): a third less
#   again (measured: `make test` 481 → 335 s, 901 → 593 CPU-s).
# Results agree with XLA's defaults to round-off (every tolerance holds under both; the one
# entry that moved most, θ1/F3 at 3 kHz in test_table, 2.8e-10 → 6.7e-10 relative, is 1e-12 of
# its own peak), and `fdjax demo` prints the same text under both.  A jaxlib that no longer
# knows the emitters' flag keeps its defaults (XLA aborts on an unknown flag: it is tried first
# in a subprocess).
_flags = ["--xla_cpu_enable_concurrency_optimized_scheduler=false"]
_CLASSIC = "--xla_cpu_use_fusion_emitters=false"


def _flag_known(flag: str) -> bool:
    import subprocess
    import sys

    env = dict(os.environ, XLA_FLAGS=flag, JAX_PLATFORMS="cpu")
    try:
        run = subprocess.run([sys.executable, "-c", "import jax.numpy as j; j.zeros(1) + 1"],
                             env=env, capture_output=True, timeout=300)
    except (OSError, subprocess.SubprocessError):
        return False
    return run.returncode == 0


if os.environ.get("FDJAX_TEST_OPTIMISE", "0") != "1":
    _flags += ["--xla_backend_optimization_level=0", "--xla_llvm_disable_expensive_passes=true"]
    # tried once per session: the worker processes inherit the answer
    if "FDJAX_TEST_CLASSIC_EMITTERS" not in os.environ:
        os.environ["FDJAX_TEST_CLASSIC_EMITTERS"] = "1" if _flag_known(_CLASSIC) else "0"
    if os.environ["FDJAX_TEST_CLASSIC_EMITTERS"] == "1":
        _flags.append(_CLASSIC)
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
# They are dropped between two test files, where a worker passes _MAX_MAPS (one file's tests
# share compiled programs, which a drop in its middle would compile again: test_control.py
# alone maps about 10 000), and after any test past _HARD_MAPS.
_MAPS = f"/proc/{os.getpid()}/maps"
_MAX_MAPS = 30_000
_HARD_MAPS = 50_000


def _n_maps() -> int:
    try:
        with open(_MAPS) as f:
            return sum(1 for _ in f)
    except OSError:  # not Linux
        return 0


import gc  # noqa: E402

import pytest  # noqa: E402


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item, nextitem):
    n = _n_maps()
    last_of_file = nextitem is None or nextitem.path != item.path
    if n > _HARD_MAPS or (n > _MAX_MAPS and last_of_file):
        jax.clear_caches()
        gc.collect()
