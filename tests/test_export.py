"""Uncertainty inputs for observer design (``tembayes export``)."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

P = dict(R0_ohm=1.80, R1_ohm_per_K=0.0095, S0_V_per_K=0.0493, S1_V_per_K2=7.4e-5, K_W_per_K=0.56)


@pytest.fixture(scope="module")
def rig():
    from tembayes.physics.rig import reference_rig

    return reference_rig(4, 6)


def test_linear_model_matches_the_simulator_for_a_small_current_step(rig):
    """The linear response to a 0.02 A step equals the nonlinear simulator's to O(dI^2)."""
    from scipy.linalg import expm

    from tembayes.constants import KELVIN
    from tembayes.export.linearise import linearise
    from tembayes.physics import Inputs, simulate

    lm = linearise(P, rig, 35.0, 2.5, t_amb_C=25.0)
    assert 0.5 * (lm.x0[lm.states.index("hot_plate")] + lm.x0[lm.states.index("cold_plate")]) == \
        pytest.approx(35.0 + KELVIN, abs=1e-6)
    assert np.max(np.linalg.eigvals(lm.A).real) < 0  # a stable rig
    t = np.arange(0.0, 601.0, 1.0)
    dI = 0.02
    u = np.ones_like(t)
    sim = simulate(Inputs(t, lm.u0[0] + dI * u, lm.u0[1] * u, lm.u0[2] * u), P, rig=rig, y0=lm.x0,
                   steady_start=False, atol=1e-7)
    y_nl = np.vstack([sim.sensors[0], sim.voltage[0]]) - lm.y0[:, None]
    # exact step response of the linear model: x(t) = A^-1 (e^{At} - I) B du
    Ainv_B = np.linalg.solve(lm.A, lm.B[:, 0] * dI)
    x = np.stack([expm(lm.A * tk) @ Ainv_B - Ainv_B for tk in t[::50]], axis=1)
    y_lin = lm.C @ x + lm.D[:, :1] * dI
    scale = np.max(np.abs(y_lin), axis=1)
    err = np.max(np.abs(y_nl[:, ::50] - y_lin), axis=1)
    assert np.all(scale[:4] > 5e-3)  # the step moves every sensor by mK: the check is not vacuous
    assert np.all(err / scale < 0.02), err / scale


def test_sensitivities_predict_the_relinearised_model(rig):
    from tembayes.export.linearise import linearise

    names = ["K_W_per_K", "R0_ohm", "g_cooler"]
    base = {**P, "g_cooler": 12.5}
    lm = linearise(base, rig, 30.0, 3.0, sensitivity=names)
    for name in names:
        h = 0.01 * base[name]  # 100x the differencing step: a first-order prediction, checked at 1e-3 of the change
        moved = linearise({**base, name: base[name] + h}, rig, 30.0, 3.0)
        for k in ("A", "B", "C", "D", "x0", "u0", "y0"):  # the matrices and the operating point
            change = getattr(moved, k) - getattr(lm, k)
            pred = lm.sensitivity[name][k] * h
            if np.max(np.abs(change)) > 1e-6 * np.max(np.abs(getattr(lm, k))):  # else rounding only
                assert np.max(np.abs(change - pred)) < 0.03 * np.max(np.abs(change)), (name, k)
    assert lm.sensitivity["R0_ohm"]["D"][-1, 0] == pytest.approx(1.0, rel=0.05)  # dV/dI moves with R


def test_ou_fit_under_white_noise_recovers_the_disturbance_and_finds_none_in_white_noise():
    from tembayes.export.observer import fit_ou_plus_white

    rng = np.random.default_rng(3)
    n, tau, sd, white = 8000, 200.0, 0.02, 0.004
    t = np.arange(n, dtype=float)
    phi = np.exp(-1.0 / tau)
    d = np.empty(n)
    d[0] = rng.normal(0, sd)
    for k in range(1, n):
        d[k] = phi * d[k - 1] + rng.normal(0, sd * np.sqrt(1 - phi * phi))
    s_hat, tau_hat = fit_ou_plus_white(t, d + rng.normal(0, white, n), white)
    # 8000 s / 200 s = 40 correlation times: sd to ~15 %, tau to a factor 1.6
    assert s_hat == pytest.approx(sd, rel=0.25)
    assert tau / 1.6 < tau_hat < tau * 1.6
    s0, _ = fit_ou_plus_white(t, rng.normal(0, white, n), white)
    assert s0 < 0.1 * white  # negative control: white noise is no disturbance


def test_disturbance_structure_finds_a_transient_after_steps_and_a_shared_disturbance():
    """Synthetic residuals: white noise on every channel; channels 0 and 1 share one slow
    disturbance; channel 2 has an extra 50 mK error only in the first 10 s after each current
    step.  The profile shows that error in the first bin only, the correlation the sharing."""
    from tembayes.export.observer import STEP_BINS_S, disturbance_structure, time_since_step

    rng = np.random.default_rng(5)
    n, white = 20000, 0.004
    t = np.arange(n, dtype=float)
    current = np.repeat(np.tile([0.5, -1.0, 1.5, -0.5], n // 2000), 500) + rng.normal(0, 1e-3, n)
    since = time_since_step(t, current)
    assert since[0] == np.inf and since[500] == 0.0 and since[777] == 277.0
    common = np.convolve(rng.normal(0, 1, n + 300), np.ones(300) / np.sqrt(300), "valid")[:n] * 0.01
    r = rng.normal(0, white, (5, n))
    r[0] += common
    r[1] += common
    r[2] += np.where(since < 10, rng.normal(0, 0.05, n), 0.0)
    R = np.eye(5) * white ** 2
    out = disturbance_structure(t, r, current, R)
    prof = out["sd_by_time_since_step"]
    assert list(out["step_bins_s"]) == list(STEP_BINS_S) and prof.shape == (5, len(STEP_BINS_S))
    assert prof[2, 0] == pytest.approx(0.05, rel=0.15) and np.all(prof[2, 1:] < 0.005)
    assert out["corr"][0, 1] > 0.9 and abs(out["corr"][0, 2]) < 0.2
    assert out["n_by_time_since_step"].sum() == n - 500  # every sample after the first step, once
    assert out["corr_by_time_since_step"].shape == (len(STEP_BINS_S), 5, 5)
    assert out["corr_by_time_since_step"][-1, 0, 1] > 0.9
    assert np.all(np.linalg.eigvalsh(out["corr"]) > -1e-9) and np.allclose(np.diag(out["corr"]), 1.0)


@pytest.fixture(scope="module")
def export1(run3, batch3):
    from tembayes.calibrate.run import load_run
    from tembayes.data import load_batch
    from tembayes.export.observer import observer_inputs

    return observer_inputs(load_run(run3[0]), load_batch(batch3), points=[(25.0, 0.0), (40.0, 3.0)],
                           modules=["TEM1"], n_draws=50)


def test_export_moments_and_noise_are_those_of_the_run_and_the_sensors(export1, run3):
    from tembayes.calibrate.run import load_run

    m = export1.modules["TEM1"]
    names = list(export1.parameters)
    assert names[:5] == ["R0_ohm", "R1_ohm_per_K", "S0_V_per_K", "S1_V_per_K2", "K_W_per_K"]
    assert "g_cooler" in names and m["cov"].shape == (len(names), len(names))
    assert np.all(np.linalg.eigvalsh(m["cov"]) > -1e-18)
    # the laws' moments are the posterior's (the anchoring moves the rig, not R and S)
    summ = load_run(run3[0]).module_summary("TEM1")
    for j, k in enumerate(names[:4]):
        assert m["mean"][j] == pytest.approx(summ[k]["mean"], abs=0.1 * summ[k]["sd"])
        assert np.sqrt(m["cov"][j, j]) == pytest.approx(summ[k]["sd"], rel=0.1)
    # bench sensor noise: 4 mK on the temperatures, 1 mV on the voltage (truth.json)
    sd = np.sqrt(np.diag(m["measurement_noise_cov"]))
    noise = run3[2]["noise_rms"]
    assert sd[:4] == pytest.approx(noise["temperature_K"], rel=0.1)
    assert sd[4] == pytest.approx(noise["voltage_V"], rel=0.1)
    assert "identification" in m["process_noise"]["source"]  # batch3 has no held-out run
    assert "population" in export1.modules and m["draws"].shape == (50, len(names))


@pytest.mark.parametrize("fmt", ["json", "npz", "mat"])
def test_export_round_trips_in_every_format(export1, fmt):
    from scipy.io import loadmat

    from tembayes.export.formats import encode

    data = encode(export1, fmt)
    m, lm = export1.modules["TEM1"], export1.modules["TEM1"]["linear"][1]
    if fmt == "json":
        doc = json.loads(data)
        A = np.array(doc["modules"]["TEM1"]["linear"]["op1"]["A"])
        cov = np.array(doc["modules"]["TEM1"]["cov"])
        dA = np.array(doc["modules"]["TEM1"]["linear"]["op1"]["sensitivity"]["K_W_per_K"]["A"])
        states = doc["states"]
        isd = doc["modules"]["TEM1"]["input_noise"]["current_sd_A"]
        dy0 = np.array(doc["modules"]["TEM1"]["linear"]["op1"]["sensitivity"]["K_W_per_K"]["y0"])
        chans = doc["modules"]["TEM1"]["process_noise"]["channels"]
    elif fmt == "npz":
        z = np.load(io.BytesIO(data))
        A, cov = z["modules__TEM1__linear__op1__A"], z["modules__TEM1__cov"]
        dA = z["modules__TEM1__linear__op1__sensitivity__K_W_per_K__A"]
        states = list(z["states"])
        isd = z["modules__TEM1__input_noise__current_sd_A"]
        dy0 = z["modules__TEM1__linear__op1__sensitivity__K_W_per_K__y0"]
        chans = list(z["modules__TEM1__process_noise__channels"])
    else:
        doc = loadmat(io.BytesIO(data), simplify_cells=True)
        A, cov = doc["modules"]["TEM1"]["linear"]["op1"]["A"], doc["modules"]["TEM1"]["cov"]
        dA = doc["modules"]["TEM1"]["linear"]["op1"]["sensitivity"]["K_W_per_K"]["A"]
        states = [str(s).strip() for s in doc["states"]]
        assert doc["schema"] == "tembayes-observer-export/1"
        isd = doc["modules"]["TEM1"]["input_noise"]["current_sd_A"]
        dy0 = doc["modules"]["TEM1"]["linear"]["op1"]["sensitivity"]["K_W_per_K"]["y0"]
        chans = [str(c).strip() for c in doc["modules"]["TEM1"]["process_noise"]["channels"]]
    np.testing.assert_allclose(A, lm.A, rtol=1e-12)
    np.testing.assert_allclose(cov, m["cov"], rtol=1e-12)
    np.testing.assert_allclose(dA, lm.sensitivity["K_W_per_K"]["A"], rtol=1e-12)
    assert states == list(lm.states)
    assert float(isd) == m["input_noise"]["current_sd_A"] and chans == ["T1_C", "T2_C", "T3_C", "T4_C", "voltage_V"]
    np.testing.assert_allclose(dy0, lm.sensitivity["K_W_per_K"]["y0"], rtol=1e-12)


def test_export_cli_refuses_a_bad_point_and_writes_nothing(run3, tmp_path, capsys):
    from tembayes.cli import main

    out = tmp_path / "x.json"
    assert main(["export", str(run3[0]), "--out", str(out), "--point", "30;2"]) == 2
    assert "--point '30;2'" in capsys.readouterr().err and not out.exists()
    assert main(["export", str(run3[0]), "--out", str(tmp_path / "x.txt")]) == 2
    assert not (tmp_path / "x.txt").exists()
    # a held-out run the module does not have: refused up front, naming the module folder
    assert main(["export", str(run3[0]), "--out", str(out), "--heldout", "validation7.csv"]) == 2
    err = capsys.readouterr().err
    assert "validation7.csv" in err and "TEM1" in err and not out.exists()
