"""A :class:`~tembayes.report.content.BatchReport` as one self-contained HTML file.

Everything is inline: the style sheet, and the figures as ``data:image/png``
URIs; no script, no link leaves the file, so it opens offline, mails as one
attachment and archives as one file.  Sections (each an ``<section id>``):
``acceptance``, ``overview``, ``quality``, ``laws``, ``population``,
``hysteresis``, ``convergence``, ``corner``, ``validation``, ``gap``,
``provenance``.
"""

from __future__ import annotations

import base64
import html
import math
from typing import TYPE_CHECKING

from tembayes.calibrate import sampler as smp
from tembayes.calibrate.diagnostics import PSIS_K_MAX
from tembayes.constants import MODULE_PARAMETERS
from tembayes.gap.conflicts import is_immaterial

if TYPE_CHECKING:
    from pathlib import Path

    from tembayes.report.content import BatchReport

_UNITS = {  # display unit and factor (display = SI x factor)
    "R0_ohm": ("R0", "Ω", 1.0),
    "R1_ohm_per_K": ("R1", "mΩ/K", 1e3),
    "S0_V_per_K": ("S0", "mV/K", 1e3),
    "S1_V_per_K2": ("S1", "µV/K²", 1e6),
    "K_W_per_K": ("K", "W/K", 1.0),
}


def _channel_unit(column):
    """Display name, unit and factor of a predicted channel: a sensor column in mK, the voltage in mV."""
    return ("V", "mV", 1e3) if column == "voltage_V" else (column.removesuffix("_C"), "mK", 1e3)


_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1180px;padding:1em 2em;
color:#1b1b1b;line-height:1.4}
h1{font-size:1.6em;margin-bottom:.2em}h2{border-bottom:2px solid #ccc;padding-bottom:.2em;margin-top:1.8em}
table{border-collapse:collapse;margin:.6em 0;font-size:.88em}th,td{border:1px solid #ccc;padding:.25em .55em;
text-align:right;vertical-align:top}th{background:#f1f1f1}td.l,th.l{text-align:left}
.pass{background:#d9f2d9;color:#0a5c0a;font-weight:600}.fail{background:#f8d4d4;color:#8a0b0b;font-weight:600}
.warn{background:#fff1c2}figure{margin:1em 0}figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:.85em;color:#555}.muted{color:#666;font-size:.9em}nav a{margin-right:.8em}
code{background:#f4f4f4;padding:0 .25em}
"""


def _e(x):
    return html.escape(str(x))


def _num(x, fmt="{:.4g}"):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, (int, float)):
        return fmt.format(x)
    return _e(x)


def _table(header, rows, left=1):
    """HTML table; the first ``left`` columns left-aligned; cells are (text, css class) or text."""
    out = [
        "<table><tr>"
        + "".join(f'<th class="{"l" if i < left else ""}">{_e(h)}</th>' for i, h in enumerate(header))
        + "</tr>"
    ]
    for r in rows:
        cells = []
        for i, c in enumerate(r):
            text, cls = c if isinstance(c, tuple) else (c, "")
            cls = (cls + (" l" if i < left else "")).strip()
            cells.append(f'<td class="{cls}">{text}</td>')
        out.append("<tr>" + "".join(cells) + "</tr>")
    return "".join(out) + "</table>"


def _figure(rep, key):
    if key not in rep.figures:
        return ""
    caption, png = rep.figures[key]
    b64 = base64.b64encode(png).decode("ascii")
    return (
        f'<figure id="fig-{_e(key)}"><img alt="{_e(caption)}" src="data:image/png;base64,{b64}">'
        f"<figcaption>{_e(caption)}</figcaption></figure>"
    )


def _param(stats, name):
    label, unit, f = _UNITS[name]
    return (f"{stats['mean'] * f:.5g} ± {stats['sd'] * f:.2g}", f"{stats['q05'] * f:.5g} … {stats['q95'] * f:.5g}")


def _acceptance(rep):
    rows = []
    for m in rep.modules:
        acc = m["acceptance"]
        cells = [_e(m["id"]), ("PASS", "pass") if acc["passed"] else ("FAIL", "fail")]
        for c in acc["checks"]:
            cells.append((f"{'✓' if c['passed'] else '✗'} {_e(c['detail'])}", "" if c["passed"] else "fail"))
        rows.append(cells)
    header = ["module", "result"] + [c["check"] for c in rep.modules[0]["acceptance"]["checks"]] if rep.modules else []
    n_pass = sum(m["acceptance"]["passed"] for m in rep.modules)
    return (
        f"<p><b>{n_pass} of {len(rep.modules)} modules pass.</b> A parameter check passes when the posterior "
        f"probability that the value lies inside its tolerance is at least {rep.confidence:g}. Tolerances: "
        + ", ".join(f"<code>{_e(t)}</code>" for t in rep.tolerances)
        + " (percentages are of the datasheet-derived value at the datasheet's hot-side temperature; "
        "set them with <code>--tolerance</code>).</p>" + _table(header, rows, left=len(header))
    )


_MODELS = {
    "paper": "paper (Evers et al.: S(T̄) at both junctions, one-node plates)",
    "full": "full (Peltier heat at each junction's own S, Thomson heat, two-layer plates, sensor lag, K(T))",
}


def _overview(rep):
    o = rep.overview
    ds = o["datasheet"]
    dd = o["datasheet_derived"]
    rows = [
        ["module type", _e(o["module_type"])],
        ["datasheet", _e(", ".join(f"{k} = {v}" for k, v in ds.items() if k != "name"))],
        [
            "datasheet-derived at " + f"{dd['at_C']:g} °C",
            f"R = {dd['R_ohm']:.4g} Ω, S = {1e3 * dd['S_V_per_K']:.4g} mV/K, K = {dd['K_W_per_K']:.4g} W/K",
        ],
        ["modules", f"{o['n_modules']}: " + _e(", ".join(o["modules"]))],
        ["batch folder", f"<code>{_e(o['batch'])}</code>"],
        ["run folder", f"<code>{_e(o['run'])}</code>"],
        ["calibration rig model", _e(o.get("rig") or "–")],
        ["rig sensors", "<br>".join(_e(d) for d in o.get("sensors", {}).values()) or "–"],
        ["rig boundaries", _e(", ".join(o.get("boundaries", [])) or "–")],
        [
            "calibration model",
            _e(_MODELS.get(o.get("model", "paper"), o.get("model")))
            + (f"; with {_e(', '.join(o['effects']))}" if o.get("effects") else "")
            + f"; discrepancy: {_e(o.get('discrepancy', 'none'))}",
        ],
        [
            "prior on the laws",
            _e("the datasheet's" if o.get("law_prior", "datasheet") == "datasheet" else o["law_prior"]),
        ],
        ["law reference temperature", f"{o['tref_C']:g} °C"],
        ["data files dated", _e(o.get("data_files_dated") or "–")],
        ["run files dated", _e(o.get("run_files_dated") or "–")],
    ]
    return _table(["", ""], rows, left=2)


def _quality(rep):
    hot, cold = rep.overview["face_sensors"]
    h, c = hot.removesuffix("_C"), cold.removesuffix("_C")
    rows = []
    for q in rep.quality:
        rows.append(
            [
                _e(q["module"]),
                _e(q["experiment"]),
                str(q["n_samples"]),
                f"{q['duration_s'] / 3600:.2f}",
                f"{q['dt_median_s']:.3g}",
                f"{q['current_min_A']:.2f} … {q['current_max_A']:.2f}",
                f"{q[hot + '_min']:.1f} … {q[hot + '_max']:.1f}",
                f"{q[cold + '_min']:.1f} … {q[cold + '_max']:.1f}",
                f"{1e3 * q['voltage_V_noise']:.2f}",
                f"{1e3 * q[cold + '_noise']:.2f}",
                f"{1e3 * q['current_A_noise']:.2f}",
            ]
        )
    return "<p class='muted'>Noise: robust white-noise level from second differences.</p>" + _table(
        [
            "module",
            "experiment",
            "samples",
            "hours",
            "Δt median [s]",
            "current [A]",
            f"{h} [°C]",
            f"{c} [°C]",
            "V noise [mV]",
            f"{c} noise [mK]",
            "I noise [mA]",
        ],
        rows,
        left=2,
    )


def _laws(rep):
    header = ["module"] + [f"{_UNITS[p][0]} [{_UNITS[p][1]}]" for p in MODULE_PARAMETERS]
    rows = []
    for m in rep.modules:
        rows.append(
            [_e(m["id"])]
            + ["{}<br><span class='muted'>{}</span>".format(*_param(m["params"][p], p)) for p in MODULE_PARAMETERS]
        )
    if rep.population:
        rows.append(
            [("population (a new module)", "")]
            + [
                "{}<br><span class='muted'>{}</span>".format(*_param(rep.population["params"][p], p))
                for p in MODULE_PARAMETERS
            ]
        )
    figs = "".join(_figure(rep, k) for k in rep.figures if k.startswith("laws_") and k != "laws_all")
    return (
        "<p>Posterior mean ± sd, and the 90 % interval below, of the laws "
        f"R(T) = R0 + R1 (T − {rep.overview['tref_C']:g} °C), S(T) = S0 + S1 (T − {rep.overview['tref_C']:g} °C) "
        "and the module conductance K. The figures put each module's 90 % band over the per-step estimates "
        "of its identification run (R from each voltage jump, S from each hold's steady state, with the rig at "
        "its posterior mean; error bars ±2 sd).</p>" + _table(header, rows) + figs + _figure(rep, "laws_all")
    )


def _deviation_cell(m, parameter):
    d = (m.get("deviation") or {}).get(parameter)
    if not d:
        return "–"
    return f"{100 * d['rel']:+.1f} % ({d['spreads']:+.1f} spreads, p {d['p_loo']:.2g})"


def _population(rep):
    rows = []
    for m in rep.modules:
        p = m["outlier_prob"]
        cls = "" if p is None else ("fail" if p > 0.5 else ("warn" if p > 0.3 else ""))
        rows.append([_e(m["id"]), (_num(p, "{:.3f}"), cls)])
    body = _table(["module", "outlier probability"], rows)
    if rep.population is None:
        return "<p>This run has no population fit.</p>" + body
    d = rep.population["diagnostics"]
    mcse = d.get("outlier_prob_mcse", {})
    odd = rep.population.get("odd_one") or {}
    par = odd.get("parameter")
    by_id = {m["id"]: m for m in rep.modules}
    header = ["module", "outlier probability", "Monte Carlo se", "odd one, if one"]
    if par:
        header.append(f"{par.split('_')[0]} from the other modules")
    body = _table(
        header,
        [
            r
            + [_num(mcse.get(r[0]), "{:.3f}"), _num(by_id[r[0]].get("odd_one_prob"), "{:.3f}")]
            + ([_e(_deviation_cell(by_id[r[0]], par))] if par else [])
            for r in rows
        ],
    )
    answer = "".join(f"<p><b>{_e(line)}</b></p>" for line in rep.population.get("answer") or [])
    return (
        answer + "<p>Which module is odd and whether it is an outlier are different questions. The odd-one "
        "probability assumes the batch holds exactly one outlier and asks which: it is settled by which "
        "unit breaks the symmetry, even among three modules. The outlier probability asks whether a module "
        "lies outside the batch's common population at all, which needs the unit-to-unit spread: a small "
        "batch learns little of it from its own units, so the figure shows what the answer would be if the "
        "type's spread were known. A unit's deviation is measured from the population of the other modules "
        "(leave-one-out), in percent, in their spreads, and as the probability that one of their units lies "
        "that far out.</p>"
        "<p>The probability that a module does not belong to the batch's common population (a robust "
        "mixture fitted to the modules' posteriors). Above 0.5 red, above 0.3 amber. Population fit: "
        f"{_e(d.get('method', ''))}, {'converged' if d.get('converged') else 'NOT converged'} "
        f"(R̂ {_num(d.get('rhat_max'), '{:.3f}')}, bulk ESS {_num(d.get('ess_bulk_min'), '{:.0f}')}).</p>"
        + body
        + _figure(rep, "outliers")
        + _figure(rep, "corner_population")
    )


def _hysteresis(rep):
    rows = []
    for m in rep.modules:
        h = m["hysteresis"]
        cells = [_e(m["id"])]
        for key, unit, f in (("R_ohm", "mΩ", 1e3), ("S_V_per_K", "µV/K", 1e6)):
            x = h.get(key)
            if not x:
                cells += ["–", "–"]
                continue
            z = x["z"]
            cells += [
                f"{x['estimate'] * f:+.3g} ± {x['sd'] * f:.2g} {unit}",
                (f"{z:+.1f}", "warn" if abs(z) > 2 else ""),
            ]
        rows.append(cells)
    return (
        "<p>Up-step minus down-step estimates of R and S (the calibration's fit with R and S shifted by ±h/2 "
        "after up- and down-steps); |z| &gt; 2 amber.</p>"
        + _table(["module", "ΔR (up − down)", "z", "ΔS (up − down)", "z"], rows)
        + _figure(rep, "hysteresis")
    )


def _convergence(rep):
    rows = []
    for m in rep.modules:
        d = m["diagnostics"]
        ok = d.get("converged")
        rows.append(
            [
                _e(m["id"]),
                ("yes", "pass") if ok else ("NO", "fail"),
                _num(d.get("rhat_max"), "{:.4f}"),
                _num(d.get("ess_bulk_min"), "{:.0f}"),
                _num(d.get("tau_max_steps"), "{:.0f}"),
                _num(d.get("chain_over_tau"), "{:.0f}"),
                _num(d.get("steps"), "{:d}"),
                _num(d.get("psis_k"), "{:.2f}"),
                _num(d.get("seconds"), "{:.0f}"),
            ]
        )
    if rep.population:
        d = rep.population["diagnostics"]
        rows.append(
            [
                ("population", ""),
                ("yes", "pass") if d.get("converged") else ("NO", "fail"),
                _num(d.get("rhat_max"), "{:.4f}"),
                _num(d.get("ess_bulk_min"), "{:.0f}"),
                _num(d.get("tau_max"), "{:.0f}"),
                _num((d.get("n_steps") or 0) / d["tau_max"] if d.get("tau_max") else None, "{:.0f}"),
                _num(d.get("n_steps"), "{:d}"),
                "–",
                _num(d.get("elapsed_s"), "{:.0f}"),
            ]
        )
    return (
        f"<p>Targets: R̂ ≤ {smp.RHAT_MAX}, bulk ESS ≥ {smp.ESS_MIN:.0f} for each law parameter, chains ≥ "
        f"{smp.MIN_TAU_MULTIPLE:.0f} integrated autocorrelation times τ; the expansion the sampler used is "
        f"checked against the exact model (PSIS k̂ &lt; {PSIS_K_MAX}).</p>"
        + _table(
            ["", "converged", "R̂ max", "bulk ESS min", "τ max [steps]", "chain / τ", "steps", "PSIS k̂", "seconds"], rows
        )
    )


def _adequacy(rep):
    rows = []
    for m in rep.modules:
        a = m["diagnostics"].get("adequacy") or {}
        if "verdict" not in a:
            continue
        fits = a["verdict"] == "fits"
        rows.append(
            [_e(m["id"]), ("fits", "pass") if fits else ("does not fit", "fail")]
            + [_num(c["value"], "{:.2f}") + f" ({_e(c['where'])})" for c in a["checks"].values()]
            + [_e("; ".join(a["reasons"]) or "–")]
        )
    if not rows:
        return "<p class='muted'>This run predates the adequacy verdict.</p>"
    limits = next(
        m["diagnostics"]["adequacy"]["checks"]
        for m in rep.modules
        if "verdict" in (m["diagnostics"].get("adequacy") or {})
    )
    head = [f"{name.replace('_', ' ')} (≤ {c['limit']:g})" for name, c in limits.items()]
    return (
        "<p>Whether the model explains the identification run it was calibrated on, from the run's own "
        "step windows: do the windows agree about the laws (score variance against the posterior's, 1 "
        "when the model is right), the noise the model leaves against the sensors' own (1), the windows' "
        "level errors in noise sds, and the residuals' lag-1 autocorrelation (0 for white noise). Each "
        "shows its worst value and where. A module that does not fit has laws that rest on a model that "
        "misses something: <code>tembayes gap</code> finds what.</p>"
        + _table(["", "verdict"] + head + ["what it means"], rows)
    )


def _validation(rep):
    if not rep.validation:
        return "<p>No validation runs in this report.</p>"
    channels = list(dict.fromkeys(c for v in rep.validation for c in v["channels"]))
    units = {c: _channel_unit(c) for c in channels}
    header = (
        ["module", "run"]
        + [f"{units[c][0]} RMSE [{units[c][1]}]" for c in channels]
        + [f"{units[c][0]} cover 50/90/95 %" for c in channels]
        + ["source"]
    )
    rows = []
    for v in rep.validation:
        ch = v["channels"]
        cells = [_e(v["module"]), _e(v["experiment"])]
        for c in channels:
            cells.append(_num(ch.get(c, {}).get("rmse", float("nan")) * units[c][2], "{:.3g}"))
        for c in channels:
            m = ch.get(c, {})
            cov90 = m.get("coverage90", float("nan"))
            cls = "warn" if math.isfinite(cov90) and not 0.8 <= cov90 <= 0.97 else ""
            cells.append(
                (
                    " / ".join(
                        _num(100 * m.get(k, float("nan")), "{:.0f}") for k in ("coverage50", "coverage90", "coverage95")
                    ),
                    cls,
                )
            )
        cells.append(("<span class='muted'>" + _e(v["source"]) + "</span>", ""))
        rows.append(cells)
    figs = "".join(_figure(rep, v["figure"]) for v in rep.validation if v.get("figure"))
    return (
        "<p>Posterior-predictive check on the validation runs: RMSE of the measurement about the predictive "
        "mean, and the fraction of samples inside the central 50/90/95 % bands (measurement noise included); "
        "a 90 % coverage outside 80–97 % is amber.</p>" + _table(header, rows, left=2) + figs
    )


def _gap(rep):
    if not rep.gap:
        return (
            "<p>No gap diagnosis in this report (run <code>tembayes gap RUN BATCH --out DIR</code> and give "
            "<code>--gap DIR</code>).</p>"
        )
    out = []
    for g in rep.gap:
        doc = g["doc"]
        best = doc.get("best")
        group = doc.get("best_group") or []
        out.append(
            f"<h3>{_e(g['folder'])}</h3><p>Verdict: <b>{_e(doc['verdict'])}</b>"
            + (f"; best: <b>{_e(best)}</b>" if best else "")
            + (f" (the data cannot tell apart: {_e(', '.join(group))})" if len(group) > 1 else "")
            + (f". Metric: {_e(doc['metric'])}" if isinstance(doc.get("metric"), str) else "")
            + ".</p>"
        )
        rows = []
        for r in doc["ranking"][:10]:
            ev = r.get("evidence")
            se = r.get("evidence_se")
            rows.append(
                [
                    _e(r["effect"]),
                    _e(r.get("evidence_kind", "")),
                    "–" if ev is None else (f"{ev:+.4g}" + (f" ± {se:.3g}" if se is not None else "")),
                    _num(None if r.get("gap_before") is None else 1e3 * r["gap_before"], "{:.2f}"),
                    _num(None if r.get("gap_after") is None else 1e3 * r["gap_after"], "{:.2f}"),
                    _num(None if r.get("shrink") is None else 100 * r["shrink"], "{:.0f}"),
                    _e(r.get("dropped") or r.get("failed") or ""),
                ]
            )
        out.append(
            _table(
                [
                    "effect",
                    "evidence kind",
                    "evidence [nats]",
                    "gap before [mK]",
                    "gap after [mK]",
                    "shrink [%]",
                    "note",
                ],
                rows,
                left=2,
            )
        )
        where = doc.get("where") or []
        if where:
            out.append(
                "<p>Where the model and the measurements part most:</p>"
                + _table(
                    ["channel", "regime", "score"],
                    [[_e(w["channel"]), _e(w["regime"]), _num(w.get("score"), "{:.2f}")] for w in where[:8]],
                    left=2,
                )
            )
        conf = [(mid, c) for mid, cs in (doc.get("conflicts") or {}).items() for c in cs]
        if conf:
            out.append(
                "<p>Prior–posterior conflicts: rig parameters calibrated outside the rig's documented "
                "plausible range (an effect hiding in the base model's parameters). A conflict is "
                "<em>needed</em> when the base model refitted with it held at the range's edge leaves a "
                "significant and material held-out step window or moves a law by more than 1.645 posterior "
                "sds; one that is not counts as no gap.</p>"
                + _table(
                    [
                        "module",
                        "parameter",
                        "posterior median",
                        "90 % interval",
                        "documented range",
                        "outside by [sd]",
                        "needed by the data",
                    ],
                    [
                        [
                            _e(mid),
                            _e(c["parameter"]),
                            f"{c['median']:.4g} {_e(c.get('unit', ''))}",
                            f"{c['q_low']:.4g} … {c['q_high']:.4g}",
                            f"{c['low']:.4g} … {c['high']:.4g}",
                            (_num(c.get("outside_sd"), "{:.1f}"), _conflict_class(c)),
                            _needed(c),
                        ]
                        for mid, c in conf
                    ],
                    left=2,
                )
            )
        elif isinstance(doc.get("conflicts"), dict):
            out.append("<p>No prior–posterior conflicts: every rig parameter inside its documented range.</p>")
        out.append(_recalibrated(doc.get("recalibrated")))
        out.append("".join(_figure(rep, k) for k in g["figures"]))
    return "".join(out)


def _conflict_class(c):
    """A conflict row's badge: ``fail`` where it is a gap, ``warn`` where it does not matter."""
    if not c.get("conflict"):
        return ""
    return "warn" if is_immaterial(c) else "fail"


def _needed(c):
    """A conflict row's range-check column: whether it matters, and the new windows and law shifts its checks left."""
    if "material" not in c:
        return "–"

    def cells(n):
        return "refit failed" if n is None else f"{n} new window cell{'s' if n != 1 else ''}"

    def shift(x):
        return "" if x is None else f", laws moved {x:.1f} sd"

    alone, together = c.get("held_cells"), c.get("held_cells_together")
    said = f"{cells(alone)}{shift(c.get('held_law_shift'))} at the edge"
    if together != alone or c.get("held_law_shift_together") != c.get("held_law_shift"):
        said += f"; {cells(together)}{shift(c.get('held_law_shift_together'))} with every conflict there"
    return ("yes" if c["material"] else "no") + f" ({said})"


def _recalibrated(rec):
    """The laws before and after the best explanation was added to the model, side by side."""
    if not rec:
        return ""
    rows = []
    for mid, after in rec["laws_after"].items():
        before = rec["laws_before"][mid]
        for p in MODULE_PARAMETERS:
            short, unit, f = _UNITS[p]
            b, a = before[p], after[p]
            shift = (a["mean"] - b["mean"]) / b["sd"] if b["sd"] > 0 else float("nan")
            rows.append(
                [
                    _e(mid),
                    f"{short} [{unit}]",
                    f"{f * b['mean']:.5g} ± {f * b['sd']:.2g}",
                    f"{f * a['mean']:.5g} ± {f * a['sd']:.2g}",
                    f"{shift:+.1f}",
                ]
            )
    note = ""
    if rec.get("modules_not_recalibrated"):
        note = (
            f"<p class='muted'>Not recalibrated (laws as before): {_e(', '.join(rec['modules_not_recalibrated']))}.</p>"
        )
    return (
        f"<p>The laws with {_e(', '.join(rec['effects']))} added to the model (the recalibrated run "
        f"<code>{_e(rec['run'])}</code>, which predict, report and export take), against the laws "
        "before:</p>" + _table(["module", "parameter", "before", "after", "moved [sd before]"], rows, left=2) + note
    )


def _provenance(rep):
    p = rep.provenance
    cal, r = p["calibration"], p["report"]
    rows = [
        ["calibration command", f"<code>{_e(cal.get('command') or '–')}</code>"],
        ["calibration seed", _e(cal.get("seed"))],
        ["calibration software", _e(", ".join(f"{k} {v}" for k, v in (cal.get("versions") or {}).items()))],
        ["calibration time", _num(cal.get("seconds"), "{:.0f}") + " s"],
        ["report command", f"<code>{_e(r.get('command') or '–')}</code>"],
        ["report seed (validation draws)", _e(r.get("seed"))],
        [
            "report software",
            _e(
                f"tembayes {r['tembayes']}, python {r['python']}, "
                + ", ".join(f"{k} {v}" for k, v in r["versions"].items())
            ),
        ],
        ["generated", _e(r["generated"]) + f" in {r['seconds']:.0f} s"],
    ]
    return _table(["", ""], rows, left=2)


SECTIONS = (
    ("acceptance", "Acceptance", _acceptance),
    ("overview", "Batch overview", _overview),
    ("quality", "Data quality", _quality),
    ("laws", "Laws R(T), S(T) and K", _laws),
    ("population", "Modules against the population", _population),
    ("hysteresis", "Hysteresis", _hysteresis),
    ("convergence", "Convergence", _convergence),
    ("adequacy", "Model adequacy", _adequacy),
    (
        "corner",
        "Corner plots",
        lambda rep: "".join(
            _figure(rep, k) for k in rep.figures if k.startswith("corner_") and k != "corner_population"
        ),
    ),
    ("validation", "Validation", _validation),
    ("gap", "Sim-to-real gap", _gap),
    ("provenance", "Provenance", _provenance),
)


def render_html(rep: BatchReport) -> str:
    """The report as one HTML document (str)."""
    o = rep.overview
    title = f"tembayes batch report: {o['module_type']}, {o['n_modules']} modules"
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{_e(title)}</h1><p class='muted'>Run <code>{_e(o['run'])}</code> · generated "
        f"{_e(rep.provenance['report']['generated'])}</p>",
        "<nav>" + "".join(f"<a href='#{sid}'>{_e(name)}</a>" for sid, name, _ in SECTIONS) + "</nav>",
    ]
    for sid, name, fn in SECTIONS:
        parts.append(f"<section id='{sid}'><h2>{_e(name)}</h2>{fn(rep)}</section>")
    if rep.notes:
        parts.append(
            "<section id='notes'><h2>Notes</h2><ul>"
            + "".join(f"<li>{_e(n)}</li>" for n in rep.notes)
            + "</ul></section>"
        )
    parts.append("</body></html>\n")
    return "".join(parts)


def write_report(rep: BatchReport, out_dir: Path, *, overwrite: bool = False) -> Path:
    """Write ``out_dir/report.html`` and ``out_dir/report.json`` atomically; returns the HTML path."""
    from tembayes.data.write import atomic_directory, write_json

    with atomic_directory(out_dir, overwrite=overwrite, kind="report") as tmp:
        (tmp / "report.html").write_text(render_html(rep), encoding="utf-8")
        write_json(tmp / "report.json", rep.to_json())
    return out_dir / "report.html"
