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
