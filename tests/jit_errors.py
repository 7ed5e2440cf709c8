"""What a failed check inside a compiled program raises: ``eqx.filter_jit`` an
``EquinoxRuntimeError``; ``jax.jit`` a ``JaxRuntimeError``, or, from some XLA:CPU programs, a
``ValueError`` ("INTERNAL: CpuCallback error", the check's message inside).  The tests match
the message as well."""

from equinox import EquinoxRuntimeError
from jax.errors import JaxRuntimeError

CHECK_FAILED = (JaxRuntimeError, EquinoxRuntimeError, ValueError)
