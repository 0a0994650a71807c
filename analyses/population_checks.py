"""Checks of the population (batch) stage on synthetic batches with known truth.

Study design (stated, so that "calibrated" has a meaning):

* truths from the virtual bench's ``draw_truth`` (type values drawn around the
  datasheet, unit-to-unit spread ``UNIT_SPREAD``), TEC1-12706 datasheet;
* batches alternate between 3 and 8 modules; half of them have one outlier
  (a random module), half of those the bench's own mechanism (S0 shifted by
  +-4 % of its unit draw), the other half one random parameter shifted by
  3-5 unit spreads (uniform, random sign);
* each module's posterior: its likelihood is Gaussian in the population
  coordinates (log R0, R1/R, log S0, S1/S, log K) around a noisy estimate of
  its truth, posterior sds drawn log-uniformly in R0 0.05-0.2 %, R1 1-3 %,
  S0 0.1-0.3 %, S1 3-10 %, K 0.3-1 % (of the value), correlations random
  (|r| up to ~0.5); 1000 exact draws of likelihood x interim prior.

Two priors on the unit-to-unit spreads are compared: ``default`` (weakly
informative, the module's defaults) and ``informed`` (the spreads learned from
an earlier 50-module batch of the type, ``PopulationResult.spread_prior``,
log-sd widened 1.5x).  ``oracle`` is the Bayes-optimal classifier that knows
the true population and the outlier mechanism and prior of this design: the
best any method can do here.

Also: two-stage vs joint fit on small batches with Gaussian likelihoods (where
the joint fit is exact), Gaussian vs importance sums, and timings for 3, 50
and 500 modules.

Run:  python analyses/population_checks.py [--batches 200] [--workers 2]
      python analyses/population_checks.py --quick        (a few minutes)
Writes analyses/results/population_checks.json and prints the tables.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from tembayes.bench.bench import TEC1_12706, UNIT_SPREAD, BenchConfig, draw_truth
from tembayes.calibrate.population import PopulationConvergenceWarning, fit_population, joint_fit
from tembayes.calibrate.priors import LEVEL_LOG_SD, SLOPE_REL_SD
from tembayes.constants import MODULE_PARAMETERS
from tembayes.data import write_json

RESULTS = Path(__file__).parent / "results"
DS = TEC1_12706
LEVEL = np.array([True, False, True, False, True])
REF = np.array([DS.resistance(), DS.resistance(), DS.seebeck(), DS.seebeck(), DS.conductance()])
#: Interim prior sd in x (exactly Gaussian there).
PRIOR_SD = np.where(LEVEL, LEVEL_LOG_SD, SLOPE_REL_SD)
SPREAD = np.array([UNIT_SPREAD[p] for p in MODULE_PARAMETERS])
#: Ranges of per-module posterior sd, relative to the value.
POST_SD_LO = np.array([0.0005, 0.01, 0.001, 0.03, 0.003])
POST_SD_HI = np.array([0.002, 0.03, 0.003, 0.10, 0.01])
S0_SHIFT = 0.04
TARGETS = {3: (0.5, 0.3), 8: (0.9, 0.1)}
BINS = (0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0)


def to_x(theta):
    theta = np.asarray(theta, dtype=float)
    return np.where(LEVEL, np.log(np.abs(theta) / REF), theta / REF)


def to_theta(x):
    return np.where(LEVEL, REF * np.exp(x), REF * x)


# --------------------------------------------------------------------------- synthetic batches


def draw_batch(rng, n, kind, *, n_draws=1000, corr=True, spreads=None):
    """Truth and per-module posteriors of one synthetic batch.

    Parameters
    ----------
    kind : {"none", "S0", "any", "spreads"}
        "spreads": one random parameter of a random module shifted by
        ``spreads`` unit spreads, random sign.

    Returns
    -------
    dict
        ``draws`` (id -> (n_draws, 5) SI), ``lik`` (id -> (mean, cov) in x),
        ``outlier`` (index or None), ``param`` (shifted parameter), ``type``
        (population type values, SI), ``theta`` (n, 5) SI truths.
    """
    ids = tuple(f"TEM{i + 1}" for i in range(n))
    k_out = int(rng.integers(n)) if kind != "none" else None
    cfg = BenchConfig(
        n_modules=n, outlier=ids[k_out] if kind == "S0" else None, outlier_shift=S0_SHIFT, n_validations=0
    )
    truth = draw_truth(cfg, rng)
    typ = np.array([truth["population"][p] for p in MODULE_PARAMETERS])
    theta = np.array([[truth["modules"][i][p] for p in MODULE_PARAMETERS] for i in ids])
    param = 2 if kind == "S0" else None
    if kind in ("any", "spreads"):
        param = int(rng.integers(5))
        size = rng.uniform(3.0, 5.0) if kind == "any" else float(spreads)
        theta[k_out, param] += rng.choice([-1.0, 1.0]) * size * SPREAD[param] * typ[param]
    draws, lik = {}, {}
    for i, mid in enumerate(ids):
        rel = np.exp(rng.uniform(np.log(POST_SD_LO), np.log(POST_SD_HI)))
        sd = np.where(LEVEL, rel, rel * np.abs(theta[i]) / REF)
        if corr:
            A = rng.standard_normal((5, 5))
            S = A @ A.T + 5.0 * np.eye(5)
            d = np.sqrt(np.diag(S))
            R = S / np.outer(d, d)
        else:
            R = np.eye(5)
        CL = R * np.outer(sd, sd)
        mL = to_x(theta[i]) + np.linalg.cholesky(CL) @ rng.standard_normal(5)
        P = np.linalg.inv(CL)
        Cp = np.linalg.inv(P + np.diag(PRIOR_SD**-2.0))
        mp = Cp @ (P @ mL)  # interim prior mean is 0 in x
        xd = mp + rng.standard_normal((n_draws, 5)) @ np.linalg.cholesky(Cp).T
        draws[mid] = to_theta(xd)
        lik[mid] = (mL, CL)
    return {
        "ids": ids,
        "draws": draws,
        "lik": lik,
        "outlier": k_out,
        "param": param,
        "type": typ,
        "theta": theta,
        "kind": kind,
    }


def gaussian_loglikes(lik):
    """Module id -> vectorised log likelihood of theta (n, 5) SI (Gaussian in x)."""
    out = {}
    for mid, (mL, CL) in lik.items():
        P = np.linalg.inv(CL)

        def f(theta, mL=mL, P=P):
            d = to_x(theta) - mL
            return -0.5 * np.einsum("ni,ij,nj->n", d, P, d)

        out[mid] = f
    return out


def read_jsonl(path):
    """The rows of a JSON-lines file (blank lines skipped)."""
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def member_logn(mL, CL, tau):
    """A module's Gaussian log density about a candidate mean, and its log-determinant.

    ``mL, CL``: the module's likelihood mean and covariance in x; ``tau``:
    the spreads in x.  Returns ``(logn, logdet)``: ``logn(mean)`` is
    ``-(mL - mean) V^-1 (mL - mean) / 2`` with ``V = CL + diag(tau^2)``.
    """
    V = CL + np.diag(tau**2)
    Vi = np.linalg.inv(V)

    def logn(mean):
        d = mL - mean
        return -0.5 * d @ Vi @ d

    return logn, np.linalg.slogdet(V)[1]


def oracle(batch):
    """Bayes-optimal outlier probabilities under the study design (true population known)."""
    typ = batch["type"]
    mu = to_x(typ)
    tau = np.where(LEVEL, SPREAD, SPREAD * np.abs(typ) / REF)
    n = len(batch["ids"])
    shifts = np.linspace(3.0, 5.0, 21)
    lr = np.zeros(n)
    for i, mid in enumerate(batch["ids"]):
        logn, _ = member_logn(*batch["lik"][mid], tau)
        base = logn(mu)
        # bench mechanism: S0 x (1 +- 4 %) -> x shift log(1 +- 0.04)
        e = np.zeros(5)
        e[2] = 1.0
        l_s0 = np.mean([np.exp(logn(mu + np.log(1 + s * S0_SHIFT) * e) - base) for s in (-1, 1)])
        l_any = 0.0
        for j in range(5):
            ej = np.zeros(5)
            ej[j] = 1.0
            dx = shifts * SPREAD[j] * (1.0 if LEVEL[j] else np.abs(typ[j]) / REF[j])
            for s in (-1, 1):
                l_any += np.mean([np.exp(logn(mu + s * d * ej) - base) for d in dx]) / 10.0
        lr[i] = 0.5 * l_s0 + 0.5 * l_any
    po = 0.5 / n * lr
    return po / (0.5 + po.sum())


# --------------------------------------------------------------------------- the study


def _one(task):
    seed, n, kind, priors = task
    rng = np.random.default_rng(seed)
    batch = draw_batch(rng, n, kind)
    row = {
        "seed": seed,
        "n": n,
        "kind": kind,
        "outlier": batch["outlier"],
        "param": batch["param"],
        "oracle": oracle(batch).tolist(),
    }
    for name, sp in priors.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PopulationConvergenceWarning)
            r = fit_population(batch["draws"], DS, rng=np.random.default_rng(seed + 1), spread_prior=sp)
        row[name] = [r.outlier_prob[i] for i in batch["ids"]]
        row[name + "_diag"] = {
            k: r.diagnostics[k]
            for k in ("converged", "rhat_max", "ess_bulk_min", "n_steps", "elapsed_s", "weight_ess_min")
        }
        row[name + "_diag"]["check"] = r.diagnostics["check"]
    return row


def informed_prior(seed):
    """Spreads from an earlier 50-module batch of the type (no outlier)."""
    batch = draw_batch(np.random.default_rng(seed), 50, "none")
    r = fit_population(batch["draws"], DS, rng=np.random.default_rng(seed))
    return r.spread_prior(widen=1.5), r


def rates(rows, key):
    """Detection rates against the targets, per batch size and outlier kind."""
    out = {}
    for n, (hi, lo) in TARGETS.items():
        for kind in ("S0", "any"):
            sel = [r for r in rows if r["n"] == n and r["kind"] == kind]
            if not sel:
                continue
            p_out = np.array([r[key][r["outlier"]] for r in sel])
            p_oth = np.array([max(p for i, p in enumerate(r[key]) if i != r["outlier"]) for r in sel])
            top = np.array([int(np.argmax(r[key])) == r["outlier"] for r in sel])
            out[f"{n}_{kind}"] = {
                "batches": len(sel),
                "threshold_outlier": hi,
                "threshold_others": lo,
                "outlier_above": float(np.mean(p_out > hi)),
                "others_below": float(np.mean(p_oth < lo)),
                "outlier_top": float(np.mean(top)),
                "all_three": float(np.mean((p_out > hi) & (p_oth < lo) & top)),
                "median_outlier_prob": float(np.median(p_out)),
            }
        sel = [r for r in rows if r["n"] == n and r["kind"] == "none"]
        if sel:
            mx = np.array([max(r[key]) for r in sel])
            out[f"{n}_none"] = {
                "batches": len(sel),
                "false_alarm_above_0.3": float(np.mean(mx > 0.3)),
                "max_prob_median": float(np.median(mx)),
            }
    return out


def target_summary(rows, key):
    """The study's targets as rates over its batches."""
    out = {}
    for n, (hi, lo) in TARGETS.items():
        sel = [r for r in rows if r["n"] == n and r["kind"] != "none"]
        ok = [
            int(np.argmax(r[key])) == r["outlier"]
            and r[key][r["outlier"]] > hi
            and max(p for i, p in enumerate(r[key]) if i != r["outlier"]) < lo
            for r in sel
        ]
        out[f"{n} modules: outlier top, > {hi}, others < {lo}"] = float(np.mean(ok))
    sel = [r for r in rows if r["kind"] == "none"]
    out["no outlier: nobody > 0.3"] = float(np.mean([max(r[key]) <= 0.3 for r in sel]))
    return out


def calibration(rows, key):
    p = np.concatenate([r[key] for r in rows])
    y = np.concatenate([[i == r["outlier"] for i in range(r["n"])] for r in rows]).astype(float)
    table = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        s = (p >= lo) & ((p < hi) if hi < 1 else (p <= hi))
        k = int(s.sum())
        frac = float(y[s].mean()) if k else None
        se = float(np.sqrt(frac * (1 - frac) / k)) if k else None
        table.append(
            {
                "bin": [lo, hi],
                "modules": k,
                "mean_prob": float(p[s].mean()) if k else None,
                "outlier_fraction": frac,
                "se": se,
            }
        )
    brier = float(np.mean((p - y) ** 2))
    return {"table": table, "brier": brier}


# --------------------------------------------------------------------------- joint, methods, timings


def _mcse_mean(a):
    import arviz as az

    return float(np.std(a) / np.sqrt(az.ess(np.asarray(a))))


def joint_check(seed, n=3):
    """Two-stage vs joint fit on one batch with Gaussian likelihoods (joint exact)."""
    rng = np.random.default_rng(seed)
    batch = draw_batch(rng, n, "S0" if seed % 2 == 0 else "none")
    t = time.perf_counter()
    two = fit_population(batch["draws"], DS, rng=np.random.default_rng(seed))
    t_two = time.perf_counter() - t
    t = time.perf_counter()
    joint = joint_fit(gaussian_loglikes(batch["lik"]), DS, rng=np.random.default_rng(seed))
    t_joint = time.perf_counter() - t
    rows = []
    for k in two.hyper:
        for stat in ("mean", "sd"):
            a, b = two.hyper[k], joint.hyper[k]
            if stat == "mean":
                va, vb, sa, sb = a.mean(), b.mean(), _mcse_mean(a), _mcse_mean(b)
            else:  # se of an sd ~ se of the mean of (x - m)^2 / (2 sd)
                va, vb = a.std(), b.std()
                sa = _mcse_mean((a - a.mean()) ** 2) / (2 * va)
                sb = _mcse_mean((b - b.mean()) ** 2) / (2 * vb)
            rows.append(
                {
                    "quantity": f"{stat} {k}",
                    "two_stage": float(va),
                    "joint": float(vb),
                    "z": float((va - vb) / np.hypot(sa, sb)),
                }
            )
    for mid in batch["ids"]:
        a, b = two.outlier_prob[mid], joint.outlier_prob[mid]
        sa, sb = two.diagnostics["outlier_prob_mcse"][mid], joint.diagnostics["outlier_prob_mcse"][mid]
        rows.append(
            {
                "quantity": f"outlier_prob {mid}",
                "two_stage": a,
                "joint": b,
                "z": float((a - b) / max(np.hypot(sa, sb), 1e-6)),
            }
        )
    z = np.array([r["z"] for r in rows])
    return {
        "seed": seed,
        "n_modules": n,
        "kind": batch["kind"],
        "rows": rows,
        "max_abs_z": float(np.abs(z).max()),
        "rms_z": float(np.sqrt(np.mean(z**2))),
        "converged": [two.diagnostics["converged"], joint.diagnostics["converged"]],
        "seconds": {"two_stage": t_two, "joint": t_joint},
    }


def method_check(seed, n=8):
    """Gaussian approximation vs importance sums (256 thinned draws per module) on the same batch."""
    batch = draw_batch(np.random.default_rng(seed), n, "any")
    out = {}
    for method in ("gaussian", "importance"):
        t = time.perf_counter()
        r = fit_population(batch["draws"], DS, rng=np.random.default_rng(seed), method=method)
        out[method] = {
            "seconds": time.perf_counter() - t,
            "outlier_prob": [r.outlier_prob[i] for i in batch["ids"]],
            "mcse": [r.diagnostics["outlier_prob_mcse"][i] for i in batch["ids"]],
            "summary": r.summary(),
            "weight_ess_min": r.diagnostics["weight_ess_min"],
        }
    d = np.abs(np.array(out["gaussian"]["outlier_prob"]) - np.array(out["importance"]["outlier_prob"]))
    out["outlier_prob_diff_max"] = float(d.max())
    return out


def timing(n, seed=11):
    batch = draw_batch(np.random.default_rng(seed), n, "none", n_draws=1000)
    t = time.perf_counter()
    r = fit_population(batch["draws"], DS, rng=np.random.default_rng(seed))
    sec = time.perf_counter() - t
    d = r.diagnostics
    return {
        "modules": n,
        "seconds": sec,
        "n_steps": d["n_steps"],
        "converged": d["converged"],
        "tau_max": d["tau_max"],
        "rhat_max": d["rhat_max"],
        "ess_bulk_min": d["ess_bulk_min"],
        "method": d["method"],
        "check": d["check"],
        "weight_ess_min": d["weight_ess_min"],
        "sampling_s": d["sampling_s"],
    }


# --------------------------------------------------------------------------- main


def _fmt_rates(name, r):
    lines = []
    for k, v in r.items():
        if k.endswith("none"):
            lines.append(
                f"  {name:<8s} {k:<7s} false alarms (max > 0.3): {v['false_alarm_above_0.3']:.2f}"
                f"  (median max prob {v['max_prob_median']:.2f}, {v['batches']} batches)"
            )
        else:
            lines.append(
                f"  {name:<8s} {k:<7s} outlier > {v['threshold_outlier']}: {v['outlier_above']:.2f}  "
                f"others < {v['threshold_others']}: {v['others_below']:.2f}  top: {v['outlier_top']:.2f}  "
                f"all three: {v['all_three']:.2f}  (median p_out {v['median_outlier_prob']:.2f}, "
                f"{v['batches']} batches)"
            )
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batches", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--joint", type=int, default=2, help="number of two-stage vs joint comparisons")
    ap.add_argument("--quick", action="store_true", help="24 batches, one joint check, timings up to 50")
    args = ap.parse_args(argv)
    if args.quick:
        args.batches, args.joint = 24, 1
    t_start = time.perf_counter()
    out = {
        "design": {
            "batches": args.batches,
            "sizes": [3, 8],
            "outlier_share": 0.5,
            "outlier_kinds": {"S0": f"S0 x (1 +- {S0_SHIFT})", "any": "one parameter +- 3-5 unit spreads"},
            "posterior_sd_rel": {p: [float(a), float(b)] for p, a, b in zip(MODULE_PARAMETERS, POST_SD_LO, POST_SD_HI)},
            "unit_spread": UNIT_SPREAD,
            "seed": args.seed,
        }
    }

    print("informed spread prior from a 50-module batch ...", flush=True)
    sp, r50 = informed_prior(args.seed + 999)
    out["informed_prior"] = {
        "spread_prior": sp,
        "true_unit_spread": UNIT_SPREAD,
        "diagnostics": {k: r50.diagnostics[k] for k in ("converged", "n_steps", "elapsed_s")},
    }
    for k, (med, lsd) in sp.items():
        print(f"  {k:<18s} median {med:.4g}  log-sd {lsd:.2f}")

    kinds = ["none", "none", "S0", "any"]
    seeds = np.random.SeedSequence(args.seed).generate_state(args.batches)
    tasks = [
        (int(seeds[b]), 3 if b % 2 == 0 else 8, kinds[(b // 2) % 4], {"default": None, "informed": sp})
        for b in range(args.batches)
    ]
    print(f"study: {len(tasks)} batches x 2 priors on {args.workers} workers ...", flush=True)
    t = time.perf_counter()
    if args.workers > 1:
        with multiprocessing.get_context("fork").Pool(args.workers) as pool:
            rows = pool.map(_one, tasks, chunksize=1)
    else:
        rows = [_one(task) for task in tasks]
    out["study_seconds"] = time.perf_counter() - t
    out["rates"] = {k: rates(rows, k) for k in ("default", "informed", "oracle")}
    out["calibration"] = {k: calibration(rows, k) for k in ("default", "informed", "oracle")}
    out["targets"] = {k: target_summary(rows, k) for k in ("default", "informed", "oracle")}
    conv = [r[k + "_diag"]["converged"] for r in rows for k in ("default", "informed")]
    checks = [r[k + "_diag"]["check"] for r in rows for k in ("default", "informed")]
    out["study_diagnostics"] = {
        "converged_fraction": float(np.mean(conv)),
        "seconds_median": float(
            np.median([r[k + "_diag"]["elapsed_s"] for r in rows for k in ("default", "informed")])
        ),
        "gaussian_check_passed_fraction": float(np.mean([c["passed"] for c in checks])),
        "gaussian_check_outlier_diff_max": float(np.max([c["outlier_prob_diff_max"] for c in checks])),
        "weight_ess_min": float(
            np.min([r[k + "_diag"]["weight_ess_min"] for r in rows for k in ("default", "informed")])
        ),
    }
    # a finer view: which parameter was off (informed prior, 8 modules)
    by_param = {}
    for j, p in enumerate(MODULE_PARAMETERS):
        sel = [r for r in rows if r["kind"] != "none" and r["param"] == j]
        if sel:
            by_param[p] = {
                k: float(np.median([r[k][r["outlier"]] for r in sel])) for k in ("default", "informed", "oracle")
            }
            by_param[p]["batches"] = len(sel)
    out["median_outlier_prob_by_parameter"] = by_param
    out["rows"] = rows

    print("two-stage vs joint ...", flush=True)
    out["joint"] = [joint_check(args.seed + 100 + k) for k in range(args.joint)]
    print("gaussian vs importance ...", flush=True)
    out["methods"] = method_check(args.seed + 200)
    print("timings ...", flush=True)
    out["timings"] = [timing(n) for n in ((3, 50) if args.quick else (3, 50, 500))]
    out["total_seconds"] = time.perf_counter() - t_start

    lines = [
        f"population checks: {args.batches} batches (3 and 8 modules, half with one outlier)",
        "targets met (fraction of batches; default / informed / oracle):",
    ]
    for t in out["targets"]["default"]:
        lines.append(
            f"  {t:<44s} " + " / ".join(f"{out['targets'][k][t]:.2f}" for k in ("default", "informed", "oracle"))
        )
    for k in ("default", "informed", "oracle"):
        lines += _fmt_rates(k, out["rates"][k])
    lines.append("calibration (bin: modules, mean prob -> observed outlier fraction):")
    for k in ("default", "informed", "oracle"):
        cells = [
            f"[{c['bin'][0]:.1f},{c['bin'][1]:.1f}) {c['modules']}: {c['mean_prob']:.2f}->{c['outlier_fraction']:.2f}"
            for c in out["calibration"][k]["table"]
            if c["modules"]
        ]
        lines.append(f"  {k:<8s} " + "  ".join(cells) + f"  Brier {out['calibration'][k]['brier']:.4f}")
    lines.append("median outlier_prob of the outlier by shifted parameter (default / informed / oracle):")
    for p, v in by_param.items():
        lines.append(
            f"  {p:<14s} {v['default']:.2f} / {v['informed']:.2f} / {v['oracle']:.2f}  ({v['batches']} batches)"
        )
    d = out["study_diagnostics"]
    lines.append(
        f"fits converged: {d['converged_fraction']:.3f}; Gaussian-vs-importance check passed "
        f"{d['gaussian_check_passed_fraction']:.3f} (max outlier_prob diff {d['gaussian_check_outlier_diff_max']:.3f}); "
        f"median fit {d['seconds_median']:.1f} s; min importance-weight ESS {d['weight_ess_min']:.0f}"
    )
    for j in out["joint"]:
        lines.append(
            f"two-stage vs joint (seed {j['seed']}, {j['n_modules']} modules, {j['kind']}): max |z| "
            f"{j['max_abs_z']:.2f}, rms z {j['rms_z']:.2f} over {len(j['rows'])} quantities; "
            f"converged {j['converged']}; {j['seconds']['two_stage']:.0f} s vs {j['seconds']['joint']:.0f} s"
        )
        for row in j["rows"]:
            if row["quantity"].startswith("outlier_prob") or row["quantity"].startswith("mean tau"):
                lines.append(
                    f"    {row['quantity']:<28s} {row['two_stage']:.4g} vs {row['joint']:.4g} (z {row['z']:+.2f})"
                )
    m = out["methods"]
    lines.append(
        f"gaussian vs importance (8 modules): max outlier_prob diff {m['outlier_prob_diff_max']:.3f}; "
        f"{m['gaussian']['seconds']:.1f} s vs {m['importance']['seconds']:.1f} s"
    )
    for tm in out["timings"]:
        lines.append(
            f"timing: {tm['modules']:>3d} modules {tm['seconds']:6.1f} s ({tm['n_steps']} steps, "
            f"method {tm['method']}, converged {tm['converged']}, check passed "
            f"{tm['check']['passed'] if tm['check'] else None})"
        )
    lines.append(f"total {out['total_seconds']:.0f} s")
    print("\n".join(lines))
    out["printed"] = lines
    path = write_json(RESULTS / "population_checks.json", out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
