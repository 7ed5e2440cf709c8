"""Why gradient descent is slow on the local tuning problem: the objective's landscape between
the gradient tuner's design and the derivative-free tuner's.

``benchmarks/tuning.py`` tunes the 12-parameter double loop at six positions by L-BFGS
(``fdjax.tune_local``) and by Nelder–Mead on the same objective J.  This script reads its
results (``benchmarks/results/tuning.json``) and, at one position (default 0.1 m), measures

* J, its terms and the gradient norm at the start, at L-BFGS's best design and at Nelder–Mead's;
* J on the straight segment from L-BFGS's design to Nelder–Mead's (is there a ridge between
  them, i.e. another basin, or is the segment downhill?);
* the spectrum of the Hessian ∇²J at L-BFGS's design (``jax.hessian``, forward over reverse):
  its condition and its negative curvature, and the spectra of its two parts, the margin
  penalties (``Objective.margin_term``) and the simulated terms (``Objective.simulated_term``);
* what trust-region Newton steps with that exact Hessian (``fdjax.tune_newton``) make of
  the valley.

About 2 minutes on 2 cores (the Hessians' programs take most of it to compile).

Usage:  python examples/tuning_landscape.py [--results benchmarks/results/tuning.json]
        [--position 0] [--newton-steps 30] [--out landscape.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import fdjax

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "benchmarks"))
from tuning import setup  # noqa: E402  (the benchmark's problem, exactly)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("--results", default=os.path.join(HERE, "..", "benchmarks", "results",
                                                      "tuning.json"))
    ap.add_argument("--position", type=int, default=0, help="index into the six positions")
    ap.add_argument("--newton-steps", type=int, default=30)
    ap.add_argument("--out", default=None, help="write the measurements to this JSON file")
    args = ap.parse_args()
    r = json.load(open(args.results))
    if r["quick"]:
        sys.exit(f"{args.results} is a --quick run; run benchmarks/tuning.py in full first")
    drive, par, obj, positions, start = setup(6)
    i = args.position
    y = float(positions[i])
    theta = {"start": np.asarray(par.from_controller(start)),
             "lbfgs": np.asarray(r["methods"]["lbfgs"]["gradient"]["best_theta"][i]),
             "nelder_mead": np.asarray(r["derivative_free"]["positions"][i]["theta_best"])}

    def J(th):
        return obj(par.to_controller(th), drive, y).total

    terms = eqx.filter_jit(lambda th: obj(par.to_controller(th), drive, y))
    value_and_grad = eqx.filter_jit(jax.value_and_grad(J))
    out = {"position_m": y, "designs": {}}
    print(f"at {y * 1e3:.0f} mm")
    for name, th in theta.items():
        t = terms(jnp.asarray(th))
        _, g = value_and_grad(jnp.asarray(th))
        row = {"J": float(t.total), "rms_error_um": float(t.rms_error_m) * 1e6,
               "margin_penalty": float(t.margin_penalty),
               "growth_rate_per_s": float(t.growth_rate),
               "gradient_norm": float(jnp.linalg.norm(g)), "theta": th.tolist()}
        out["designs"][name] = row
        print(f"  {name:12s} J {row['J']:.4f}  RMS {row['rms_error_um']:.3f} µm  margin "
              f"penalty {row['margin_penalty']:.4f}  |∇J| {row['gradient_norm']:.3g}")
    a = np.linspace(0.0, 1.0, 11)
    d = theta["nelder_mead"] - theta["lbfgs"]
    seg = [float(terms(jnp.asarray(theta["lbfgs"] + s * d)).total) for s in a]
    out["segment"] = {"fraction": a.tolist(), "J": seg,
                      "monotone_decreasing": bool(np.all(np.diff(seg) < 0))}
    print("  J from L-BFGS's design (0) to Nelder–Mead's (1):",
          " ".join(f"{v:.3f}" for v in seg))
    print("  downhill all the way (one basin)" if out["segment"]["monotone_decreasing"]
          else "  a ridge between them (another basin)")
    hess = eqx.filter_jit(jax.hessian(J))
    h = np.asarray(hess(jnp.asarray(theta["lbfgs"])))
    w, v = np.linalg.eigh(0.5 * (h + h.T))
    _, g = value_and_grad(jnp.asarray(theta["lbfgs"]))
    out["hessian_at_lbfgs"] = {
        "eigenvalues": w.tolist(),
        "gradient_in_eigenbasis": (v.T @ np.asarray(g)).tolist(),
        "step_to_nelder_mead_in_eigenbasis": (v.T @ d).tolist()}
    print("  Hessian eigenvalues at L-BFGS's design:", " ".join(f"{x:.3g}" for x in w))
    pos = w[w > 0]
    print(f"  positive ones span {pos.max() / pos.min():.3g}; {int(np.sum(w < 0))} negative")
    # whose walls: J = J_m + J_s, the margin penalties (the open loops on the frequency grid,
    # no simulation) and the rest (the simulated tracking error and the barriers)
    for key, name, term in (("margin_term", "margin penalties'", obj.margin_term),
                            ("simulated_term", "simulated terms'", obj.simulated_term)):
        h_t = np.asarray(eqx.filter_jit(jax.hessian(
            lambda th, term=term: term(par.to_controller(th), drive, y)))(
                jnp.asarray(theta["lbfgs"])))
        w_t = np.linalg.eigvalsh(0.5 * (h_t + h_t.T))
        out["hessian_at_lbfgs"][key] = w_t.tolist()
        print(f"  the {name} Hessian there, its three largest: "
              + " ".join(f"{x:.3g}" for x in w_t[::-1][:3]))
    # trust-region Newton steps with that exact Hessian from L-BFGS's design
    r_newton = fdjax.tune_newton(par, obj, drive, np.array([y]), theta["lbfgs"],
                                 steps=args.newton_steps)
    trials = np.asarray(r_newton.history)[:, 0]
    newton = np.minimum.accumulate(trials)[1:].tolist()  # J of the accepted point per step
    out["trust_region_newton_from_lbfgs"] = newton
    nm_best = out["designs"]["nelder_mead"]["J"]
    below = [k + 1 for k, v in enumerate(newton) if v <= nm_best]
    print(f"  {args.newton_steps} trust-region Newton steps from L-BFGS's design: J "
          f"{out['designs']['lbfgs']['J']:.4f} → {newton[-1]:.4f}; Nelder–Mead's best "
          f"{nm_best:.4f} " + (f"passed at step {below[0]}" if below else "not reached"))
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(out, fh, indent=2)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
