"""No recompilation for new values: positions and data reach the compiled programs as arrays.

``eqx.filter_jit`` treats a Python float as static (one compile per value) and a closure over
data as a new function (one compile per call).  Each test replaces a library's jitted core by
the same function wrapped in ``eqx.debug.assert_max_traces(max_traces=1)`` and calls the public
function with several values, as Python floats and as arrays: a second trace would raise.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import fdjax
from fdjax._drive import _model, _modes, _twin, _updating

POSITIONS = (0.1, 0.25, 0.4, 0.55, 0.7)


def _trace_once(monkeypatch, module, jitted: str, impl):
    """Make ``module.<jitted>`` the jitted ``impl`` that may be traced at most once."""
    monkeypatch.setattr(module, jitted, eqx.filter_jit(eqx.debug.assert_max_traces(
        impl, max_traces=1)))


@pytest.fixture(scope="module")
def drive():
    return fdjax.reference_drive()


def _values(positions):
    """Each position as a Python float, then as an array (float64, 0-d)."""
    return [*positions, *(jnp.asarray(y, jnp.float64) for y in positions)]


def test_frf_compiles_once_over_positions(drive, monkeypatch):
    _trace_once(monkeypatch, _model, "_drive_entries_jit", _model._drive_entries)
    freq = np.geomspace(10.0, 2000.0, 16)
    for y in _values(POSITIONS):
        drive.frf(y, freq)
    # 1-D arrays of one shape: the same program
    drive.frf(np.array([0.3]), freq)
    drive.frf(jnp.array([0.6]), freq)


def test_frf_direct_compiles_once_over_positions(drive, monkeypatch):
    _trace_once(monkeypatch, _model, "_drive_frf_direct_jit", _model._drive_frf_direct)
    freq = np.geomspace(10.0, 2000.0, 4)
    for y in _values(POSITIONS):
        drive.frf_direct(y, freq)


def test_fe_matrices_compiles_once_over_positions(drive, monkeypatch):
    _trace_once(monkeypatch, _twin, "_assemble_jit", _twin._assemble)
    for y in _values(POSITIONS):
        fdjax.fe_matrices(drive, y)


def test_state_space_compiles_once_over_positions(drive, monkeypatch):
    _trace_once(monkeypatch, _twin, "_realise_jit", _twin._realise)
    for y in _values(POSITIONS):
        fdjax.state_space(drive, y, twin=fdjax.TwinOptions(kept_modes=8))


def test_drive_modes_compiles_once_over_positions(drive, monkeypatch):
    _trace_once(monkeypatch, _modes, "_modes_jit", _modes._modes_at)
    _trace_once(monkeypatch, _modes, "_modes_batch_jit", _modes._modes_batch)
    for y in _values(POSITIONS):
        fdjax.drive_modes(drive, y, n_modes=4)
    fdjax.drive_modes(drive, np.array([0.2, 0.3]), n_modes=4)
    fdjax.drive_modes(drive, jnp.array([0.5, 0.6]), n_modes=4)


def test_update_model_compiles_once_for_new_data(drive, monkeypatch):
    """A second data set (target values, bounds, position, tolerances, visibility) of the same
    shapes runs the compiled solve again: the data go through optimistix's ``args``."""
    _trace_once(monkeypatch, _updating, "_update_jit", _updating._update)
    m = fdjax.drive_modes(drive, 0.2, n_modes=4)
    first = fdjax.update_model(
        drive, fdjax.ModalData(m.frequency_hz[:3], m.damping_ratio[:3], m.phase_deg[:3]),
        {"nut.stiffness": (1e8, 2e9), "carriage.pitch_stiffness": (1e6, 1e8)}, 0.2,
        n_modes=4, max_steps=2,
    )
    second = fdjax.update_model(
        drive, fdjax.ModalData(1.01 * m.frequency_hz[:3], 1.1 * m.damping_ratio[:3],
                               m.phase_deg[:3] - 5.0),
        {"nut.stiffness": (2e8, 1.8e9), "carriage.pitch_stiffness": (2e6, 5e7)}, 0.35,
        n_modes=4, max_steps=2, tolerances=(0.02, 0.2, 10.0), visibility=0.1,
    )
    assert int(first.steps) <= 2 and int(second.steps) <= 2
    assert first.parameters != second.parameters


def test_an_eager_objective_compiles_nothing_the_second_time(drive):
    """Called eagerly, the objective runs its compiled programs: a second call at a new
    position, with a new controller, compiles nothing (the discretisation shared by the run
    and the open loops used to run its matrix exponential's loops op by op, compiling them
    anew on every call: 0.3 s a call)."""
    from compile_events import compilations

    ref = fdjax.reciprocating(stroke=1e-3, v_max=0.05, a_max=2.0, j_max=400.0, cycles=1)
    obj = fdjax.Objective(ref, np.geomspace(5.0, 3900.0, 64),
                          twin=fdjax.TwinOptions(kept_modes=4))
    loop = fdjax.DoubleLoop()
    first = float(obj(loop, drive, 0.3).total)
    # a position given as a JAX scalar (weakly typed) is cast by JAX's own one-op program, the
    # first time such a scalar is cast in the process: its first call runs here
    float(obj(loop, drive, jnp.asarray(0.2)).total)
    stiffer = eqx.tree_at(lambda c: c.log_kv, loop, loop.log_kv + 0.1)
    y = jnp.asarray(0.3)
    with compilations() as names:
        again = float(obj(loop, drive, y).total)
        float(obj(stiffer, drive, 0.5).total)
    assert names == [], names
    assert again == first
