"""Uncertainty inputs for observer design (``tembayes export``)."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

P = dict(R0_ohm=1.80, R1_ohm_per_K=0.0095, S0_V_per_K=0.0493, S1_V_per_K2=7.4e-5, K_W_per_K=0.56)


@pytest.fixture(scope="module")
def rig():
    from tembayes.physics.rigread import rig_from_config

    return rig_from_config(None, 4, 3)


def test_linear_model_matches_the_simulator_for_a_small_current_step(rig):
    """The linear response to a 0.02 A step equals the nonlinear simulator's to O(dI^2)."""
    from scipy.linalg import expm

    from tembayes.constants import KELVIN
    from tembayes.export.linearise import linearise
    from tembayes.physics import Inputs, simulate

    lm = linearise(P, rig, 35.0, 2.5, room_C=25.0)
    assert 0.5 * (lm.x0[lm.states.index("hot_plate")] + lm.x0[lm.states.index("cold_plate")]) == pytest.approx(
        35.0 + KELVIN, abs=1e-6
    )
    assert np.max(np.linalg.eigvals(lm.A).real) < 0  # a stable rig
    t = np.arange(0.0, 601.0, 1.0)
    dI = 0.02
    u = np.ones_like(t)
    sim = simulate(
        Inputs(t, lm.u0[0] + dI * u, lm.u0[1:, None] * u), P, rig=rig, y0=lm.x0, steady_start=False, atol=1e-7
    )
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
    from tembayes.common.ou import fit_ou

    rng = np.random.default_rng(3)
    n, tau, sd, white = 8000, 200.0, 0.02, 0.004
    t = np.arange(n, dtype=float)
    phi = np.exp(-1.0 / tau)
    d = np.empty(n)
    d[0] = rng.normal(0, sd)
    for k in range(1, n):
        d[k] = phi * d[k - 1] + rng.normal(0, sd * np.sqrt(1 - phi * phi))
    fit = fit_ou(t, d + rng.normal(0, white, n), white_sd=white)
    s_hat, tau_hat = fit.sd, fit.tau_s
    # 8000 s / 200 s = 40 correlation times: sd to ~15 %, tau to a factor 1.6
    assert s_hat == pytest.approx(sd, rel=0.25)
    assert tau / 1.6 < tau_hat < tau * 1.6
    assert (
        fit_ou(t, rng.normal(0, white, n), white_sd=white).sd < 0.1 * white
    )  # negative control: white noise is no disturbance


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
    R = np.eye(5) * white**2
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

    # the default operating points: the calibrated range's
    return observer_inputs(load_run(run3[0]), load_batch(batch3), modules=["TEM1"], n_draws=50)


def test_export_moments_and_noise_are_those_of_the_run_and_the_sensors(export1, run3):
    from tembayes.calibrate.run import load_run

    m = export1.modules["TEM1"]
    names = list(export1.parameters)
    assert names[:5] == ["R0_ohm", "R1_ohm_per_K", "S0_V_per_K", "S1_V_per_K2", "K_W_per_K"]
    assert "g_cooler" in names and m.cov.shape == (len(names), len(names))
    assert np.all(np.linalg.eigvalsh(m.cov) > -1e-18)
    # the laws' moments are the posterior's (the anchoring moves the rig, not R and S)
    summ = load_run(run3[0]).module_summary("TEM1")
    for j, k in enumerate(names[:4]):
        assert m.mean[j] == pytest.approx(summ.laws[k].mean, abs=0.1 * summ.laws[k].sd)
        assert np.sqrt(m.cov[j, j]) == pytest.approx(summ.laws[k].sd, rel=0.1)
    # bench sensor noise: 4 mK on the temperatures, 1 mV on the voltage (truth.json)
    sd = np.sqrt(np.diag(m.measurement_noise_cov))
    noise = run3[2]["noise_rms"]
    assert sd[:4] == pytest.approx(noise["temperature_K"], rel=0.1)
    assert sd[4] == pytest.approx(noise["voltage_V"], rel=0.1)
    assert "identification" in m.process_noise["source"]  # batch3 has no held-out run
    assert "population" in export1.modules and m.draws.shape == (50, len(names))


@pytest.mark.parametrize("fmt", ["json", "npz", "mat"])
def test_export_round_trips_in_every_format(export1, fmt):
    from scipy.io import loadmat

    from tembayes.export.formats import encode

    data = encode(export1, fmt)
    m, lm = export1.modules["TEM1"], export1.modules["TEM1"].linear[1]
    if fmt == "json":
        doc = json.loads(data)
        A = np.array(doc["modules"]["TEM1"]["linear"]["op1"]["A"])
        cov = np.array(doc["modules"]["TEM1"]["cov"])
        dA = np.array(doc["modules"]["TEM1"]["linear"]["op1"]["sensitivity"]["K_W_per_K"]["A"])
        states = doc["states"]
        isd = doc["modules"]["TEM1"]["input_noise"]["current_sd_A"]
        dy0 = np.array(doc["modules"]["TEM1"]["linear"]["op1"]["sensitivity"]["K_W_per_K"]["y0"])
        chans = doc["modules"]["TEM1"]["process_noise"]["channels"]
        outputs, inputs, fields = doc["outputs"], doc["inputs"], doc["fields"]
    elif fmt == "npz":
        z = np.load(io.BytesIO(data))
        A, cov = z["modules__TEM1__linear__op1__A"], z["modules__TEM1__cov"]
        dA = z["modules__TEM1__linear__op1__sensitivity__K_W_per_K__A"]
        states = list(z["states"])
        isd = z["modules__TEM1__input_noise__current_sd_A"]
        dy0 = z["modules__TEM1__linear__op1__sensitivity__K_W_per_K__y0"]
        chans = list(z["modules__TEM1__process_noise__channels"])
        outputs, inputs = list(z["outputs"]), list(z["inputs"])
        fields = {k: list(z[f"fields__{k}"]) for k in ("path", "shape", "unit", "meaning")}
    else:
        doc = loadmat(io.BytesIO(data), simplify_cells=True)
        A, cov = doc["modules"]["TEM1"]["linear"]["op1"]["A"], doc["modules"]["TEM1"]["cov"]
        dA = doc["modules"]["TEM1"]["linear"]["op1"]["sensitivity"]["K_W_per_K"]["A"]
        states = [str(s).strip() for s in doc["states"]]
        assert doc["schema"] == "tembayes-observer-export/3"
        isd = doc["modules"]["TEM1"]["input_noise"]["current_sd_A"]
        dy0 = doc["modules"]["TEM1"]["linear"]["op1"]["sensitivity"]["K_W_per_K"]["y0"]
        chans = [str(c).strip() for c in doc["modules"]["TEM1"]["process_noise"]["channels"]]
        outputs, inputs = [str(c).strip() for c in doc["outputs"]], [str(c).strip() for c in doc["inputs"]]
        fields = {k: [str(c).strip() for c in v] for k, v in doc["fields"].items()}
    np.testing.assert_allclose(A, lm.A, rtol=1e-12)
    np.testing.assert_allclose(cov, m.cov, rtol=1e-12)
    np.testing.assert_allclose(dA, lm.sensitivity["K_W_per_K"]["A"], rtol=1e-12)
    assert states == list(lm.states)
    assert float(isd) == m.input_noise["current_sd_A"] and chans == ["T1_C", "T2_C", "T3_C", "T4_C", "voltage_V"]
    assert outputs == chans and inputs == ["current_A", "T_water_C", "T_amb_C"]  # one naming scheme: the CSV's
    assert fields["path"][0] == "schema" and len(set(map(len, fields.values()))) == 1
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


def _covered(**kw):
    """A synthetic calibrated range: a staircase -1.6..0.8 A whose steady T̄ falls 12..50 degC with the current."""
    from pathlib import Path

    from tembayes.export.coverage import OperatingRange

    current = np.round(np.arange(-1.6, 0.81, 0.2), 6)
    tavg = 20.0 - 10.0 * current + 2.0 * current**2
    base = dict(
        tavg_C=(float(tavg.min()), float(tavg.max())),
        current_A=(-1.6, 0.8),
        boundaries_C={"T_water_C": (19.9, 20.2), "T_amb_C": (21.5, 22.5)},
        states=np.column_stack([tavg, current]),
        modules=("TEM1", "TEM2"),
        source=Path("runs/x"),
    )
    return OperatingRange(**{**base, **kw})


def test_default_points_are_steady_states_inside_the_calibrated_range():
    from tembayes.export.coverage import check_points, default_points

    covered = _covered()
    points = default_points(covered)
    assert [p[1] for p in points] == [-1.6, 0.0, 0.8]  # the lowest, the nearest-zero and the highest current
    assert points[1][0] == pytest.approx(20.0) and points[0][0] == pytest.approx(20.0 + 16.0 + 5.12, abs=0.05)
    assert (
        all(covered.contains(*p) for p in points)
        and check_points(points, covered=covered, allow_extrapolation=False) == []
    )
    # the old defaults (25 C, 2 A; 40 C, 4 A) lie outside a staircase of -1.6..0.8 A
    assert not covered.contains(25.0, 2.0) and not covered.contains(40.0, 4.0)


def test_a_point_outside_the_range_is_refused_naming_it_and_the_range_or_warned_about_when_allowed():
    from tembayes.errors import DataError
    from tembayes.export.coverage import check_points

    covered = _covered()
    with pytest.raises(DataError) as err:
        check_points([(30.0, -0.5), (25.0, 2.0)], covered=covered, allow_extrapolation=False)
    msg = str(err.value)
    assert "T_avg 25 C, I 2 A (--point 25,2)" in msg and "30" not in msg.split("outside")[0]
    assert "I -1.600..0.800 A" in msg and "TEM1, TEM2" in msg and "--allow-extrapolation" in msg
    warned = check_points([(30.0, -0.5), (25.0, 2.0)], covered=covered, allow_extrapolation=True)
    assert len(warned) == 1 and "T_avg 25 C, I 2 A" in warned[0] and "outside the calibrated range" in warned[0]


def test_boundary_warnings_name_a_point_whose_water_is_far_from_the_runs():
    from types import SimpleNamespace

    from tembayes.constants import KELVIN
    from tembayes.export.coverage import BOUNDARY_MARGIN_K, boundary_warnings

    covered = _covered()
    inputs = ("current_A", "T_water_C", "T_amb_C")
    near, far = (
        SimpleNamespace(tavg_C=t, current_A=i, u0=np.array([i, tw + KELVIN, 295.0]), inputs=inputs)
        for t, i, tw in ((20.0, 0.0, 20.5), (45.0, 0.5, 20.2 + BOUNDARY_MARGIN_K + 1.0))
    )
    assert boundary_warnings([[near]], covered=covered, room_C=22.0, room="T_amb_C", controlled=("T_water_C",)) == []
    out = boundary_warnings(
        [[near, far], [near, near]], covered=covered, room_C=30.0, room="T_amb_C", controlled=("T_water_C",)
    )
    assert len(out) == 2 and "T_amb_C 30 C" in out[0] and "T_avg 45 C, I 0.5 A needs T_water_C" in out[1]


def test_default_export_points_lie_inside_the_runs_range(export1):
    meta = export1.meta
    (tl, th), (il, ih) = meta["calibrated_range"]["tavg_C"], meta["calibrated_range"]["current_A"]
    assert il == pytest.approx(-1.6, abs=0.01) and ih == pytest.approx(0.8, abs=0.01)  # batch3's staircase
    assert len(meta["points"]) == 3 and meta["warnings"] == [] and meta["allow_extrapolation"] is False
    for t, i in meta["points"]:
        assert tl - 0.011 <= t <= th + 0.011 and il - 0.0011 <= i <= ih + 0.0011
    assert [lm.current_A for lm in export1.modules["TEM1"].linear] == [p[1] for p in meta["points"]]


def test_every_field_of_the_file_is_described_in_its_schema_and_in_the_docs(export1):
    import re
    from pathlib import Path

    from tembayes.export.formats import encode
    from tembayes.export.schema import FIELDS

    doc = json.loads(encode(export1, "json"))
    known = {f.path for f in FIELDS}

    def paths(tree, prefix=""):
        for k, v in tree.items():
            key = f"{prefix}.{k}" if prefix else k
            if isinstance(v, dict) and key not in ("fields", "units", "meta.module_ids"):
                yield from paths(v, key)
            else:
                yield key

    def generic(path):
        path = re.sub(r"^modules\.[^.]+\.", "modules.<module>.", path)
        path = re.sub(r"\.op\d+\.", ".op<k>.", path)
        path = re.sub(r"\.boundaries_C\.[^.]+$", ".boundaries_C.<boundary>", path)
        return re.sub(r"\.sensitivity\.[^.]+\.[^.]+$", ".sensitivity.<parameter>.<X>", path)

    missing = sorted({generic(p) for p in paths(doc)} - known)
    assert not missing, f"fields in the file but not in tembayes.export.schema.FIELDS: {missing}"
    assert doc["fields"]["path"] == [f.path for f in FIELDS] and all(f.unit for f in FIELDS)
    docs = (Path(__file__).resolve().parents[1] / "docs" / "outputs.md").read_text(encoding="utf-8")
    undocumented = [f.path for f in FIELDS if f"`{f.path}`" not in docs]
    assert not undocumented, f"export fields missing from docs/outputs.md: {undocumented}"


def test_export_cli_refuses_a_point_outside_the_calibrated_range_and_writes_nothing(run3, tmp_path, capsys):
    from tembayes.cli import main

    out = tmp_path / "x.json"
    assert main(["export", str(run3[0]), "--out", str(out), "--point", "25,2", "--module", "TEM1"]) == 2
    err = capsys.readouterr().err
    assert "T_avg 25 C, I 2 A (--point 25,2)" in err and "calibrated range" in err and "I -1.6" in err
    assert "--allow-extrapolation" in err and not out.exists()


def test_export_cli_allow_extrapolation_warns_and_records_it(run3, tmp_path, capsys):
    from tembayes.cli import main

    out = tmp_path / "x.json"
    assert (
        main(
            [
                "export",
                str(run3[0]),
                "--out",
                str(out),
                "--point",
                "25,2",
                "--point",
                "25,0",
                "--module",
                "TEM1",
                "--draws",
                "20",
                "--allow-extrapolation",
            ]
        )
        == 0
    )
    assert "warning: operating point T_avg 25 C, I 2 A lies outside" in capsys.readouterr().err
    meta = json.loads(out.read_text())["meta"]
    assert meta["allow_extrapolation"] is True and meta["points"] == [[25.0, 2.0], [25.0, 0.0]]
    assert any("T_avg 25 C, I 2 A lies outside the calibrated range" in w for w in meta["warnings"])
    assert not any("I 0 A lies outside" in w for w in meta["warnings"])  # the inside point is not flagged
