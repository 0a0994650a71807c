"""The outlier question on the out-of-model bench: the module stage included.

``outlier_study.py`` checks the population stage on synthetic module
posteriors.  Here every module is simulated on the out-of-model bench
(``tembayes simulate --fidelity high``: a rig and module the calibration model
does not contain) and calibrated by ``tembayes calibrate`` with its defaults,
so the population stage sees posteriors with the module stage's real errors,
part of them shared by the batch's modules.

Design (stated before the runs):

* null batches: the out-of-model runs of the law-coverage study
  (``analyses/law_coverage.py --fidelity high``, ``--null-runs``: 4 modules
  without an outlier, two module types), their module files refitted by the
  population stage of this code, as the batch of 4 and as each of its four
  3-module sub-batches;
* outlier batches: 4 modules of a type, one of them (cycling TEM1..TEM4)
  with S0 shifted by 4 or 6 of the bench's S0 unit spreads (1 %), random sign
  (``simulate --outlier``), the two types alternating; fitted as the batch of
  4 and as each 3-module sub-batch that holds the outlier;
* every fit twice: ``default`` (the spread hyperprior) and ``informed`` (the
  spreads one null batch of the type learned, its first batch, as
  ``--population-prior`` passes them; that batch's own informed rows are
  left out).

The sub-batches of one batch share modules, so they are not independent
cases; the batches of 4 are.  Reported per size and shift, beside the
synthetic study's rates (``analyses/results/outlier_study.json``, sizes 3 and 8):
which one (the outlier has the highest ``odd_one_prob``), detected
(``outlier_prob`` > 0.5), false alarms (a module above 0.3 without an
outlier), and how far: the outlier's S0 ``deviation`` in % against its true
S0 relative to the geometric mean of the other modules' true S0 (the tool's
``rel`` is relative to the population of the other modules).

Run:  python analyses/outlier_out_of_model.py --null-runs LAWCOV_WORK --work /tmp/tembayes-oom-outliers --batches 12
      python analyses/outlier_out_of_model.py ... --summarise
Writes analyses/results/outlier_out_of_model.{json,md}.
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from tembayes.bench.bench import UNIT_SPREAD
from tembayes.calibrate.moduledigest import read_digest
from tembayes.calibrate.population import PopulationConvergenceWarning, fit_population
from tembayes.data import load_batch, write_json

sys.path.insert(0, str(Path(__file__).parent))
from law_coverage import TYPES  # noqa: E402

RESULTS = Path(__file__).parent / "results"
S0_SPREAD = UNIT_SPREAD["S0_V_per_K"]
SHIFTS = (4, 6)
#: The run label law_coverage.py --fidelity high writes (its defaults: --model full --discrepancy robust).
NULL_RUN_LABEL = "high-paper-full-robust"
NULL_BATCH_LABEL = "high-paper"


def tembayes(*cmd):
    p = subprocess.run([sys.executable, "-m", "tembayes", *map(str, cmd)], capture_output=True, text=True, check=False)
    if p.returncode not in (0, 1):
        raise RuntimeError(f"{' '.join(map(str, cmd))}: {p.stderr.strip().splitlines()[-1:]}")


def outlier_batch(work, b, n=4, shifts=SHIFTS):
    """Simulate and calibrate batch ``b`` of ``n`` modules (types and ``shifts`` alternate); its folders."""
    t = list(TYPES)[b % 2]
    shift = shifts[(b // 2) % len(shifts)]
    bdir = work / "batches" / (f"{t}-s{shift}-b{b}" + ("" if n == 4 else f"-n{n}"))
    rdir = work / "runs" / bdir.name
    if not (bdir / "truth.json").exists():
        ds = work / f"{t}.toml"
        ds.write_text(TYPES[t])
        odd = ["--outlier", f"TEM{b % n + 1}", "--outlier-shift", shift * S0_SPREAD] if shift else []
        tembayes(
            "simulate", bdir, "--modules", n, "--fidelity", "high", "--datasheet", ds, "--seed", 1000 * n + 3000 + b,
            "--validations", 0, *odd, "--overwrite",
        )  # fmt: skip
    if not (rdir / "summary.json").exists():
        tembayes(
            "calibrate", bdir, "--out", rdir, "--seed", 0, "--quiet", "--no-figures", "--workers", 1, "--overwrite"
        )
    return bdir, rdir


def module_draws(bdir, rdir):
    """Converged modules' law draws (id -> (M, 5) SI) and the batch's datasheet."""
    batch = load_batch(bdir)
    law = {}
    for mid in batch.modules:
        f = rdir / "modules" / f"{mid}.nc"
        if f.exists():
            _, why, draws, _ = read_digest(f)
            if not why:
                law[mid] = draws
    return law, batch.datasheet


def fit(law, datasheet, ids, spread_prior, seed):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PopulationConvergenceWarning)
        return fit_population(
            {m: law[m] for m in ids},
            datasheet,
            rng=np.random.default_rng(seed),
            spread_prior=spread_prior,
            design_reach=False,  # the spread curve and the smallest flagged deviation are not studied here
        )


def true_offset(truth, mid, others):
    """The module's true S0 relative to the geometric mean of the ``others``' true S0."""
    s0 = {m: v["S0_V_per_K"] for m, v in truth["modules"].items()}
    return float(s0[mid] / np.exp(np.mean([np.log(s0[m]) for m in others])) - 1.0)


def subsets_of(ids, out_id):
    """The batch as a whole and its 3-module sub-batches (batches of 4), each holding the outlier if there is one."""
    if out_id is not None and out_id not in ids:  # the outlier did not converge: nothing to ask
        return []
    if len(ids) != 4:  # 8 modules: their 3-module sub-batches are many, and the batches of 4 have them
        return [tuple(ids)] if len(ids) >= 3 else []
    return [tuple(ids)] + [s for s in itertools.combinations(ids, 3) if out_id is None or out_id in s]


def rows_of(bdir, rdir, priors, shift, skip_prior_source=False):
    """One row per fitted (sub-)batch and prior."""
    truth = json.loads((bdir / "truth.json").read_text())
    law, ds = module_draws(bdir, rdir)
    out_id = next((m for m, v in truth["modules"].items() if v.get("outlier")), None)
    subsets = subsets_of(sorted(law), out_id)
    rows = []
    for name, prior in priors[ds.name].items():
        if skip_prior_source and name == "informed":
            continue
        for k, sub in enumerate(subsets):
            pop = fit(law, ds, sub, prior, seed=100 + k)
            head = {"batch": bdir.name, "type": ds.name, "prior": name, "size": len(sub), "whole": k == 0}
            rows.append({**head, **answer_row(pop, truth, sub, out_id, shift)})
    return rows


def answer_row(pop, truth, sub, out_id, shift):
    """What the population fit of sub-batch ``sub`` says, and the truth about its outlier ``out_id``."""
    dev = pop.deviation.get(out_id, {}).get("S0_V_per_K", {}) if out_id else {}
    return {
        "shift": shift,
        "outlier": out_id,
        "modules": list(sub),
        "outlier_prob": pop.outlier_prob,
        "odd_one_prob": pop.odd_one_prob,
        "p_any_outlier": pop.p_any_outlier,
        "converged": bool(pop.diagnostics.get("converged", False)),
        "dev_rel": dev.get("rel"),
        "dev_spreads": dev.get("spreads"),
        "true_offset": None if out_id is None else true_offset(truth, out_id, [m for m in sub if m != out_id]),
    }


def informed_priors(null_root, run_label):
    """Per type: the spreads its first null batch learned (``spread_prior`` format), and that batch's name."""
    priors, sources = {}, {}
    for t in TYPES:
        name = f"{t}-b0"
        law, ds = module_draws(null_root / "batches" / NULL_BATCH_LABEL / name, null_root / "runs" / run_label / name)
        pop = fit(law, ds, sorted(law), None, seed=99)
        priors[t] = {"default": None, "informed": pop.spread_prior()}
        sources[t] = name
    return priors, sources


def rates(rows):
    """Per prior, size, shift: cases, which one, detected, false alarm, median odd-one and outlier prob."""
    out = {}
    for r in rows:
        out.setdefault((r["prior"], r["size"], r["shift"], r["whole"]), []).append(r)
    table = []
    for (prior, size, shift, whole), rs in sorted(out.items()):
        e = {"prior": prior, "size": size, "shift": shift, "whole_batch": whole, "cases": len(rs)}
        if shift == 0:
            e["false_alarm"] = float(np.mean([max(r["outlier_prob"].values()) > 0.3 for r in rs]))
            e["max_outlier_prob_median"] = float(np.median([max(r["outlier_prob"].values()) for r in rs]))
        else:
            e["which_one"] = float(
                np.mean([max(r["odd_one_prob"], key=r["odd_one_prob"].get) == r["outlier"] for r in rs])
            )
            e["detected"] = float(np.mean([r["outlier_prob"][r["outlier"]] > 0.5 for r in rs]))
            e["median_outlier_prob"] = float(np.median([r["outlier_prob"][r["outlier"]] for r in rs]))
            e["median_odd_one_prob"] = float(np.median([r["odd_one_prob"][r["outlier"]] for r in rs]))
            err = [100 * (r["dev_rel"] - r["true_offset"]) for r in rs if r["dev_rel"] is not None]
            e["deviation_error_pct_median_abs"] = float(np.median(np.abs(err))) if err else None
        table.append(e)
    return table


def synthetic_rates():
    f = RESULTS / "outlier_study.json"
    if not f.exists():
        return None
    return json.loads(f.read_text()).get("rates")


def synthetic(res, e):
    """The synthetic study's which-one / detected / false-alarm rate at the row's prior, size 3 and shift."""
    syn = (res.get("synthetic_rates") or {}).get(e["prior"], {}).get(f"3x{e['shift']}")
    if e["size"] != 3 or not syn:
        return "–"
    keys = ("false_alarm_0.3",) if e["shift"] == 0 else ("which_one", "detected_0.5")
    return " / ".join(f"{syn[k]:.2f}" for k in keys)


def markdown(res):
    lines = [
        "# The outlier question on the out-of-model bench",
        "",
        f"Null batches: {res['n_null_batches']} (the law-coverage study's out-of-model runs); outlier batches: "
        f"{res['n_outlier_batches']}; the informed prior from {', '.join(res['prior_sources'].values())}.",
        "Sub-batches of 3 share modules with their batch of 4: not independent cases. The last column is the "
        "synthetic study's rate at 3 modules (which one / detected, or false alarm), "
        f"{res['synthetic_batches_per_cell']} batches each.",
        "",
        "| prior | size | shift (spreads) | whole batch | cases | which one | detected (> 0.5) | median outlier_prob "
        "| median odd_one_prob | false alarm (> 0.3) | median abs error of the S0 deviation [%] | synthetic |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for e in res["rates"]:

        def f(k, e=e):
            v = e.get(k)
            return "–" if v is None else f"{v:.3g}" if isinstance(v, float) else str(v)

        lines.append(
            f"| {e['prior']} | {e['size']} | {e['shift']} | {e['whole_batch']} | {e['cases']} | {f('which_one')} "
            f"| {f('detected')} | {f('median_outlier_prob')} | {f('median_odd_one_prob')} | {f('false_alarm')} "
            f"| {f('deviation_error_pct_median_abs')} | {synthetic(res, e)} |"
        )
    lines += ["", f"Population fits not converged: {res['not_converged']} of {res['n_fits']}.", ""]
    lines += [
        "Each outlier batch as a whole (default prior / informed): the outlier's true S0 offset from the "
        "geometric mean of the other modules' truths, and what the tool says.",
        "",
        "| batch | outlier | true offset [%] | deviation [%] | deviation [spreads] | odd_one_prob | outlier_prob |",
        "|---|---|---|---|---|---|---|",
    ]

    def pair(b, k, fmt, scale=1.0):
        return " / ".join("–" if b[p][k] is None else format(scale * b[p][k], fmt) for p in ("default", "informed"))

    for b in res["outlier_batches"]:
        lines.append(
            f"| {b['batch']} | {b['outlier']} | {100 * b['true_offset']:+.2f} | {pair(b, 'dev_rel', '+.2f', 100)} | "
            f"{pair(b, 'dev_spreads', '+.1f')} | {pair(b, 'odd_one_prob', '.2f')} | {pair(b, 'outlier_prob', '.2f')} |"
        )
    return "\n".join(lines) + "\n"


def outlier_batches(rows):
    """Per outlier batch, fitted whole: the truth and the tool's answer about the outlier, per prior."""
    out = {}
    for r in rows:
        if not (r["whole"] and r["shift"]):
            continue
        o = r["outlier"]
        e = out.setdefault(r["batch"], {"batch": r["batch"], "outlier": o, "true_offset": r["true_offset"]})
        e[r["prior"]] = {
            "dev_rel": r["dev_rel"],
            "dev_spreads": r["dev_spreads"],
            "odd_one_prob": r["odd_one_prob"][o],
            "outlier_prob": r["outlier_prob"][o],
        }
    return [e for e in out.values() if "default" in e and "informed" in e]


def cached_rows(work, bdir, rdir, priors, shift, skip_prior_source=False):
    """:func:`rows_of`, cached in ``work/rows`` (the fits are the slow part)."""
    f = work / "rows" / f"{rdir.parent.name}-{rdir.name}.json"
    if not f.exists():
        f.parent.mkdir(exist_ok=True)
        write_json(f, rows_of(bdir, rdir, priors, shift, skip_prior_source))
        print(f"fitted {rdir.name}", flush=True)
    return json.loads(f.read_text())


def fitted_rows(a):
    """Rows of every null batch and every calibrated outlier batch; the informed priors' sources."""
    priors, sources = informed_priors(a.null_runs, a.null_label)
    rows = []
    null_dirs = sorted((a.null_runs / "runs" / a.null_label).glob("*-b*"))
    for rdir in null_dirs:
        bdir = a.null_runs / "batches" / NULL_BATCH_LABEL / rdir.name
        rows += cached_rows(a.work, bdir, rdir, priors, 0, skip_prior_source=rdir.name in sources.values())
    for rdir in sorted((a.work / "runs").glob("*-b*")):
        if (rdir / "summary.json").exists():
            shift = int(re.search(r"-s(\d+)-b", rdir.name).group(1))
            rows += cached_rows(a.work, a.work / "batches" / rdir.name, rdir, priors, shift)
    return rows, sources, len(null_dirs)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--null-runs", type=Path, required=True, help="the --work folder of law_coverage.py --fidelity high"
    )
    ap.add_argument(
        "--null-label",
        default=NULL_RUN_LABEL,
        help=f"the null runs' label under --null-runs/runs (default {NULL_RUN_LABEL})",
    )
    ap.add_argument("--work", type=Path, default=Path("/tmp/tembayes-oom-outliers"))
    ap.add_argument("--batches", type=int, default=12, help="outlier batches (types and shifts alternate)")
    ap.add_argument("--modules", type=int, default=4, help="modules per simulated batch (default 4)")
    ap.add_argument("--shifts", default="4,6", help="S0 shifts in spreads, cycled (0: no outlier; default 4,6)")
    ap.add_argument("--shard", default="0/1", help="K/N: simulate and calibrate every N-th outlier batch from K")
    ap.add_argument("--fit", action="store_true", help="only fit the populations of what is there (cached)")
    ap.add_argument("--summarise", action="store_true", help="fit what is not cached, record the rates")
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    if not (a.fit or a.summarise):
        k, n = map(int, a.shard.split("/"))
        for b in range(k, a.batches, n):
            t0 = time.time()
            outlier_batch(a.work, b, a.modules, tuple(int(x) for x in a.shifts.split(",")))
            print(f"outlier batch {b}: {time.time() - t0:.0f} s", flush=True)
        return
    rows, sources, n_null = fitted_rows(a)
    if a.fit:
        return
    res = {
        "n_null_batches": n_null,
        "n_outlier_batches": len({r["batch"] for r in rows if r["shift"]}),
        "prior_sources": sources,
        "n_fits": len(rows),
        "not_converged": sum(not r["converged"] for r in rows),
        "rates": rates(rows),
        "outlier_batches": outlier_batches(rows),
        "synthetic_rates": synthetic_rates(),
        "synthetic_batches_per_cell": (synthetic_rates() or {}).get("default", {}).get("3x0", {}).get("batches"),
    }
    RESULTS.mkdir(exist_ok=True)
    write_json(RESULTS / "outlier_out_of_model.json", res)
    with open(RESULTS / "outlier_out_of_model_rows.jsonl", "w") as fh:
        fh.writelines(json.dumps(r) + "\n" for r in rows)
    (RESULTS / "outlier_out_of_model.md").write_text(markdown(res))
    print(markdown(res))


if __name__ == "__main__":
    main()
