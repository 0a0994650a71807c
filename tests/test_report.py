"""The batch-calibration report (``tembayes report``): tolerances, structure and
content of the HTML, and a render in headless Chromium whose screenshot is checked.

Uses the calibrated 3-module bench batch of ``conftest.run3`` (TEM2 the
bench's outlier), a copy of its batch with a 1-hour validation run of TEM1,
and a gap folder with a ``gap.json`` in the contract's form.
"""

from __future__ import annotations

import base64
import io
import json
import os
import re
import shutil
import subprocess

import numpy as np
import pytest
from benchdata import record_validation

from tembayes.cli import main
from tembayes.report.tolerances import DEFAULT_TOLERANCES, Tolerance, parse_tolerance

SECTIONS = (
    "acceptance",
    "overview",
    "quality",
    "laws",
    "population",
    "hysteresis",
    "convergence",
    "adequacy",
    "corner",
    "validation",
    "gap",
    "provenance",
)


def test_tolerances_parse_and_bad_ones_are_named():
    assert parse_tolerance("R0=5%") == Tolerance("R0=5%", "R0_ohm", "relative", (0.05,))
    assert parse_tolerance("R1_ohm_per_K=0.008:0.012").value == (0.008, 0.012)
    assert parse_tolerance("outlier_prob=0.3").kind == "max"
    assert parse_tolerance("converged=no").value == (False,)
    assert len([parse_tolerance(t) for t in DEFAULT_TOLERANCES]) == 5
    for bad, says in (
        ("R1=5%", "datasheet gives no value of R1_ohm_per_K"),
        ("Q=5%", "unknown name 'Q'"),
        ("R0", "expected NAME=VALUE"),
        ("K=0.6:0.5", "LOW < HIGH"),
        ("S0=abc%", "'abc' is not"),
        ("outlier_prob=2", "between 0 and 1"),
        ("R0=0.5", "PERCENT%"),
    ):
        with pytest.raises(ValueError, match=re.escape(says)):
            parse_tolerance(bad)


@pytest.fixture(scope="module")
def report_inputs(run3, batch3, tmp_path_factory):
    """(run folder, batch copy with TEM1/validation.csv, gap folder, truth)."""
    out, _, truth = run3
    d = tmp_path_factory.mktemp("rep")
    batch = d / "batch"
    shutil.copytree(batch3, batch)
    record_validation(truth["modules"]["TEM1"], batch / "TEM1" / "validation.csv", 7, hours=1.0)
    gap = d / "gap"
    gap.mkdir()
    (gap / "gap.json").write_text(
        json.dumps(
            {
                "verdict": "explained",
                "best": "sensor_lag",
                "best_group": ["sensor_lag"],
                "metric": "excess RMSE [K] over T1..T4",
                "where": [{"channel": "T3_C", "regime": "heating, transient", "score": 4.2}],
                "ranking": [
                    {
                        "effect": "sensor_lag",
                        "evidence": 812.5,
                        "evidence_se": 40.1,
                        "evidence_kind": "heldout_elpd",
                        "gap_before": 0.021,
                        "gap_after": 0.0012,
                        "shrink": 0.94,
                    },
                    {
                        "effect": "thomson",
                        "evidence": 3.0,
                        "evidence_kind": "screen",
                        "gap_before": 0.021,
                        "gap_after": 0.0209,
                        "shrink": 0.005,
                    },
                ],
                "conflicts": {
                    "TEM1": [
                        {
                            "parameter": "g_paste_cold",
                            "unit": "W/K",
                            "low": 20.0,
                            "high": 50.0,
                            "median": 11.5,
                            "q_low": 11.2,
                            "q_high": 11.8,
                            "outside_sd": 2.4,
                            "conflict": True,
                        }
                    ]
                },
            }
        )
    )
    return out, batch, gap, truth


@pytest.fixture(scope="module")
def report(report_inputs, tmp_path_factory):
    """``tembayes report`` run through the CLI: (folder, html text, report.json)."""
    run, batch, gap, _ = report_inputs
    out = tmp_path_factory.mktemp("rep_out") / "report"
    assert (
        main(
            [
                "report",
                str(run),
                "--out",
                str(out),
                "--batch",
                str(batch),
                "--gap",
                str(gap),
                "--draws",
                "60",
                "--tolerance",
                "R0=5%",
                "--tolerance",
                "S0=0.1%",
                "--tolerance",
                "outlier_prob=0.5",
            ]
        )
        == 0
    )
    return out, (out / "report.html").read_text(encoding="utf-8"), json.loads((out / "report.json").read_text())


def _images(html):
    return re.findall(r'<img alt="([^"]*)" src="data:image/png;base64,([^"]+)"', html)


def test_report_is_one_self_contained_file_with_every_section(report):
    out, html, doc = report
    assert sorted(p.name for p in out.iterdir()) == [".tembayes-output.json", "report.html", "report.json"]
    for sid in SECTIONS:
        assert f"<section id='{sid}'>" in html
    # which model the laws rest on, and whether it fits each module's run
    assert 'calibration model</td><td class="l">paper (Evers' in html and "discrepancy: none" in html
    assert 'prior on the laws</td><td class="l">the datasheet&#x27;s</td>' in html
    adequacy = html.split("<section id='adequacy'>")[1].split("</section>")[0]
    assert adequacy.count('<td class="pass">fits</td>') == len(doc["modules"]) == 3, adequacy
    # nothing outside the file: no external source, link, script or stylesheet
    assert not re.search(r'(src|href)\s*=\s*["\'](?!data:|#)', html)
    assert "<script" not in html and "<link" not in html
    from PIL import Image

    imgs = _images(html)
    # per module laws + corner, the batch laws, outliers, population corner, hysteresis, TEM1 validation
    assert len(imgs) == 3 + 3 + 1 + 1 + 1 + 1 + 1
    population = html.split("<section id='population'>")[1].split("</section>")[0]
    assert "Likeliest odd one: " in population and 'id="fig-outliers"' in population
    for alt, b64 in imgs:
        im = Image.open(io.BytesIO(base64.b64decode(b64)))
        im.verify()  # a whole, decodable PNG
        assert im.format == "PNG" and min(im.size) > 200, alt


def test_report_content_matches_the_run(report, run3):
    _, html, doc = report
    _, summ, truth = run3
    # every module's R0 posterior mean as in summary.json, in the laws table
    for _mid, m in summ.modules.items():
        assert f"{m.laws['R0_ohm'].mean:.5g} ± {m.laws['R0_ohm'].sd:.2g}" in html
        assert f"{m.outlier_prob:.3f}" in html
    # the datasheet-derived value and the calibration command are shown
    assert "R = 1.752 Ω" in html and f"emcee {summ.calibration['versions']['emcee']}" in html
    # validation: only TEM1 has a run; its metrics are the contract's five channels
    assert [(v["module"], v["experiment"]) for v in doc["validation"]] == [("TEM1", "validation.csv")]
    assert set(doc["validation"][0]["channels"]) == {"T1_C", "T2_C", "T3_C", "T4_C", "voltage_V"}
    assert 0.6 < doc["validation"][0]["channels"]["T3_C"]["coverage90"] <= 1.0
    # gap summary: verdict, best, the conflict row
    assert "Verdict: <b>explained</b>; best: <b>sensor_lag</b>" in html and "g_paste_cold" in html
    # provenance: seed and versions of the report
    assert doc["provenance"]["report"]["versions"]["emcee"] and "report command" in html


def test_acceptance_fails_a_tolerance_the_posterior_misses_and_passes_a_wide_one(report, run3):
    """S0 within 0.1 % of the datasheet value: a band of +-48 uV/K, narrower than a module's
    90 % posterior interval (+-1.645 sd, about +-90 uV/K), so no module can have
    P(inside) >= 0.95 and every one fails, wherever its S0 lies.  R0 within 5 % passes
    exactly when the posterior is clearly inside."""
    _, html, doc = report
    _, summ, _ = run3
    for m in doc["modules"]:
        checks = {c["check"]: c for c in m["acceptance"]["checks"]}
        s0 = checks["S0=0.1%"]
        sd = summ.modules[m["id"]].laws["S0_V_per_K"].sd
        assert 2 * 0.001 * 0.0483 < 2 * 1.645 * sd  # the premise
        assert not s0["passed"] and s0["p_inside"] < 0.95
        r0, post = checks["R0=5%"], summ.modules[m["id"]].laws["R0_ohm"]
        ref = doc["overview"]["datasheet_derived"]["R_ohm"]
        margin = min(abs(post.mean - 0.95 * ref), abs(post.mean - 1.05 * ref)) / post.sd
        if margin > 4:  # clearly inside or outside: the check must say which
            assert r0["passed"] == (0.95 * ref < post.mean < 1.05 * ref)
        assert doc["passed"][m["id"]] is False and m["acceptance"]["passed"] is False
    assert html.count(">FAIL<") == 3 and "0 of 3 modules pass" in html


def test_report_refuses_bad_input_and_writes_nothing(report_inputs, tmp_path, capsys):
    run, batch, gap, _ = report_inputs
    out = tmp_path / "r"
    assert main(["report", str(run), "--out", str(out), "--batch", str(batch), "--tolerance", "R1=5%"]) == 2
    assert "R1=5%" in capsys.readouterr().err and not out.exists()
    bad = tmp_path / "badgap"
    bad.mkdir()
    (bad / "gap.json").write_text(json.dumps({"verdict": "no_gap"}))
    assert main(["report", str(run), "--out", str(out), "--batch", str(batch), "--gap", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "gap.json" in err and "'where'" in err and not out.exists()


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    if os.environ.get("TEMBAYES_REQUIRE_BROWSER"):
        pytest.fail("TEMBAYES_REQUIRE_BROWSER is set but no chromium is installed (apt-get install chromium)")
    pytest.skip("no chromium: install Debian's chromium to run the browser test (.ci/run does)")


def _screenshot(browser, html_path, png_path, tmp_path, height=5200):
    cmd = [
        browser,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={tmp_path / ('profile-' + png_path.stem)}",
        "--hide-scrollbars",
        f"--window-size=1280,{height}",
        f"--screenshot={png_path}",
        html_path.as_uri(),
    ]
    subprocess.run(cmd, check=True, capture_output=True, timeout=180)
    from PIL import Image

    return np.asarray(Image.open(png_path).convert("RGB"), dtype=float) / 255.0


def _plotted_rows(rgb):
    """Fraction of screen rows that cross plotted data: rows with at least 5 pixels in a
    saturated colour (bands, lines, markers), which the report's grey text and pale table
    shading are not; the few coloured text rows (links, PASS) stay a small fraction."""
    mx, mn = rgb.max(axis=2), rgb.min(axis=2)
    sat = np.where(mx > 0, (mx - mn) / np.maximum(mx, 1e-9), 0.0)
    return float(np.mean(((sat > 0.3) & (mx > 0.25)).sum(axis=1) >= 5))


def test_report_renders_in_headless_chromium_with_its_figures(report, tmp_path):
    """The screenshot of the top of the report is not blank, and its figures are drawn: the
    same page with the images taken out (the control) has almost none of their colour."""
    browser = _chromium()
    out, html, _ = report
    shot = _screenshot(browser, out / "report.html", tmp_path / "report.png", tmp_path)
    assert shot.shape[1] == 1280 and shot.shape[0] >= 5000
    grey = shot.mean(axis=2)
    assert grey.std() > 0.08 and (grey < 0.5).mean() > 0.01  # not blank: text and lines on the page
    control_html = tmp_path / "no_images.html"
    control_html.write_text(re.sub(r"<img [^>]*>", "", html), encoding="utf-8")
    control = _screenshot(browser, control_html, tmp_path / "control.png", tmp_path)
    # measured on the example batch: 0.35 of the rows with the figures, 0.018 without
    with_figs, without = _plotted_rows(shot), _plotted_rows(control)
    assert with_figs > 0.15, with_figs
    assert with_figs > 5 * without, (with_figs, without)


def test_the_gap_section_shows_the_laws_before_and_after_the_recalibration():
    from tembayes.report.html import _recalibrated

    law = {"mean": 1.8, "sd": 0.002, "q05": 1.797, "q95": 1.803}
    before = {p: dict(law) for p in ("R0_ohm", "R1_ohm_per_K", "S0_V_per_K", "S1_V_per_K2", "K_W_per_K")}
    after = {**before, "R0_ohm": {**law, "mean": 1.81, "sd": 0.003}}
    html = _recalibrated(
        {
            "effects": ["sensor_lag"],
            "run": "run",
            "laws_before": {"TEM1": before, "TEM2": before},
            "laws_after": {"TEM1": after},
            "modules_not_recalibrated": ["TEM2"],
        }
    )
    row = html.split("<tr>")[2]  # the first module's R0
    assert ">TEM1<" in row and "1.8 ± 0.002" in row and "1.81 ± 0.003" in row and "+5.0" in row
    assert html.count("<tr>") == 1 + 5 and "Not recalibrated (laws as before): TEM2" in html
    assert "sensor_lag added" in html
    assert _recalibrated(None) == ""
