"""The typed summary.json record: every key read, the document kept whole, older runs readable."""

import copy

import pytest

from tembayes.calibrate.runsummary import LawSummary, RunSummary
from tembayes.constants import MODULE_PARAMETERS


def _law(mean, sd):
    return {"mean": mean, "sd": sd, "q05": mean - 1.645 * sd, "q95": mean + 1.645 * sd}


def _doc():
    entry = {p: _law(1.0 + i, 0.01) for i, p in enumerate(MODULE_PARAMETERS)}
    entry |= {
        "outlier_prob": 0.12,
        "diagnostics": {
            "converged": True,
            "rhat_max": 1.004,
            "adequacy": {"verdict": "does_not_fit", "reasons": ["window offsets"]},
        },
        "hysteresis": {"R_ohm": {"estimate": 1e-4, "sd": 2e-4, "z": 0.5}},
        "nuisance": {"g_cooler": _law(11.0, 0.3)},
    }
    other = copy.deepcopy(entry) | {"outlier_prob": None}
    other["diagnostics"] = {"converged": False}
    return {
        "tref_C": 25.0,
        "modules": {"TEM1": entry, "TEM2": other},
        "population": {"S0_V_per_K": {"mean": 0.05}},
        "population_diagnostics": {"converged": True},
        "population_spreads": {"spread_S0_rel": {"median": 0.01, "log_sd": 0.3}},
        "population_excluded": {"TEM2": "R-hat 1.03"},
        "failed_modules": {},
        "converged": False,
        "calibration": {"seed": 3, "effects": []},
        "batch": {"path": "/data/lot42"},
        "a_key_added_later": [1, 2],
    }


def test_every_typed_field_reads_its_key():
    s = RunSummary.from_json(_doc())
    tem1, tem2 = s.modules["TEM1"], s.modules["TEM2"]
    assert tem1.laws["S0_V_per_K"] == LawSummary.from_json(_law(3.0, 0.01))
    assert tem1.outlier_prob == 0.12 and tem2.outlier_prob is None
    assert tem1.converged and not tem2.converged
    assert tem1.adequacy_failed and tem1.adequacy_reasons == ("window offsets",)
    assert not tem2.adequacy_failed and tem2.adequacy_reasons == ()
    assert tem1.nuisance["g_cooler"].mean == 11.0 and tem1.hysteresis["R_ohm"]["z"] == 0.5
    assert s.population_excluded == {"TEM2": "R-hat 1.03"} and s.converged is False
    assert s.calibration["seed"] == 3 and s.batch["path"] == "/data/lot42" and s.tref_C == 25.0


def test_to_json_is_the_document_whole_and_a_copy():
    doc = _doc()
    s = RunSummary.from_json(doc)
    assert s.to_json() == doc  # untyped keys too
    doc["modules"]["TEM1"]["outlier_prob"] = 0.9  # the record does not share the caller's dict
    out = s.to_json()
    out["converged"] = True
    assert s.to_json()["modules"]["TEM1"]["outlier_prob"] == 0.12 and s.to_json()["converged"] is False


def test_a_run_that_predates_the_population_keys_reads_with_empty_values():
    doc = _doc()
    for k in ("population_diagnostics", "population_spreads", "population_excluded", "failed_modules", "tref_C"):
        del doc[k]
    del doc["modules"]["TEM1"]["nuisance"], doc["modules"]["TEM1"]["hysteresis"]
    s = RunSummary.from_json(doc)
    assert s.population_excluded == {} and s.failed_modules == {} and s.population_spreads is None
    assert s.tref_C == pytest.approx(25.0) and s.modules["TEM1"].nuisance == {}
    with pytest.raises(TypeError):
        s.modules["TEM1"].laws["R0_ohm"] = None  # read-only
