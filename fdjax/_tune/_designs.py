r"""Saving and loading a set of named controllers (the designs of a synthesis), bit for bit.

``DIR/controllers.eqx`` holds the leaves of every controller (``eqx.tree_serialise_leaves``),
``DIR/controllers.json`` what is needed to rebuild their structure (kind, the network's width,
the number of interpolation points, the filter bounds) and the user's metadata (the drive they
were tuned for, the objective, the units).
"""

from __future__ import annotations

import os

import jax.numpy as jnp

from .._control._controllers import AbstractController, DoubleLoop, PIDLoop
from .._filters import MCM, NotchFilter, PeakFilter
from ._parameterisation import MCM_PARAMETERS
from ._schedule import (
    ATANetwork,
    InterpolatedLoop,
    ScheduledLoop,
    bounds_from_json,
    bounds_json,
    read_json,
    read_leaves,
    write_pair,
)

__all__ = ["save_designs", "load_designs"]

_FORMAT = "fdjax-designs/1"


def _describe(name: str, c: AbstractController) -> dict:
    if isinstance(c, ScheduledLoop):
        return {"kind": "ScheduledLoop", "width": c.network.width, "gains": c.network.gains,
                "travel_m": list(c.network.travel_m), "bounds": bounds_json(c.bounds)}
    if isinstance(c, InterpolatedLoop):
        return {"kind": "InterpolatedLoop", "n_points": int(c.positions_m.shape[0]),
                "bounds": bounds_json(c.bounds)}
    if isinstance(c, DoubleLoop):
        if not isinstance(c.mcm, MCM):
            raise ValueError(f"`save_designs(controllers=...)`: {name!r} must have an fdjax.MCM "
                             f"(of peak and notch filters), got a {type(c.mcm).__name__}")
        return {"kind": "DoubleLoop",
                "peaks": 0 if c.mcm.peak is None else int(c.mcm.peak.K.shape[0]),
                "notches": 0 if c.mcm.notch is None else int(c.mcm.notch.omega.shape[0])}
    if isinstance(c, PIDLoop):
        return {"kind": "PIDLoop"}
    raise TypeError(f"`save_designs(controllers=...)`: {name!r} is a {type(c).__name__}; "
                    "DoubleLoop, PIDLoop, InterpolatedLoop and ScheduledLoop can be saved")


def _skeleton(d: dict) -> AbstractController:
    kind = d["kind"]
    if kind == "PIDLoop":
        return PIDLoop()
    if kind == "DoubleLoop":  # files written before the counts were recorded: one and one
        n_p, n_n = d.get("peaks", 1), d.get("notches", 1)
        peak = PeakFilter(*(jnp.full(n_p, v) for v in (0.1, 1000.0, 0.1, 0.0))) if n_p else None
        notch = NotchFilter(*(jnp.full(n_n, v) for v in (5000.0, 0.01, 0.1))) if n_n else None
        return DoubleLoop(mcm=MCM(peak, notch))
    if kind == "InterpolatedLoop":
        n = d["n_points"]
        return InterpolatedLoop(DoubleLoop(), jnp.arange(1.0, n + 1.0),
                                jnp.zeros((n, len(MCM_PARAMETERS))), bounds_from_json(d["bounds"]))
    if kind == "ScheduledLoop":
        net = ATANetwork(tuple(d["travel_m"]), width=d["width"], gains=d.get("gains", False))
        return ScheduledLoop(DoubleLoop(), net, bounds_from_json(d["bounds"]))
    raise ValueError(f"`load_designs(folder=...)`: unknown controller kind {kind!r}")


def save_designs(folder: str | os.PathLike, controllers: dict[str, AbstractController], *,
                 metadata: dict | None = None) -> None:
    """Write ``controllers`` (a dict name → controller) to ``folder``/controllers.eqx and
    ``folder``/controllers.json (module docstring); :func:`load_designs` reads them back bit
    for bit."""
    if not isinstance(controllers, dict) or not controllers:
        raise TypeError("`save_designs(controllers=...)` must be a non-empty dict of name → "
                        "controller")
    for k in controllers:  # JSON's keys are strings: another key would not come back
        if not isinstance(k, str):
            raise TypeError(f"`save_designs(controllers=...)` must be named by strings, got "
                            f"the key {k!r} ({type(k).__name__})")
    meta = {"format": _FORMAT, "names": list(controllers),
            "controllers": {k: _describe(k, c) for k, c in controllers.items()},
            "metadata": dict(metadata or {})}
    folder = os.fspath(folder)
    os.makedirs(folder, exist_ok=True)
    write_pair(os.path.join(folder, "controllers.eqx"), controllers,
               os.path.join(folder, "controllers.json"), meta, "save_designs")


SHIPPED = os.path.join(os.path.dirname(os.path.dirname(__file__)), "data", "reference_designs")
"""The designs shipped with fdjax: Fig. 18's seven controllers, tuned by ``fdjax tune`` for
:func:`fdjax.reference_drive`."""


def load_designs(
    folder: str | os.PathLike | None = None,
) -> tuple[dict[str, AbstractController], dict]:
    """Read the controllers written by :func:`save_designs`: (dict name → controller, the
    metadata).  Without a folder: the designs shipped with fdjax (Fig. 18's seven controllers
    for the reference drive, ``"mcm_ata_e2e"`` the end-to-end schedule; the metadata says how
    they were tuned)."""
    folder = SHIPPED if folder is None else os.fspath(folder)
    where = "load_designs(folder=...)"
    if os.path.isfile(folder):  # the file given for its folder
        raise NotADirectoryError(f"`{where}` must be the folder that holds controllers.eqx and "
                                 f"controllers.json, got the file {folder!r}; did you mean "
                                 f"{os.path.dirname(folder) or '.'!r}?")
    leaves, meta_path = (os.path.join(folder, n) for n in ("controllers.eqx", "controllers.json"))
    for p in (leaves, meta_path):
        if not os.path.exists(p):
            raise FileNotFoundError(f"`{where}`: no file {p!r}")
    meta = read_json(meta_path, where, "a set of fdjax designs")
    if meta.get("format") != _FORMAT:
        raise ValueError(f"`{where}`: {meta_path!r} is not a set of fdjax "
                         f"designs (format {meta.get('format')!r}, expected {_FORMAT!r})")
    try:
        like = {k: _skeleton(meta["controllers"][k]) for k in meta["names"]}
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"`{where}`: {meta_path!r} does not describe a set of fdjax designs "
                         f"({type(err).__name__}: {err})") from err
    got = read_leaves(leaves, like, where, "the designs")
    return {k: got[k] for k in meta["names"]}, meta.get("metadata", {})
