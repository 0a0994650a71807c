"""summarize_experiment: the numbers behind ``tembayes inspect``."""

from __future__ import annotations

import numpy as np
import pytest

from tembayes.constants import KELVIN
from tembayes.data import experiment_from_arrays, load_experiment, noise_estimate, summarize_experiment
from tembayes.physics import REFERENCE

CSV_COLUMNS = REFERENCE.layout.csv_columns
TEMPERATURE_COLUMNS = REFERENCE.layout.temperatures


def test_summary_of_a_staircase():
    rng = np.random.default_rng(3)
    n = 6000
    t = 100.0 + 0.2 * np.arange(n)
    t[1000:] += 0.1  # one longer gap
    levels = np.repeat([0.0, 0.2, 0.4, -0.2, -0.4, 0.0], n // 6)
    cur = levels + rng.normal(0, 1e-3, n)
    volt = 1.7 * cur + rng.normal(0, 2e-3, n)
    drift = np.linspace(0, 5, n)  # slow signal: must not inflate the noise estimate
    sensors = np.array([21.0, 22.0, 27.0, 28.0])[:, None] + drift + KELVIN + rng.normal(0, 0.004, (4, n))
    tw = 20.0 + KELVIN + rng.normal(0, 0.03, n)
    ta = np.full(n, 23.0 + KELVIN)
    s = summarize_experiment(experiment_from_arrays(t, cur, volt, sensors, [tw, ta]))

    assert s["n_samples"] == n and isinstance(s["n_samples"], int)
    assert s["duration_s"] == pytest.approx(0.2 * (n - 1) + 0.1)
    assert s["dt_median_s"] == pytest.approx(0.2)
    assert s["dt_min_s"] == pytest.approx(0.2)
    assert s["dt_max_s"] == pytest.approx(0.3)
    assert s["current_min_A"] == pytest.approx(-0.4, abs=0.01)
    assert s["current_max_A"] == pytest.approx(0.4, abs=0.01)
    assert s["n_current_levels"] == 5
    assert s["T1_C_min"] == pytest.approx(21.0, abs=0.02)
    assert s["T1_C_max"] == pytest.approx(26.0, abs=0.02)
    assert s["T_amb_C_min"] == pytest.approx(23.0) and s["T_amb_C_max"] == pytest.approx(23.0)
    assert s["current_A_noise"] == pytest.approx(1e-3, rel=0.1)
    assert s["voltage_V_noise"] == pytest.approx(np.hypot(1.7e-3, 2e-3), rel=0.1)  # own + current noise
    for c in ("T1_C", "T2_C", "T3_C", "T4_C"):
        assert s[f"{c}_noise"] == pytest.approx(0.004, rel=0.1)
    assert s["T_water_C_noise"] == pytest.approx(0.03, rel=0.1)
    assert s["T_amb_C_noise"] == 0.0
    for c in TEMPERATURE_COLUMNS:
        assert f"{c}_min" in s and f"{c}_max" in s
    for c in CSV_COLUMNS[1:]:
        assert f"{c}_noise" in s
    assert all(type(v) in (int, float) for v in s.values())


def test_summary_of_loaded_file(data_factory):
    s = summarize_experiment(load_experiment(data_factory.write_csv()))
    assert s["n_samples"] == 50
    assert s["dt_median_s"] == pytest.approx(0.2)
    assert s["n_current_levels"] == 1
    assert 20.0 < s["T1_C_min"] < s["T1_C_max"] < 30.0


def test_noise_estimate_edge_cases():
    assert np.isnan(noise_estimate([1.0]))
    assert noise_estimate([1.0, 1.0, 1.0]) == 0.0


def _lagged(t, x, tau):
    """First-order response [same unit as x] with time constant ``tau`` [s]."""
    y = np.zeros_like(x)
    for k in range(1, len(t)):
        a = np.exp(-(t[k] - t[k - 1]) / tau)
        y[k] = a * y[k - 1] + (1 - a) * x[k - 1]
    return y


def _rig_run(hold, rng):
    """A seconds-stamped run of steps every ``hold`` s: the bottom block answers in 150 s, the top in 3 s."""
    t = np.arange(0.0, 60.0 + 40 * hold, 0.2)
    level = np.where(t < 60.0, 0.0, 0.2 * (1 + ((t - 60.0) // hold) % 4))
    cur = level + rng.normal(0, 1e-3, t.size)
    top, bottom = _lagged(t, level, 3.0), _lagged(t, level, 150.0)
    tw, ta = np.full(t.size, 20.0 + KELVIN), np.full(t.size, 22.0 + KELVIN)
    t3 = ta - 6.0 * bottom
    sensors = np.array([tw + 0.5 * top, tw + 1.0 * top, t3, t3 + 0.05 * (ta - t3)]) + rng.normal(0, 0.004, (4, t.size))
    return experiment_from_arrays(t, cur, 2.0 * cur, sensors, [tw, ta])


def test_short_holds_are_not_read_as_minutes():
    """Holds of 12 s cut the bottom block's 150 s response short: its 63 % time then measures the hold."""
    from tembayes.data.preflight import check_experiment

    found = check_experiment(_rig_run(12.0, np.random.default_rng(0)))
    assert not [f for f in found if f.column == "time_s"], [f.problem for f in found]
    minutes = _rig_run(900.0, np.random.default_rng(0))
    minutes = experiment_from_arrays(
        minutes.time / 60.0, minutes.current, minutes.voltage, minutes.sensors, minutes.boundaries
    )
    assert [f.column for f in check_experiment(minutes) if f.severity == "error"] == ["time_s"]
