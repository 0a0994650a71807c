"""The calibration model's physics (``--model paper|full``) and catalogue effects in a calibration (``--effect``)."""

from __future__ import annotations

import numpy as np
import pytest

from tembayes.calibrate.modelform import FORMS
from tembayes.calibrate.module import CalibrationOptions, calibration_rig, parameter_space
from tembayes.cli import main
from tembayes.constants import KELVIN, MODULE_PARAMETERS
from tembayes.errors import ModelError
from tembayes.physics.simulate import Inputs, simulate

LAWS = {"R0_ohm": 1.75, "R1_ohm_per_K": 0.009, "S0_V_per_K": 0.047, "S1_V_per_K2": 1e-4, "K_W_per_K": 0.54}


def _run(rig, extra=None):
    t = np.linspace(0.0, 900.0, 901)
    current = np.where(t < 100, 0.0, np.where(t < 500, 1.2, -1.2))
    inputs = Inputs(t, current, [np.full_like(t, 20.0 + KELVIN), np.full_like(t, 23.0 + KELVIN)])
    return simulate(inputs, {**LAWS, **(extra or {})}, rig=rig)


def test_the_full_form_is_the_paper_form_plus_its_physics():
    full = calibration_rig({"preset": "reference"}, CalibrationOptions(model="full"))
    paper = calibration_rig({"preset": "reference"}, CalibrationOptions(model="paper"))
    assert dict(full.physics) == {"thomson_fraction": 1.0} and dict(paper.physics) == {}
    assert "g_ceramic" in full.parameter_names and "g_ceramic" not in paper.parameter_names
    assert {"hot_ceramic", "cold_ceramic"} <= {n for n, _ in full.nodes}
    # the rig's physics is what build() uses unless a parameter mapping says otherwise
    a = _run(full)
    b = _run(full, {"thomson_fraction": 1.0})
    c = _run(full, {"thomson_fraction": 0.0})
    np.testing.assert_array_equal(a.sensors, b.sensors)
    assert np.max(np.abs(a.sensors - c.sensors)) > 0.02  # Thomson heat moves the blocks by tens of mK


def test_the_full_form_samples_its_physics_and_refuses_what_it_already_holds():
    class Data:  # the noise priors need only the channels' noise
        noise = np.array([1e-3, 4e-3, 4e-3])

    full = calibration_rig({"preset": "reference"}, CalibrationOptions(model="full"))
    _, space = parameter_space(full, _datasheet(), Data, 0.1, form="full")
    assert {"sensor_tau_s", "K1_per_K"} <= set(space.names) and "g_ceramic" in space.fixed  # held at nominal
    assert set(MODULE_PARAMETERS) <= set(space.names) and "thomson_fraction" not in space.names
    for name in FORMS["full"].includes:
        with pytest.raises(ModelError, match=f"already contains {name}"):
            parameter_space(full, _datasheet(), Data, 0.1, (name,), form="full")
        with pytest.raises(ModelError, match="already contains"):
            CalibrationOptions(model="full", effects=(name,))
    with pytest.raises(ModelError, match="both sampled and at a fixed value"):
        CalibrationOptions(model="paper", effects=("sensor_lag",), effect_values={"sensor_tau_s": 5.0})


def _datasheet():
    from tembayes.bench import TEC1_12706

    return TEC1_12706


def test_calibrate_effect_option_samples_or_fixes_an_effect(monkeypatch, tmp_path, capsys):
    import shutil

    from corpus import EXAMPLE

    seen = {}

    def fake(batch, out, **kw):
        seen.update(kw)
        raise ModelError("stop here")

    monkeypatch.setattr("tembayes.calibrate.batch.calibrate_batch", fake)
    b = tmp_path / "b"
    (b / "TEM1").mkdir(parents=True)
    shutil.copy(EXAMPLE / "batch.toml", b)
    shutil.copy(EXAMPLE / "TEM1" / "identification.csv", b / "TEM1")
    argv = [
        "calibrate",
        str(b),
        "--out",
        str(tmp_path / "run"),
        "--effect",
        "k_temperature",
        "--effect",
        "sensor_lag=5",
        "--workers",
        "1",
        "--model",
        "paper",
    ]
    assert main(argv) == 2 and "stop here" in capsys.readouterr().err
    opt = seen["options"]
    assert opt.effects == ("k_temperature",) and opt.effect_values == {"sensor_tau_s": 5.0}
    assert calibration_rig({}, opt).physics["sensor_tau_s"] == 5.0
    assert main([*argv[:4], "--effect", "no_such"]) == 2
    assert "the catalogue has" in capsys.readouterr().err
    assert main([*argv[:4], "--effect", "thomson"]) == 2  # the default form, full, holds Thomson heat
    assert "already contains thomson" in capsys.readouterr().err
