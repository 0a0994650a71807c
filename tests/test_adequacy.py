"""The adequacy verdict: a model that fits passes (the model that misses an effect: ``test_gap``)."""

import json

from tembayes.calibrate.adequacy import LIMITS, assess


def _numbers(**over):
    n = {
        "window_score_variance_ratios": {
            "R0_ohm": 1.1,
            "R1_ohm_per_K": 0.9,
            "S0_V_per_K": 1.3,
            "S1_V_per_K2": 1.0,
            "K_W_per_K": 0.8,
        },
        "noise_scale_median": {"voltage_V": 1.0, "dT_K": 1.02, "Tmean_K": 0.97},
        "offset_sd_over_noise_median": {"voltage_V": 0.03, "dT_K": 0.05, "Tmean_K": 0.04},
        "residual_lag1_autocorrelation": {"voltage_V": -0.02, "dT_K": 0.04, "Tmean_K": 0.01},
    }
    for key, (where, value) in over.items():
        n[key] = {**n[key], where: value}
    return n


def test_every_check_names_its_worst_channel_and_the_verdict_follows_the_limits():
    assert assess(_numbers()).verdict == "fits"
    assert assess(_numbers()).reasons == []
    bad = assess(_numbers(residual_lag1_autocorrelation=("dT_K", LIMITS["residual_lag1"] + 0.01)))
    assert bad.verdict == "does_not_fit"
    (reason,) = bad.reasons
    assert reason.startswith("dT_K's residuals are correlated")
    # a strongly negative correlation is as much a misfit as a positive one
    assert assess(_numbers(residual_lag1_autocorrelation=("voltage_V", -0.9))).verdict == "does_not_fit"
    just = assess(_numbers(window_score_variance_ratios=("S1_V_per_K2", LIMITS["window_agreement"])))
    assert just.verdict == "fits"
    over = assess(_numbers(window_score_variance_ratios=("S1_V_per_K2", 1.01 * LIMITS["window_agreement"])))
    assert over.checks[0].where == "S1_V_per_K2" and not over.checks[0].passed
    nan = assess(_numbers(noise_scale_median=("Tmean_K", float("nan"))))
    assert nan.verdict == "does_not_fit" and nan.checks[1].where == "Tmean_K"


def test_a_model_that_is_the_rig_fits_its_run(run3):
    _, summ, _ = run3
    for mid, m in summ.modules.items():
        a = m.diagnostics["adequacy"]
        assert a["verdict"] == "fits", (mid, a["reasons"])
        json.dumps(a)  # summary.json takes it as it is
