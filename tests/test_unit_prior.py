"""A known type's population as a new unit's prior on the laws (``calibrate --unit-prior``, ``design --population``)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from tembayes.bench import TEC1_12706
from tembayes.calibrate import CalibrationOptions
from tembayes.calibrate.earlier import unit_prior_of_run
from tembayes.calibrate.priors import LawPrior, ParameterPrior, law_log_prior
from tembayes.constants import MODULE_PARAMETERS
from tembayes.data import load_batch
from tembayes.errors import DataError

LEVELS = ("R0_ohm", "S0_V_per_K", "K_W_per_K")


def test_an_earlier_runs_population_becomes_the_unit_prior_and_other_runs_are_refused(run3, batch3, tmp_path):
    """The prior is the population-predictive draws' log moments (R0, S0, K) or moments (R1, S1).

    Against the population block's mean and sd: a log-normal's mean ``c e^(s^2/2)`` matches
    to 0.1 %; its sd ``mean sqrt(e^(s^2) - 1)`` only as far as the draws are log-normal.  A
    predictive from three modules has heavy tails (the logs' excess kurtosis 9-76 on this
    batch, the sds up to 7.5 % apart), so the sd is checked against what the logs' skewness
    g and excess kurtosis k make of it: to second order in s, the draws' variance is
    (c s)^2 (1 + g s + 7/12 k s^2 + 1.5 s^2), a log-normal's (c s)^2 (1 + 1.5 s^2); on this
    batch the expansion gives the ratio to 1 %.
    """
    from scipy.stats import kurtosis, skew

    from tembayes.calibrate.run import load_run

    out, summ, _ = run3
    name = load_batch(batch3).datasheet.name
    lp = unit_prior_of_run(out, name)
    pop = summ.to_json()["population"]
    draws = load_run(out).population_draws()
    for j, p in enumerate(lp.priors):
        mean, sd = pop[p.name]["mean"], pop[p.name]["sd"]
        if p.name in LEVELS:
            logs = np.log(draws[:, j])
            assert (np.log(p.center), p.scale) == pytest.approx((logs.mean(), logs.std(ddof=1)), rel=1e-9)
            m = p.center * np.exp(0.5 * p.scale**2)
            assert m == pytest.approx(mean, rel=1e-3)
            g, k, s2 = skew(logs), kurtosis(logs), p.scale**2
            expected = np.sqrt((1 + 1.5 * s2) / (1 + g * p.scale + 7 / 12 * k * s2 + 1.5 * s2))
            assert m * np.sqrt(np.expm1(s2)) / sd == pytest.approx(expected, rel=0.02)
        else:
            assert (p.center, p.scale) == pytest.approx((mean, sd), rel=1e-3)
    assert str(out.resolve()) in lp.source
    with pytest.raises(DataError, match=f"module type '{name}', not 'TEC1-12710'"):
        unit_prior_of_run(out, "TEC1-12710")
    unconverged = tmp_path / "unconverged"
    shutil.copytree(out, unconverged)
    doc = json.loads((unconverged / "summary.json").read_text())
    doc["population_diagnostics"]["converged"] = False
    (unconverged / "summary.json").write_text(json.dumps(doc))
    with pytest.raises(DataError, match="did not converge"):
        unit_prior_of_run(unconverged, name)


def _tight(module, scale=1e-4):
    """A law prior centred on ``module``'s truth, ``scale`` wide (the log's sd, or relative for the slopes)."""
    kinds = {k: ("lognormal" if k in LEVELS else "normal") for k in MODULE_PARAMETERS}
    return LawPrior(
        tuple(
            ParameterPrior(k, kinds[k], module[k], scale if k in LEVELS else scale * abs(module[k]))
            for k in MODULE_PARAMETERS
        ),
        "test",
    )


def test_a_unit_prior_is_the_calibrations_prior_on_the_laws():
    """A prior 0.01 % wide holds every law to within it; the datasheet's leaves R0 at least 10 times wider.

    The Laplace sd can only fall below the prior's sd when the data add
    information, so ``sd <= prior sd`` (to 1 %) checks that the prior is the one
    in the problem; the datasheet prior's R0 sd on the same run (~0.2 %) shows
    the tight one was not the datasheet's.
    """
    from tembayes.calibrate.module import _problem
    from tembayes.design.search import Designer
    from tembayes.design.widths import expected_widths

    d = Designer(TEC1_12706, None, seed=0, n_draws=1, jobs=1)
    module = next(iter(d.setup.truth["modules"].values()))
    from tembayes.bench.bench import run_experiment

    exp = run_experiment(d.protocol(0.8, 120.0), module, d.setup.effects, np.random.default_rng(1), **d.setup.run)
    start = {**d.setup.effects, **module["rig"], **{k: module[k] for k in MODULE_PARAMETERS}}
    lp = _tight(module)
    tight = expected_widths(exp, TEC1_12706, options=CalibrationOptions(law_prior=lp), start=start, max_nfev=3)
    sheet = expected_widths(exp, TEC1_12706, start=start, max_nfev=3)
    for p in lp.priors:
        prior_sd = p.center * p.scale if p.name in LEVELS else p.scale
        assert tight.sd_laplace[p.name] <= 1.01 * prior_sd, p.name
    assert sheet.sd_laplace["R0_ohm"] > 10 * tight.sd_laplace["R0_ohm"]

    class _Module:
        id = "TEM1"
        identification = exp

    prob = _problem(_Module, TEC1_12706, None, CalibrationOptions(law_prior=lp), (), 0)
    assert prob.space.priors[: len(MODULE_PARAMETERS)] == lp.priors


@pytest.mark.slow  # a population refit (1-2 min); the unit prior's making and refusals stay in CI
def test_a_run_under_a_unit_prior_records_it_and_its_population_divides_it_out(
    run3, batch3, tmp_path, monkeypatch, quick_population
):
    """summary.json names the prior, the run gives it back, the prior group draws from it, the population divides it;
    a resume under another prior than the modules were sampled under is refused."""
    from tembayes.calibrate import calibrate_batch
    from tembayes.calibrate import population as P
    from tembayes.calibrate.batch import finish_run
    from tembayes.calibrate.run import load_run

    out, summ, _ = run3
    lp = unit_prior_of_run(out, load_batch(batch3).datasheet.name)
    seen = {}
    fit = P.fit_population

    def spy(*args, **kw):
        seen.update(kw)
        return fit(*args, **kw)

    monkeypatch.setattr(P, "fit_population", spy)
    opt = CalibrationOptions(model="paper", discrepancy="none", law_prior=lp)
    earlier = tmp_path / "earlier"
    shutil.copytree(out, earlier)
    with pytest.raises(DataError, match="the datasheet's, not population of .*--unit-prior"):
        calibrate_batch(load_batch(batch3), earlier, seed=0, resume=True, options=opt)
    run = tmp_path / "run"
    shutil.copytree(out / "modules", run / "modules")
    again = finish_run(load_batch(batch3), run, seed=0, options=opt)
    assert again.calibration["law_prior"] == lp.source
    back = load_run(run)
    assert back.calibration_options().law_prior == lp
    theta = back.draws("TEM1")[:50]
    np.testing.assert_allclose(seen["log_interim_prior"](theta), law_log_prior(lp.priors)(theta))
    r0 = back.prior_draws(("R0_ohm",))[:, 0]
    assert np.median(r0) == pytest.approx(lp.priors[0].center, rel=3 * lp.priors[0].scale / np.sqrt(len(r0)) + 1e-9)


def test_the_commands_refuse_a_run_that_is_no_unit_prior_and_write_nothing(batch3, tmp_path):
    from tembayes.cli import main

    nowhere = tmp_path / "nowhere"
    assert main(["calibrate", str(batch3), "--out", str(tmp_path / "c"), "--unit-prior", str(nowhere)]) != 0
    assert main(["design", str(batch3), "--out", str(tmp_path / "d"), "--population", str(nowhere)]) != 0
    assert not (tmp_path / "c").exists() and not (tmp_path / "d").exists()
