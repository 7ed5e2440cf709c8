"""Counting what XLA compiles inside a block (JAX's compilation events), for the tests that
check a second call compiles nothing."""

import contextlib

import jax


@contextlib.contextmanager
def compilations():
    """The names of the functions XLA compiles inside the block (JAX's compilation events)."""
    names = []

    def listen(event, seconds, fun_name=None, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            names.append(str(fun_name))  # e.g. "jit(_run)"

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield names
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
