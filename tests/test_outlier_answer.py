"""The outlier answer: the spread sensitivity, the smallest deviation a design flags, the words, the figure,
and an earlier run's spreads as the prior (``--population-prior``)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from tembayes.bench.bench import TEC1_12706
from tembayes.calibrate.earlier import population_prior_of_run
from tembayes.calibrate.population.detectable import smallest_flagged
from tembayes.calibrate.population.model import Population
from tembayes.calibrate.runsummary import RunSummary
from tembayes.errors import DataError
from tembayes.report.outliers import OutlierAnswer

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_calibrate_population import fit, make_batch  # noqa: E402

#: A module's likelihood covariance in population coordinates: the population tests' posterior sds.
COV = np.diag([0.001, 0.02 * 0.0085 / 1.7, 0.002, 0.06 * 9.0e-5 / 0.048, 0.006]) ** 2


def test_outlier_probability_rises_as_the_assumed_spread_falls():
    """3 modules, one S0 10 spreads (10 %) off: given a small enough S0 spread it is surely an outlier.

    Restricting the hyper draws to tau_S0 <= s is conditioning on it: for
    the clear outlier the conditional outlier probability is > 0.9 at the
    true 1 %, falls as s grows, and at the largest s (most of the posterior
    below it) stays at or above the unconditioned value (the draws above it,
    left out, are those with the largest spreads).
    """
    draws, _, _ = make_batch(7, 3, outlier=0, shift=0.10, at_centre=True, clip=1.0)
    r = fit(draws)
    curve = r.outlier_vs_spread.to_json()
    assert curve["module"] == "U1" and curve["parameter"] == "S0_V_per_K" and curve["spread_name"] == "spread_S0_rel"
    rows = curve["rows"]
    at_1pc = next(x for x in rows if x["spread_max"] == pytest.approx(0.01))
    assert at_1pc["outlier_prob"] > 0.9
    valid = [x["outlier_prob"] for x in rows if x["outlier_prob"] is not None]
    assert valid[0] > valid[-1] >= r.outlier_prob["U1"]


def test_leaving_a_module_out_reweights_the_hyper_draws_by_its_inverse_likelihood():
    """A known answer: mu_S0 ~ N(0, s^2) over the draws and log L_1 = a mu_S0.

    Leaving module 1 out weights the draws by exp(-a mu), which moves their
    mean to -a s^2 (a Gaussian tilt; small enough for PSIS, k < 0.5): module
    1 at x = 0 with tau = s then sits +a s spreads from the others.  Weights
    the other way round (exp(+a mu)) put it at -a s.
    """
    from tembayes.calibrate.population.deviation import loo_deviation
    from tembayes.calibrate.population.model import N_HYPER

    pop = Population(TEC1_12706)
    rng = np.random.default_rng(3)
    S, sd, a = 20000, 0.01, 50.0
    h = np.zeros((S, N_HYPER))
    h[:, :5] = pop.mu_mean
    h[:, 2] = sd * rng.standard_normal(S)
    h[:, 5:10] = np.log(sd)  # tau = s in every parameter
    log_like = np.zeros((S, 2))
    log_like[:, 0] = a * h[:, 2]
    mean = np.tile(pop.mu_mean, (2, 1))
    mean[:, 2] = 0.0
    cov = np.tile(np.eye(5) * 1e-12, (2, 1, 1))
    dev = loo_deviation(pop, mean, cov, h, log_like)
    assert dev.k_hat[0] < 0.5
    assert dev.spreads[0, 2] == pytest.approx(a * sd, abs=0.03)
    assert dev.spreads[1, 2] == pytest.approx(0.0, abs=0.03)  # module 2's term is flat: no reweighting


def test_small_batches_need_larger_deviations_and_known_spreads_lower_them():
    """The design property: 3 modules flag only far larger S0 deviations than 8; a known 1 % spread lowers it.

    Even with the spread known, a unit 3 spreads off is no outlier at the prior
    odds (member density phi(3) against the 6-spread component's phi(0.5)/6:
    13 to 1, times a per-parameter outlier prior of ~2 %: P ~ 0.2), so 8
    modules need more than 3.
    """
    rng = np.random.default_rng(0)
    default = Population(TEC1_12706)
    known = Population(TEC1_12706, spread_prior={"tau_S0_rel": (0.01, 0.3)})
    three, eight = (smallest_flagged(default, n, 2, COV, rng) for n in (3, 8))
    three_known = smallest_flagged(known, 3, 2, COV, rng)
    assert three.spreads > 1.5 * eight.spreads and eight.spreads > 3.0, (three, eight)
    assert three_known.rel < 0.5 * three.rel, (three_known, three)
    assert 0.0 < three_known.rel < 0.15


def _doc(n=3):
    ids = [f"M{i + 1}" for i in range(n)]
    law = {"mean": 1.0, "sd": 0.01, "q05": 0.98, "q95": 1.02}
    dev = {
        p: {"rel": 0.001, "spreads": 0.1, "p_loo": 0.9} for p in ("R0_ohm", "R1_ohm_per_K", "S1_V_per_K2", "K_W_per_K")
    }
    mods = {}
    for i, m in enumerate(ids):
        s0 = {"rel": 0.031, "spreads": 3.3, "p_loo": 0.05} if i == 0 else {"rel": -0.01, "spreads": -0.5, "p_loo": 0.6}
        mods[m] = {
            **{p: law for p in ("R0_ohm", "R1_ohm_per_K", "S0_V_per_K", "S1_V_per_K2", "K_W_per_K")},
            "outlier_prob": 0.6 if i == 0 and n >= 8 else 0.05,
            "odd_one_prob": 0.7 if i == 0 else 0.3 / (n - 1),
            "deviation": {**dev, "S0_V_per_K": s0},
            "diagnostics": {"converged": True},
        }
    rows = [
        {"spread_max": 0.005, "outlier_prob": None, "odd_one_prob": None, "posterior_mass": 0.0},
        {"spread_max": 0.01, "outlier_prob": 0.8, "odd_one_prob": 0.95, "posterior_mass": 0.05},
        {"spread_max": 0.02, "outlier_prob": 0.2, "odd_one_prob": 0.8, "posterior_mass": 0.45},
        {"spread_max": 0.04, "outlier_prob": 0.1, "odd_one_prob": 0.7, "posterior_mass": 0.9},
    ]
    return {
        "modules": mods,
        "p_any_outlier": 0.2,
        "outlier_vs_spread": {"module": "M1", "parameter": "S0_V_per_K", "spread_name": "spread_S0_rel", "rows": rows},
        "smallest_flagged_deviation": {"parameter": "S0_V_per_K", "n_modules": n, "spreads": 16.0, "rel": 0.37}
        if n < 8
        else None,
    }


def test_the_answer_in_words_names_the_odd_one_how_far_and_what_would_decide_it():
    lines = OutlierAnswer.of(RunSummary.from_json(_doc(3))).lines()
    assert lines[0].startswith("Likeliest odd one: M1 (odd_one_prob 0.70; M2 0.15, M3 0.15)")
    assert "Its S0 sits +3.1 % from the other modules (+3.3 of their spreads)" in lines[0]
    assert "probability 0.05" in lines[0]
    assert lines[1] == "Probability that the batch holds an outlier at all: 0.20."
    # the smallest spread the draws reach, and the one nearest the batch's own median
    assert "if it is at most 1 %, P = 0.80; if it is at most 2 %, P = 0.20" in lines[2]
    assert lines[3].startswith("With 3 modules") and "37 % (16 typical spreads)" in lines[3]


def test_the_answer_says_when_the_deviation_is_approximate_and_when_the_spread_was_stated():
    doc = _doc(3)
    doc["population_diagnostics"] = {"deviation_k_hat": {"M1": 0.93, "M2": 0.2, "M3": 0.2}}
    doc["population_prior"] = {"spread_S0_rel": {"median": 0.01, "log_sd": 0.3}}
    lines = OutlierAnswer.of(RunSummary.from_json(doc)).lines()
    assert "(approximate: leave-one-out Pareto k 0.93 > 0.7)" in lines[0]
    # left out by a refit, its deviation is no approximation
    doc["population_diagnostics"]["deviation_refit"] = ["M1"]
    assert "approximate" not in OutlierAnswer.of(RunSummary.from_json(doc)).lines()[0]
    # ... unless that refit did not converge
    doc["population_diagnostics"]["deviation_refit_unconverged"] = ["M1"]
    first = OutlierAnswer.of(RunSummary.from_json(doc)).lines()[0]
    assert "(approximate: the fit of the other modules without it did not converge)." in first
    # the S0 spread was stated: the run already knows what would decide it
    assert not any("depends on this type's" in line for line in lines)
    assert lines[-1].startswith("With 3 modules")


def test_a_large_batch_flags_and_says_nothing_of_spreads():
    lines = OutlierAnswer.of(RunSummary.from_json(_doc(8))).lines()
    assert lines[0] == "Off the batch's population (outlier_prob > 0.5): M1."
    assert not any("spread" in line and "at most" in line for line in lines)


def test_no_population_no_answer():
    doc = _doc(3)
    doc["p_any_outlier"] = None
    assert OutlierAnswer.of(RunSummary.from_json(doc)) is None


def _earlier(tmp_path, **change):
    doc = {
        "batch": {"module_type": "TEC1-12706"},
        "population": {"S0_V_per_K": {"mean": 0.05, "sd": 0.0006, "q05": 0.049, "q95": 0.051}},
        "population_spreads": {"spread_S0_rel": {"median": 0.011, "log_sd": 0.25}},
        "population_diagnostics": {"converged": True},
    }
    doc.update(change)
    run = tmp_path / "earlier"
    run.mkdir(exist_ok=True)
    (run / "summary.json").write_text(json.dumps(doc))
    return run


def test_an_earlier_runs_spreads_and_its_refusals(tmp_path):
    assert population_prior_of_run(_earlier(tmp_path), "TEC1-12706") == {"spread_S0_rel": (0.011, 0.25)}
    with pytest.raises(DataError, match="module type 'TEC1-12706', not 'TEC1-12710'"):
        population_prior_of_run(_earlier(tmp_path), "TEC1-12710")
    with pytest.raises(DataError, match="no population_spreads"):
        population_prior_of_run(_earlier(tmp_path, population_spreads=None), "TEC1-12706")
    with pytest.raises(DataError, match="is not there"):
        population_prior_of_run(tmp_path / "nowhere", "TEC1-12706")
    with pytest.raises(DataError, match="has no population: that run fitted none"):
        population_prior_of_run(_earlier(tmp_path, population=None), "TEC1-12706")
    with pytest.raises(DataError, match="did not converge"):
        population_prior_of_run(_earlier(tmp_path, population_diagnostics={"converged": False}), "TEC1-12706")
    bad = {"spread_S0_rel": {"median": -0.01, "log_sd": 0.25}}
    with pytest.raises(DataError, match="population_spreads.spread_S0_rel"):
        population_prior_of_run(_earlier(tmp_path, population_spreads=bad), "TEC1-12706")
    with pytest.raises(DataError, match="population_spreads.spread_X_rel"):
        population_prior_of_run(
            _earlier(tmp_path, population_spreads={"spread_X_rel": {"median": 0.01, "log_sd": 0.2}}), "TEC1-12706"
        )


@pytest.mark.slow  # a population refit (1-2 min); the stated spreads' refit (test_calibrate_pipeline) and
# the refusals (test_an_earlier_runs_spreads_and_its_refusals) stay in CI
def test_population_prior_reaches_the_fit_and_a_clash_with_the_table_is_refused(
    run3, batch3, tmp_path, quick_population
):
    import shutil

    from tembayes.calibrate import CalibrationOptions, calibrate_batch
    from tembayes.data import load_batch

    out, summ, _ = run3
    earlier = population_prior_of_run(_earlier(tmp_path), load_batch(batch3).datasheet.name)
    run = tmp_path / "run"
    shutil.copytree(out / "modules", run / "modules")
    paper = CalibrationOptions(model="paper", discrepancy="none")  # run3's: a resume reuses only the same calibration
    again = calibrate_batch(load_batch(batch3), run, seed=0, resume=True, population_prior=earlier, options=paper)
    assert again.to_json()["population_prior"] == {"spread_S0_rel": {"median": 0.011, "log_sd": 0.25}}
    # the 1.1 % holds the S0 spread near it (the hyperprior's median is 2 %)
    assert again.population_spreads["spread_S0_rel"]["median"] < summ.population_spreads["spread_S0_rel"]["median"]
    stated = tmp_path / "batch"
    shutil.copytree(batch3, stated)
    with open(stated / "batch.toml", "a") as f:
        f.write("\n[population]\nspread_S0_rel = 0.01\n")
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(DataError, match="spread_S0_rel, which --population-prior also gives"):
        calibrate_batch(load_batch(stated), tmp_path / "refused", seed=0, population_prior=earlier)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_the_outliers_figure_draws_the_run(run3):
    from tembayes.plots.calibrate import plot_outliers

    out, summ, _ = run3
    fig = plot_outliers(out)
    left, right = fig.axes[:2]
    heights = [b.get_height() for b in left.patches]
    assert heights == pytest.approx([summ.modules[m].odd_one_prob for m in summ.modules])
    assert len(right.lines) == 3


def test_a_run_from_before_the_outlier_answer_reads_and_reports_without_it():
    """A summary.json without the new keys: no answer, a clear refusal to draw, the typed fields empty."""
    doc = _doc(3)
    for k in ("p_any_outlier", "outlier_vs_spread", "smallest_flagged_deviation"):
        del doc[k]
    for m in doc["modules"].values():
        del m["odd_one_prob"], m["deviation"]
    s = RunSummary.from_json(doc)
    assert OutlierAnswer.of(s) is None and s.p_any_outlier is None and s.modules["M1"].deviation is None


def test_the_spread_curve_carries_its_monte_carlo_error():
    """Known answer: a row holding every draw has the module's own outlier_prob se; a row of fewer, that se scaled.

    The effective share of the draws is the module's (its se against the
    per-draw values' sd); a row's se is its draws' sd over the root of that
    share of their number.
    """
    from tembayes.calibrate.population.membership import Membership
    from tembayes.calibrate.population.sensitivity import SPREAD_FACTORS, spread_sensitivity

    pop = Population(TEC1_12706)
    S, rng = 1000, np.random.default_rng(1)
    h = np.tile(np.concatenate([pop.mu_mean, pop.logtau_mean, [-2.0]]), (S, 1))
    h[:, 5 + 2] += rng.uniform(np.log(0.3), np.log(2.9), S)  # tau_S0 from 0.3 to 2.9 x its prior median
    lmem = np.log(rng.uniform(0.05, 0.95, (S, 3)))
    off = -np.expm1(lmem[:, 0])
    mcse = np.array([2.0, 1.0, 1.0]) * off.std() / np.sqrt(S)  # an effective share of 1/4
    m = Membership(1 - np.exp(lmem).mean(0), mcse, np.full(3, 1 / 3), 0.5, hyper=h, log_member=lmem)
    curve = spread_sensitivity(pop, m, 0, 2, "U1")
    assert SPREAD_FACTORS[-1] == 3.0 and curve.posterior_mass[-1] == 1.0
    assert curve.outlier_prob_mcse[-1] == pytest.approx(mcse[0])
    sel = np.exp(h[:, 7] - pop.logtau_mean[2]) <= SPREAD_FACTORS[3]  # the row at the prior median
    assert 0.2 < sel.mean() < 0.8 and curve.posterior_mass[3] == sel.mean()
    assert curve.outlier_prob_mcse[3] == pytest.approx(off[sel].std() / np.sqrt(sel.sum() / 4))
    assert curve.to_json()["rows"][-1]["outlier_prob_mcse"] == pytest.approx(mcse[0])
