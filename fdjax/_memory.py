"""Releasing compiled programs before a process runs out of memory maps.

XLA:CPU maps the machine code of every compiled program into memory: thousands of maps for
one of the tuning programs (a line-search step with the whole sampled simulation inside), and
the kernel allows a process 65530 by default (``vm.max_map_count``), after which the next
compilation fails ("LLVM compilation error: Cannot allocate memory") and the process crashes.
Long pipelines (:func:`fdjax.synthesise`, :func:`fdjax.evaluate`) call :func:`release` between
stages: past a threshold it drops JAX's caches, which frees the maps; a program needed again
is compiled again.
"""

from __future__ import annotations

import gc
import os

import jax

__all__ = ["release", "memory_maps", "available_bytes"]

_THRESHOLD = 25_000


def memory_maps() -> int:
    """The number of memory maps of this process (0 where /proc is not there)."""
    try:
        with open(f"/proc/{os.getpid()}/maps") as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


def release(threshold: int = _THRESHOLD) -> bool:
    """Drop JAX's compiled programs when the process holds more than ``threshold`` memory
    maps; True when it did."""
    if memory_maps() <= threshold:
        return False
    jax.clear_caches()
    gc.collect()
    return True


def available_bytes() -> int | None:
    """The memory available to a new allocation (MemAvailable of /proc/meminfo, bytes), or
    None where it cannot be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None
