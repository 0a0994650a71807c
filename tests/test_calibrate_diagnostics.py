"""A module's diagnostics record: what counts as converged, and its JSON round trip."""

import dataclasses
import json

import pytest

from tembayes.calibrate.diagnostics import PSIS_K_MAX, ModuleDiagnostics, PsisCheck


def _record(**kw):
    base = dict(
        rhat={"R0_ohm": 1.004},
        ess_bulk={"R0_ohm": 1500.0},
        ess_tail={"R0_ohm": 1400.0},
        tau_steps={"R0_ohm": 80.0},
        rhat_max=1.004,
        rhat_walkers_max=1.02,
        ess_bulk_min=1500.0,
        tau_max_steps=80.0,
        tau_max_all_steps=120.0,
        chain_over_tau=60.0,
        steps=8000,
        burn_in_steps=2000,
        nwalkers=40,
        acceptance_mean=0.3,
        acceptance_min=0.2,
        sampler_converged=True,
        psis=(
            PsisCheck(stage=1, k_hat=1.3, weight_ess_fraction=0.05, max_logw_dev=9.0, early_steps=1000),
            PsisCheck(stage=2, k_hat=0.4, weight_ess_fraction=0.8, max_logw_dev=1.0),
        ),
        resumed=False,
        map_nfev=42,
        level_band_neglected=0.01,
        discrepancy={"method": "robust"},
        adequacy={"verdict": "fits"},
        timings={"total_s": 51.0},
    )
    return ModuleDiagnostics(**{**base, **kw})


def test_json_round_trip_keeps_every_field_and_the_stored_keys():
    d = _record()
    doc = json.loads(json.dumps(d.to_json()))
    assert ModuleDiagnostics.from_json(doc) == d
    # the stored record: the early check keeps its step count, the last has none
    assert doc["psis"][0]["early_steps"] == 1000 and "early_steps" not in doc["psis"][1]
    assert doc["converged"] is True


@pytest.mark.parametrize("k, sampler, converged", [(0.4, True, True), (PSIS_K_MAX, True, False), (0.4, False, False)])
def test_converged_needs_the_sampler_targets_and_the_last_psis_check(k, sampler, converged):
    last = PsisCheck(stage=2, k_hat=k, weight_ess_fraction=0.5, max_logw_dev=1.0)
    d = _record(sampler_converged=sampler, psis=(_record().psis[0], last))
    assert d.converged is converged
    assert (d.reasons() == []) is converged


def test_reasons_name_each_failed_target_with_its_number():
    d = _record(sampler_converged=False, rhat_max=1.03, ess_bulk_min=300.0, chain_over_tau=12.0)
    assert d.reasons() == ["R-hat 1.030 > 1.01", "bulk ESS 300 < 1000", "chain 12 autocorrelation times < 50"]
    off = dataclasses.replace(
        _record(), psis=(PsisCheck(stage=3, k_hat=0.95, weight_ess_fraction=0.1, max_logw_dev=4.0),)
    )
    assert off.reasons() == ["expansion PSIS k_hat 0.95 >= 0.7"]


class _Like:
    """A likelihood whose log-likelihood is ``f(X)``: the exact-over-linearised log-weights are ``f``."""

    def __init__(self, f):
        self.f = f
        self.calls = []

    def log_likelihood_x(self, X):
        self.calls.append(len(X))
        return self.f(X)


def _stage_check(curvature, *, converged=True, seed=3):
    """``_final_checks`` on 5000 N(0, 1) draws with log-weights ``curvature x0^2``: a Pareto tail of shape 2 x curvature."""
    from types import SimpleNamespace

    import numpy as np

    from tembayes.calibrate.module import CalibrationOptions, _final_checks
    from tembayes.common.seeds import stream

    X = np.random.default_rng(seed).standard_normal((5000, 7))
    exact = _Like(lambda X: curvature * X[:, 0] ** 2)
    st = SimpleNamespace(
        run=SimpleNamespace(chain=X[None], converged=converged),
        like=_Like(lambda X: np.zeros(len(X))),
        rng=stream(seed, "stage"),
    )
    prob = SimpleNamespace(options=CalibrationOptions(), space=SimpleNamespace(ndim=7), base_seed=seed)
    return _final_checks(prob, st, 1, exact), exact.calls


def test_a_failing_first_psis_look_is_decided_by_a_larger_sample():
    # w ~ exp(c x^2), x ~ N(0, 1): P(w > t) ~ t^(-1/(2c)), a Pareto tail of shape k = 2c
    light, calls = _stage_check(0.1)  # k = 0.2: the first look passes and decides
    assert calls == [400] and [c.draws for c in light] == [400] and light[-1].k_hat < PSIS_K_MAX
    heavy, calls = _stage_check(0.8)  # k = 1.6 (infinite mean): both looks fail, both are kept, the larger decides
    assert calls == [400, 2000] and [c.draws for c in heavy] == [400, 2000]
    assert min(c.k_hat for c in heavy) >= PSIS_K_MAX and [c.recheck for c in heavy] == [False, True]
    unconverged, calls = _stage_check(0.8, converged=False)  # rebuilt anyway: no second look
    assert calls == [400] and [c.draws for c in unconverged] == [400]


def test_the_law_shift_is_how_far_the_weights_move_a_laws_mean():
    import numpy as np

    from tembayes.calibrate.module import law_shift_sd

    # log-weights a x on x ~ N(0, 1) tilt it to N(a, 1): the mean moves by a sds
    x = np.random.default_rng(0).standard_normal((4000, 5))
    for a in (0.0, 0.3, 0.6):
        shift = law_shift_sd(x, a * x[:, 2])
        # the weighted mean's Monte Carlo sd is ~sqrt(exp(a^2) / 4000) < 0.02; the max over 5 laws adds ~2.3 of them
        assert abs(shift - a) < 0.06, (a, shift)


def test_a_psis_record_keeps_its_draws_and_law_shift_and_reads_older_records():
    new = PsisCheck(stage=2, k_hat=0.5, weight_ess_fraction=0.6, max_logw_dev=3.0, draws=2000, law_shift_sd=0.12)
    assert PsisCheck(**json.loads(json.dumps(new.to_json()))) == new
    old = {"stage": 1, "k_hat": 0.4, "weight_ess_fraction": 0.8, "max_logw_dev": 1.0}
    assert PsisCheck(**old).to_json() == old


def test_an_unconverged_expansion_names_the_draws_that_decided():
    last = PsisCheck(stage=3, k_hat=0.81, weight_ess_fraction=0.1, max_logw_dev=4.0, draws=2000, law_shift_sd=0.4)
    off = dataclasses.replace(_record(), psis=(last,))
    assert off.reasons() == ["expansion PSIS k_hat 0.81 >= 0.7 on 2000 draws"]


def test_a_second_look_passes_only_on_usable_weights():
    from tembayes.calibrate.diagnostics import RECHECK_MIN_ESS

    # the liquid-plate module's second look: k_hat under the limit on 12 effective draws of 2000
    degenerate = PsisCheck(stage=2, k_hat=0.686, weight_ess_fraction=0.006, max_logw_dev=68.0, draws=2000, recheck=True)
    assert not degenerate.passes
    off = dataclasses.replace(_record(), psis=(degenerate,))
    assert not off.converged
    assert off.reasons() == [f"expansion PSIS weights degenerate: 12 effective of 2000 draws < {RECHECK_MIN_ESS}"]
    usable = dataclasses.replace(degenerate, weight_ess_fraction=0.06)  # 120 effective draws
    assert usable.passes and dataclasses.replace(_record(), psis=(usable,)).converged
    # a first look is judged on k_hat alone
    assert dataclasses.replace(degenerate, recheck=False).passes
    assert PsisCheck(**json.loads(json.dumps(degenerate.to_json()))) == degenerate
