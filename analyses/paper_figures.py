"""The paper's Figures 5-9 for a batch, from the deterministic identification.

Runs the step method (``tembayes.identify.pipeline.identify_batch``) on a
batch folder and writes, into the output folder:

- ``identification_run.png`` (Fig. 5), ``law_R.png`` (Fig. 6),
  ``law_S.png`` (Fig. 7);
- per module and validation run ``validation_<module>_<run>_constant.png``
  (Fig. 8, R and S frozen at 35 degC), ``..._linear.png`` (Fig. 9, the linear
  laws) and ``error_vs_tavg_<module>_<run>.png`` (cold-side error against the
  mean temperature, both models);
- ``summary.md``: per module the law parameters of the corrected method and
  of the paper's literal recipe with their standard errors, the batch
  average, and the validation RMSE per sensor of both models.

truth.json is never read unless ``--truth`` is given (a bench batch): then
the parameter tables get "truth" and "error %" columns.

Run (from the repository root):

    python analyses/paper_figures.py [--batch data/example] [--out analyses/results/paper_figures] [--truth]

Runtime: about 3 minutes for the 3-module example batch (the rig fits
dominate), a few seconds more for the figures.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import tembayes  # noqa: E402
from tembayes.data import atomic_write_text, load_batch  # noqa: E402
from tembayes.identify.pipeline import batch_average, identify_batch  # noqa: E402
from tembayes.plots import save_identify_figures  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_BATCH = ROOT / "data" / "example"
DEFAULT_OUT = ROOT / "analyses" / "results" / "paper_figures"

#: Display of each parameter: (label, unit, factor from SI, decimals).
DISPLAY = {
    "R0_ohm": ("R0", "ohm", 1.0, 4),
    "R1_ohm_per_K": ("R1", "mohm/K", 1e3, 3),
    "S0_V_per_K": ("S0", "mV/K", 1e3, 3),
    "S1_V_per_K2": ("S1", "uV/K^2", 1e6, 2),
    "K_W_per_K": ("K", "W/K", 1.0, 5),
}


def fmt(value, sd, key):
    _, _, f, d = DISPLAY[key]
    if value is None:
        return "—"
    return f"{value * f:.{d}f} ± {sd * f:.{d}f}" if sd is not None else f"{value * f:.{d}f}"


def pct(value, truth):
    return "—" if value is None or truth is None else f"{100.0 * (value - truth) / truth:+.1f}"


def parameter_table(res, truth=None):
    """Markdown table of one module's law parameters: corrected fit, paper recipe (and truth)."""
    head = "| parameter | unit | fit ± sd | paper recipe ± sd |"
    rule = "|---|---|---|---|"
    if truth is not None:
        head += " truth | error % fit | error % paper |"
        rule += "---|---|---|"
    lines = [head, rule]
    fit = res.fit | {"K_W_per_K": res.rig_fit.values["K_W_per_K"]}
    sd = res.fit_sd | {"K_W_per_K": res.rig_fit.sd["K_W_per_K"]}
    for key, (label, unit, f, d) in DISPLAY.items():
        paper = res.fit_paper.get(key)
        row = f"| {label} | {unit} | {fmt(fit[key], sd[key], key)} | {fmt(paper, res.fit_paper_sd.get(key), key)} |"
        if truth is not None:
            t = truth.get(key)
            row += f" {'—' if t is None else f'{t * f:.{d}f}'} | {pct(fit[key], t)} | {pct(paper, t)} |"
        lines.append(row)
    return lines


def shown(path):
    """A path relative to the repository root when it is inside it (no machine-specific prefixes)."""
    path = Path(path).resolve()
    return path.relative_to(ROOT).as_posix() if path.is_relative_to(ROOT) else str(path)


def summary_markdown(batch, results, figures, out, runtime, truth=None):
    lines = [
        f"# Paper figures: {batch.path.name}",
        "",
        f"Made by `analyses/paper_figures.py` on {datetime.date.today().isoformat()} "
        f"(tembayes {tembayes.__version__}, batch `{shown(batch.path)}`, {runtime:.0f} s).",
        "",
        "Laws: X(T) = X0 + X1 (T_avg − 25 °C).  *fit*: R from the voltage jump extrapolated to the step "
        "instant, S with the junction temperatures reconstructed through the rig network (weighted fits). "
        "*paper recipe*: R from the first sample after the step, S with sensor dT = T2 − T3 and sensor "
        "T_mean (unweighted fits).  K comes from the rig fit (no paper-recipe value).",
        "",
        "## Law parameters per module",
    ]
    if truth is not None:
        lines += ["", "Truth from `truth.json` (bench batch); error % = (estimate − truth) / truth."]
    for mid, res in results.items():
        t = None if truth is None else truth["modules"].get(mid)
        lines += ["", f"### {mid}", ""] + parameter_table(res, t)
    avg = batch_average(results)
    lines += [
        "",
        "## Batch average (the dashed line of law_R.png / law_S.png)",
        "",
        "| parameter | unit | mean | spread between modules (sd) |",
        "|---|---|---|---|",
    ]
    for key, (label, unit, f, d) in DISPLAY.items():
        lines.append(f"| {label} | {unit} | {avg[key] * f:.{d}f} | {avg[key + '_spread'] * f:.{d}f} |")
    lines += [
        "",
        "## Validation RMSE per sensor",
        "",
        "*constant*: R, S frozen at their 35 °C values with their own rig fit (paper Fig. 8); "
        "*linear*: the laws (Fig. 9).  Sensors in K, voltage in mV.",
        "",
        "| module | run | model | T1 [K] | T2 [K] | T3 [K] | T4 [K] | V [mV] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for mid, res in results.items():
        for run, models in res.validation.items():
            for model in ("constant", "linear"):
                e = models[model]
                cells = [f"{e[ch]['rmse']:.3f}" for ch in ("T1_C", "T2_C", "T3_C", "T4_C")]
                lines.append(
                    f"| {mid} | {run} | {model} | " + " | ".join(cells) + f" | {1e3 * e['voltage_V']['rmse']:.2f} |"
                )
    lines += ["", "## Figures", ""]
    lines += [f"- [{p.name}]({p.relative_to(out).as_posix()})" for p in figures]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=Path, default=DEFAULT_BATCH, help="batch folder (default: data/example)")
    ap.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, help="output folder (default: analyses/results/paper_figures)"
    )
    ap.add_argument(
        "--truth",
        nargs="?",
        const=True,
        default=None,
        metavar="TRUTH_JSON",
        help="compare with a bench truth.json (default: BATCH/truth.json)",
    )
    args = ap.parse_args(argv)

    t0 = time.monotonic()

    def progress(msg):
        print(f"[{time.monotonic() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    truth = None
    if args.truth is not None:
        path = args.batch / "truth.json" if args.truth is True else Path(args.truth)
        truth = json.loads(path.read_text())

    batch = load_batch(args.batch)
    results = identify_batch(batch, progress=progress)
    progress("figures")
    figures = save_identify_figures(results, batch, args.out)
    text = summary_markdown(batch, results, figures, args.out, time.monotonic() - t0, truth)
    summary = atomic_write_text(args.out / "summary.md", text)
    progress(f"wrote {len(figures)} figures and {summary}")
    print(text)


if __name__ == "__main__":
    main()
