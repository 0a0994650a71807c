"""Every stage on rigs other than the reference one: layout, simulator, bench, preflight, step data."""

from __future__ import annotations

from importlib import resources

import numpy as np
import pytest

from tembayes.bench import BenchConfig, simulate_batch
from tembayes.bench import bench as bench_module
from tembayes.bench.anyrig import bench_rig, mounting_parameters, outside_bench_rig
from tembayes.bench.protocols import identification_staircase
from tembayes.constants import KELVIN
from tembayes.data import load_batch
from tembayes.errors import DataError, ModelError
from tembayes.physics import Inputs, shipped_rig, simulate
from tembayes.physics.rigread import REFERENCE, rig_file_of, rig_from_config

PAPER = {"R0_ohm": 1.7, "R1_ohm_per_K": 0.0085, "S0_V_per_K": 0.048, "S1_V_per_K2": 1e-4, "K_W_per_K": 0.54}


@pytest.mark.parametrize(
    "name, face, hot, cold, paths",
    [
        ("reference", ("T2_C", "T3_C"), ("T2_C", "T1_C"), ("T3_C", "T4_C"),
         (("T_water_C", "T1_C", "T2_C"), ("T_amb_C", "T4_C", "T3_C"))),
        ("reference-faces", ("T2_C", "T3_C"), ("T2_C",), ("T3_C",), (("T_water_C", "T2_C"), ("T_amb_C", "T3_C"))),
        ("heatsink-al", ("T_hot_C", "T_cold_C"), ("T_hot_C",), ("T_cold_C", "T_load_C"),
         (("T_amb_C", "T_hot_C"), ("T_amb_C", "T_load_C", "T_cold_C"))),
        ("liquid-plates", ("T_hot_C", "T_cold_C"), ("T_hot_C",), ("T_cold_C",),
         (("T_hot_liquid_C", "T_hot_C"), ("T_cold_liquid_C", "T_cold_C"))),
    ],
)  # fmt: skip
@pytest.mark.parametrize("resolution", [{}, {"leg_cells": 3, "split": 5, "layers": True}])
def test_layout_reads_the_sensors_places_from_the_graph(name, face, hot, cold, paths, resolution):
    """The face sensors, the sides and the heat paths do not depend on the resolution the rig is built at."""
    layout = shipped_rig(name).build(**resolution).layout
    assert layout.face == face and layout.hot_side == hot and layout.cold_side == cold
    assert layout.paths == paths
    assert layout.leak_boundary == "ambient"


def test_without_a_rig_the_columns_are_the_contract_defaults(tmp_path):
    """An experiment made or read with no rig named has the reference rig's columns (contract section 2)."""
    from tembayes.data import experiment_from_arrays, load_experiment, write_experiment_csv

    assert REFERENCE.layout.csv_columns == (
        "time_s", "current_A", "voltage_V", "T1_C", "T2_C", "T3_C", "T4_C", "T_water_C", "T_amb_C",
    )  # fmt: skip
    t = np.arange(5.0)
    exp = experiment_from_arrays(t, np.zeros(5), np.zeros(5), np.full((4, 5), 300.0), np.full((2, 5), 295.0))
    assert exp.columns == REFERENCE.layout.csv_columns
    path = write_experiment_csv(tmp_path / "x.csv", exp)
    assert load_experiment(path).boundary_names == ("T_water_C", "T_amb_C")


@pytest.mark.parametrize("name", ["heatsink-al", "liquid-plates"])
def test_at_zero_current_the_rig_settles_between_its_boundaries(name):
    """One, two or three boundaries: with no heat source every node ends inside their range, and with all
    boundaries at one temperature exactly there."""
    rig = shipped_rig(name).build(leg_cells=2, split=3, layers=True)
    nb = len(rig.boundaries)
    t = np.linspace(0.0, 20000.0, 401)
    levels = 290.0 + 5.0 * np.arange(nb)
    start = np.full(len(rig.node_names), 330.0)
    sim = simulate(
        Inputs(t, np.zeros_like(t), np.repeat(levels[:, None], len(t), axis=1)),
        PAPER,
        rig=rig,
        y0=start,
        steady_start=False,
    )
    end = sim.sensors[0, :, -1]
    assert np.all(end >= levels.min() - 1e-6) and np.all(end <= levels.max() + 1e-6)
    same = simulate(Inputs(t, np.zeros_like(t), np.full((nb, len(t)), 300.0)), PAPER, rig=rig)
    np.testing.assert_allclose(same.sensors[0], 300.0, atol=1e-9)


def test_inputs_with_another_number_of_boundaries_are_refused():
    rig = shipped_rig("heatsink-al").build()
    t = np.arange(3.0)
    with pytest.raises(ModelError, match="2 boundary temperature.*'heatsink-al' has 1 \\(T_amb_C\\)"):
        simulate(Inputs(t, np.zeros(3), np.full((2, 3), 300.0)), PAPER, rig=rig)


def test_mounting_parameters_are_the_module_and_its_contacts():
    assert mounting_parameters(rig_from_config(None, 2, 3, layers=True)) == {
        "c_legs", "c_plate_hot", "c_plate_cold", "g_ceramic", "g_paste_hot", "g_paste_cold",
    }  # fmt: skip
    assert mounting_parameters(shipped_rig("heatsink-al").build(layers=True)) == {
        "c_legs", "c_plate", "g_ceramic", "g_paste",
    }  # fmt: skip


@pytest.fixture(scope="module")
def heatsink_batch(tmp_path_factory):
    out = tmp_path_factory.mktemp("anyrig") / "batch"
    config = BenchConfig(n_modules=2, seed=5, n_validations=0, hold=300.0, rig={"preset": "heatsink-al"})
    truth = simulate_batch(out, config, progress=lambda msg: None)
    return out, truth


def test_the_robust_carry_over_moves_a_lead_share_in_its_logit_and_a_resistance_relatively(heatsink_batch):
    """The held parameters' carry-over moves a lead share in its logit and a resistance relatively: a share
    near its floor moved additively crossed zero in a few draws, and relatively passed one."""
    from tembayes.calibrate.model import StepResponseModel
    from tembayes.calibrate.module import (
        CalibrationOptions,
        calibration_rig,
        flat_coordinates,
        parameter_space,
        positive_coordinates,
    )
    from tembayes.calibrate.stepdata import step_data

    batch = load_batch(heatsink_batch[0])
    rig = calibration_rig(batch.rig_config, CalibrationOptions())
    data = step_data(batch.modules["TEM1"].identification, face=rig.layout.face)
    space = parameter_space(rig, batch.datasheet, data, StepResponseModel(data, rig).shift_bound)[1]
    positive, shares = positive_coordinates(space), flat_coordinates(space, rig)
    assert space.index("g_sink") in positive and space.index("lead_share") not in positive
    assert list(shares) == [space.index("lead_share")]
    np.testing.assert_allclose(shares[space.index("lead_share")], (0.0001, 0.01))  # its documented range
    assert space.index("R1_ohm_per_K") not in positive + list(shares)


def test_the_calibration_samples_the_lead_share_flat_and_the_rig_as_before(heatsink_batch):
    from tembayes.calibrate.model import StepResponseModel
    from tembayes.calibrate.module import CalibrationOptions, calibration_rig, parameter_space
    from tembayes.calibrate.stepdata import step_data

    out, _ = heatsink_batch
    batch = load_batch(out)
    rig = calibration_rig(batch.rig_config, CalibrationOptions())
    data = step_data(batch.modules["TEM1"].identification, face=rig.layout.face)
    space, _ = parameter_space(rig, batch.datasheet, data, StepResponseModel(data, rig).shift_bound)
    kinds = {p.name: p.kind for p in space.priors}
    assert kinds["lead_share"] == "uniform" and kinds["g_sink"] == "reciprocal" and kinds["c_sink"] == "lognormal"
    assert kinds["leak"] == "reciprocal"  # the load's only way out: a series path, not a shunt


def test_bench_writes_the_rigs_columns_and_rig_entry(heatsink_batch):
    out, truth = heatsink_batch
    assert (out / "TEM1" / "identification.csv").read_text().splitlines()[0] == (
        "time_s,current_A,voltage_V,T_hot_C,T_cold_C,T_load_C,T_amb_C"
    )
    assert '[rig]\npreset = "heatsink-al"' in (out / "batch.toml").read_text()
    batch = load_batch(out)
    exp = batch.modules["TEM2"].identification
    assert exp.boundary_names == ("T_amb_C",) and batch.layout.face == ("T_hot_C", "T_cold_C")
    # the module's mounting drawn per module, the rig's own values once for the batch
    a, b = (truth["modules"][m]["rig_bench"] for m in ("TEM1", "TEM2"))
    assert a["g_sink"] == b["g_sink"] and a["c_sink"] == b["c_sink"]
    assert a["g_paste"] != b["g_paste"] and a["c_plate"] != b["c_plate"]
    p = {q.name: q for q in shipped_rig("heatsink-al").parameters}
    assert all(p[k].low <= v <= p[k].high for k, v in a.items() if k in p)
    # heating the hot side: the sink side's sensor warms above the room, the load cools below it
    i = np.argmax(exp.current)
    assert exp.channel("T_hot_C")[i] > exp.channel("T_amb_C")[i] > exp.channel("T_cold_C")[i]


def test_bench_copies_a_rig_file_into_the_batch(tmp_path):
    rig_file = tmp_path / "mine.toml"
    rig_file.write_text(shipped_rig("liquid-plates").path.read_text())
    out = tmp_path / "batch"
    config = BenchConfig(n_modules=1, seed=1, n_validations=0, hold=60.0, rig={"file": str(rig_file)}, physics="paper")
    simulate_batch(out, config, progress=lambda msg: None)
    assert (out / "rig.toml").read_text() == rig_file.read_text()
    assert '[rig]\nfile = "rig.toml"' in (out / "batch.toml").read_text()
    batch = load_batch(out)
    exp = batch.modules["TEM1"].identification
    assert exp.boundary_names == ("T_hot_liquid_C", "T_cold_liquid_C", "T_amb_C")
    # a run records the rig file's digest with the batch's inputs
    from tembayes.data.digest import batch_inputs, file_sha256

    assert batch_inputs(batch)["rig.toml"] == file_sha256(rig_file)


def test_the_out_of_model_benchs_sensor_bodies_replace_a_rig_files_own_response_times():
    """reference-faces' T2 and T3 lag by their own times in the rig file; on the out-of-model bench the
    bodies (their heat capacity behind a contact) respond instead, and the times are neither drawn nor used."""
    bench = outside_bench_rig(bench_rig(rig_file_of({"preset": "reference-faces"})))
    assert not bench.lags and not {"tau_T2", "tau_T3"} & set(bench.parameter_names)
    assert bench_rig(rig_file_of({"preset": "reference-faces"})).lag_parameters == {"tau_T2", "tau_T3"}


def test_the_out_of_model_benchs_sensors_read_through_bodies_and_leads():
    """A sensor body behind its contact reads its node pulled towards the room through the leads by
    g_lead / (g_sensor + g_lead) of their difference at steady state (the heat-sink rig at 1 A).

    Compared with the node without leads: the leads' heat (at most 0.4 mW/K of difference here) also
    moves the node itself, through its own links of 0.05 W/K and more, by up to a few per cent of
    the reading's shift; hence 15 %."""
    rig = outside_bench_rig(bench_rig(rig_file_of({"preset": "heatsink-al"})))
    assert {c: rig.sensors[c] for c in ("T_hot_C", "T_load_C")} == {
        "T_hot_C": "sensor_T_hot_C",
        "T_load_C": "sensor_T_load_C",
    }
    t = np.linspace(0.0, 30000.0, 301)
    room = np.full((1, len(t)), 295.0)
    values = {**PAPER, "g_sensor": 0.01, "g_lead": 1e-4}
    led = simulate(Inputs(t, np.ones_like(t), room), values, rig=rig, steady_start=False)
    bare = simulate(Inputs(t, np.ones_like(t), room), {**values, "g_lead": 1e-12}, rig=rig, steady_start=False)
    for k in range(len(rig.sensors)):
        node, read = bare.sensors[0, k, -1], led.sensors[0, k, -1]
        assert abs(node - 295.0) > 2.0  # the current moved it well away from the room
        assert read - node == pytest.approx(1e-4 / 0.0101 * (295.0 - node), rel=0.15), k


def test_a_rig_files_lead_share_reads_as_a_sensor_body_with_leads_does():
    """A sensor whose rig-file entry has ``lead = "lead_share"`` reads its node plus the share of the room's
    difference, exactly; the out-of-model bench's sensor body behind a contact, with leads of
    g_lead / (g_sensor + g_lead) = the same share, reads within 15 % of that shift (see above).  Two
    constructions of one physics: the share the calibration samples is the bodies' conductance ratio."""
    file = rig_file_of({"preset": "heatsink-al"})
    model = file.build(leg_cells=2, split=3, layers=True)
    assert set(model.leads) == set(model.sensors)
    t = np.linspace(0.0, 30000.0, 301)
    room = np.full((1, len(t)), 295.0)
    share = 0.01
    inputs = Inputs(t, np.ones_like(t), room)
    bare = simulate(inputs, {**PAPER, "lead_share": 1e-12}, rig=model)
    led = simulate(inputs, {**PAPER, "lead_share": share}, rig=model)
    node = bare.sensors[0, :, -1]
    assert np.all(np.abs(node - 295.0) > 2.0)
    np.testing.assert_allclose(led.sensors[0, :, -1] - node, share * (295.0 - node), rtol=1e-6)
    bench = outside_bench_rig(bench_rig(file))
    assert "lead_share" not in bench.parameter_names and not bench.leads  # the bodies' own leads replace it
    g_sensor = 0.01
    values = {**PAPER, "g_sensor": g_sensor, "g_lead": share * g_sensor / (1.0 - share)}
    body = simulate(inputs, values, rig=bench, steady_start=False)
    body_bare = simulate(inputs, {**values, "g_lead": 1e-12}, rig=bench, steady_start=False)
    shift = body.sensors[0, :, -1] - body_bare.sensors[0, :, -1]
    np.testing.assert_allclose(shift, share * (295.0 - body_bare.sensors[0, :, -1]), rtol=0.15)


def test_the_linear_model_reads_the_room_through_the_sensors_leads():
    """With leads the sensors' outputs take the room's share directly (D), the nodes' the rest (C):
    the linear model's output equals the simulator's at the operating point and after a step of the
    room, where the instant jump is D alone."""
    from scipy.linalg import expm

    from tembayes.export.linearise import linearise

    rig = shipped_rig("heatsink-al").build(leg_cells=2, split=3, layers=True)
    share = 0.008
    params = {**PAPER, "lead_share": share}
    lm = linearise(params, rig, 30.0, 1.0, room_C=22.0)
    room = 1 + rig.layout.room_index
    assert lm.D[:3, room].tolist() == pytest.approx([share] * 3)
    t = np.arange(0.0, 601.0, 1.0)
    dT = 0.5
    u = np.ones_like(t)
    sim = simulate(Inputs(t, lm.u0[0] * u, (lm.u0[1:, None] + dT) * u), params, rig=rig, y0=lm.x0, steady_start=False)
    still = simulate(Inputs(t, lm.u0[0] * u, lm.u0[1:, None] * u), params, rig=rig, y0=lm.x0, steady_start=False)
    np.testing.assert_allclose(still.sensors[0, :, 0], lm.y0[:3], atol=1e-9)
    Ainv_B = np.linalg.solve(lm.A, lm.B[:, room] * dT)
    for k in (0, 60, 600):
        x = expm(lm.A * t[k]) @ Ainv_B - Ainv_B
        y_lin = lm.C[:3] @ x + lm.D[:3, room] * dT
        np.testing.assert_allclose(sim.sensors[0, :, k] - lm.y0[:3], y_lin, atol=2e-4 * dT + 1e-9)
    assert sim.sensors[0, 0, 0] - lm.y0[0] == pytest.approx(share * dT, rel=1e-6)  # the jump is the leads'


def test_out_of_model_bench_on_another_rig_draws_its_extras_and_remounts(tmp_path):
    """Also: holds shorter than the rig's slowest time constant (120 s against 193 s) load; the
    maximum-principle check once read a hold still relaxing towards the room as 'settled'."""
    config = BenchConfig(
        n_modules=2, seed=2, n_validations=0, hold=120.0, fidelity="high", rig={"preset": "heatsink-al"}
    )
    truth = simulate_batch(tmp_path / "b", config, progress=lambda msg: None)
    assert truth["generator"]["bench_rig"].endswith("-outside")
    one, two = (truth["modules"][m]["rig_bench"] for m in ("TEM1", "TEM2"))
    for k in ("c_sensor", "g_sensor", "g_lead", "leak_module"):
        assert k in one
    assert one["c_sensor"] == two["c_sensor"] and one["g_lead"] == two["g_lead"]  # one rig's sensors
    assert one["g_sink"] != two["g_sink"] and abs(np.log(one["g_sink"] / two["g_sink"])) < 0.2  # re-mounted
    assert one["leak_module"] != two["leak_module"]  # the module's own
    assert "sensor_tau_s" not in truth["bench_layout"]["physics"]  # the bodies lag instead
    assert load_batch(tmp_path / "b").layout.sensors == ("T_hot_C", "T_cold_C", "T_load_C")


def test_swapped_sensors_on_a_heat_path_are_refused_by_name(heatsink_batch, tmp_path):
    """The load and the cold-plate thermocouple swapped: the path T_amb -> T_load -> T_cold runs backwards."""
    import shutil

    from tembayes.data import write_experiment_csv
    from tembayes.data.write import experiment_from_arrays

    out, _ = heatsink_batch
    copy = tmp_path / "swapped"
    shutil.copytree(out, copy)
    exp = load_batch(out).modules["TEM1"].identification
    swapped = experiment_from_arrays(
        exp.time,
        exp.current,
        exp.voltage,
        exp.sensors[[0, 2, 1]],
        exp.boundaries,
        sensor_names=exp.sensor_names,
        boundary_names=exp.boundary_names,
    )
    write_experiment_csv(copy / "TEM1" / "identification.csv", swapped)
    with pytest.raises(DataError, match="T_amb_C -> T_load_C -> T_cold_C is not the order of the heat path") as err:
        load_batch(copy)
    assert "identification.csv" in str(err.value)


def test_step_data_reads_the_face_sensors(heatsink_batch):
    from tembayes.calibrate.stepdata import step_data

    out, _ = heatsink_batch
    batch = load_batch(out)
    exp = batch.modules["TEM1"].identification
    data = step_data(exp, face=batch.layout.face)
    i = np.searchsorted(exp.time, data.time[5])
    assert data.obs[1, 5] == pytest.approx(exp.channel("T_hot_C")[i] - exp.channel("T_cold_C")[i])
    assert data.boundaries(data.time[:3]).shape == (1, 3)
    assert abs(data.boundaries([exp.time[0]])[0, 0] - (22.0 + KELVIN)) < 1.5


def test_a_fast_rigs_time_unit_check_scales_with_its_time_constant(tmp_path):
    """Liquid-cooled plates settle in seconds: accepted in seconds (the batch loads), refused in minutes."""
    from tembayes.data.preflight import ERROR, check_experiment
    from tembayes.data.write import experiment_from_arrays

    out = tmp_path / "batch"
    simulate_batch(
        out, BenchConfig(n_modules=1, seed=2, n_validations=0, rig={"preset": "liquid-plates"}),
        progress=lambda msg: None,
    )  # fmt: skip
    batch = load_batch(out)
    exp = batch.modules["TEM1"].identification
    assert batch.layout.slowest_tau_s < 10.0
    minutes = experiment_from_arrays(
        exp.time / 60.0, exp.current, exp.voltage, exp.sensors, exp.boundaries,
        sensor_names=exp.sensor_names, boundary_names=exp.boundary_names,
    )  # fmt: skip
    found = [f for f in check_experiment(minutes, layout=batch.layout) if f.severity == ERROR]
    assert found and found[0].column == "time_s" and "minutes or hours" in found[0].problem
    assert "this rig settles in about" in found[0].problem


def test_gap_suspects_follow_the_parameters_roles():
    """The reference rig's table is the one its parameters always had; on the heat-sink rig the sink's fins
    are its main path, not a leak, and the paste both faces share is a contact of no one side."""
    from tembayes.gap.conflicts import parameter_roles, suspect_start, suspect_table

    assert suspect_table(rig_from_config(None, 2, 3, layers=True)) == {
        ("leak_top", "high"): ("ambient_leak",),
        ("leak_bottom", "high"): ("ambient_leak",),
        ("c_plate_hot", "high"): ("sensor_lag", "contact_resistance"),
        ("c_plate_cold", "high"): ("sensor_lag", "contact_resistance"),
        ("g_paste_hot", "low"): ("contact_resistance",),
        ("g_paste_cold", "low"): ("contact_resistance",),
    }
    rig = shipped_rig("heatsink-al").build(layers=True)
    roles = parameter_roles(rig)
    assert "g_sink" not in roles and roles["leak"] == ("leak", None) and roles["g_paste"] == ("contact", None)
    row = {"parameter": "g_paste", "conflict": True, "median": 10.0, "low": 15.0, "high": 60.0}
    start = suspect_start("contact_resistance", [row], rig)
    assert start["contact_R_hot_K_per_W"] == start["contact_R_cold_K_per_W"] == pytest.approx(1 / 10 - 1 / 15)


def test_an_extra_leak_goes_where_the_rig_leaks_not_through_the_heat_sink():
    from tembayes.physics.simulate import build

    rig = shipped_rig("heatsink-al").build()
    base = build(PAPER, rig)["network"].Gb[0, :, 0]
    more = build({**PAPER, "extra_leak_W_per_K": 0.1}, rig)["network"].Gb[0, :, 0]
    i = rig.node_names.index
    # the cold side's room leak: the load block's and the cold plate rim's share of it, in their proportion
    share = rig.parameter("face_share").nominal
    assert more[i("load")] - base[i("load")] == pytest.approx(0.1 * (1 - share))
    assert more[i("cold_plate")] - base[i("cold_plate")] == pytest.approx(0.1 * share)
    assert more[i("sink")] == base[i("sink")]


def test_inputs_and_the_step_model_read_boundaries_by_name():
    """An experiment whose boundary columns come in another order than the rig's: the inputs follow the rig,
    and the step model refuses data cut in the other order rather than mixing them up."""
    from tembayes.calibrate.model import StepResponseModel
    from tembayes.data.write import experiment_from_arrays

    rig = shipped_rig("liquid-plates").build()
    t = np.arange(0.0, 5.0)
    cols = ("T_amb_C", "T_cold_liquid_C", "T_hot_liquid_C")
    b = np.array([np.full(5, 295.0), np.full(5, 290.0), np.full(5, 300.0)])
    exp = experiment_from_arrays(
        t, np.zeros(5), np.zeros(5), np.full((2, 5), 295.0), b,
        sensor_names=("T_hot_C", "T_cold_C"), boundary_names=cols,
    )  # fmt: skip
    np.testing.assert_array_equal(Inputs.from_experiment(exp, rig).boundaries[:, 0], [300.0, 290.0, 295.0])

    class Data:  # what the step model reads of StepData before anything else
        boundary_names = cols
        source = "x.csv"

    with pytest.raises(ModelError, match="T_hot_liquid_C, T_cold_liquid_C, T_amb_C in this order"):
        StepResponseModel(Data, rig)


def test_identify_on_a_rig_with_three_sensors(heatsink_batch):
    """The step method and the rig fit on the heat-sink rig: its fit parameters, the laws near the truth."""
    from tembayes.identify.pipeline import identify_module

    out, truth = heatsink_batch
    batch = load_batch(out)
    res = identify_module(batch.modules["TEM1"], batch.datasheet, rig_config=batch.rig_config)
    assert set(res.rig_fit.values) == {"K_W_per_K", "g_sink", "c_sink", "g_paste", "leak", "c_plate"}
    t = truth["modules"]["TEM1"]
    # the bench's layered plates and finer legs against the lumped step method: within a few per cent
    for k in ("R0_ohm", "S0_V_per_K"):
        assert res.fit[k] == pytest.approx(t[k], rel=0.05), k


@pytest.fixture(scope="module")
def flat_plates_batch(tmp_path_factory):
    """Liquid plates held at one temperature through the reference staircase (no plate steps)."""
    out = tmp_path_factory.mktemp("flat") / "batch"
    config = BenchConfig(n_modules=1, seed=3, n_validations=0, hold=300.0, rig={"preset": "liquid-plates"})
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(bench_module, "identification_run", lambda rig, imax, hold: identification_staircase(imax, hold))
        simulate_batch(out, config, progress=lambda msg: None)
    return out


def test_identify_refuses_a_run_whose_temperature_the_boundaries_hold(flat_plates_batch):
    """Liquid plates at one temperature: the reference staircase moves the mean junction temperature by
    tenths of a kelvin, too little for the laws' slopes; identify says so instead of fitting a line."""
    from tembayes.identify.pipeline import identify_module

    batch = load_batch(flat_plates_batch)
    with pytest.raises(DataError, match=r"spans only 0\.\d+ K") as err:
        identify_module(batch.modules["TEM1"], batch.datasheet, rig_config=batch.rig_config)
    assert "identification.csv" in str(err.value) and "step the boundaries' temperature" in str(err.value)


def test_calibrate_refuses_a_flat_mean_temperature_and_writes_nothing(flat_plates_batch, tmp_path, capsys):
    """On a flat T-bar the slopes were confidently wrong (S1 18 times the truth, 50 sd): refused, by name."""
    from tembayes.cli import main

    assert main(["calibrate", str(flat_plates_batch), "--out", str(tmp_path / "run"), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert "identification.csv" in err and "spans only 0." in err and "calibrate refuses the run" in err
    assert not (tmp_path / "run").exists()


@pytest.fixture(scope="module")
def plates_batch(tmp_path_factory):
    out = tmp_path_factory.mktemp("plates") / "batch"
    config = BenchConfig(n_modules=1, seed=3, n_validations=0, rig={"preset": "liquid-plates"})
    return out, simulate_batch(out, config, progress=lambda msg: None)


def test_plate_staircase_moves_the_plates_at_rest_and_approaches_each_setpoint():
    """Three staircases of 13 holds; the setpoint changes only at the start of a 0 A hold that follows
    a 0 A hold, and the liquid approaches it as a first-order circulator (1 - 1/e after one tau)."""
    from tembayes.bench.protocols import CIRCULATOR_TAU_S, plate_staircase

    p = plate_staircase(6.4, hold=600.0, setpoints_C=(15.0, 35.0, 55.0))
    assert len(p.levels) == 39 and p.duration == 39 * 600.0
    changes = np.flatnonzero(np.diff(p.setpoints)) + 1
    assert list(changes) == [13, 26]
    for k in changes:
        assert p.levels[k - 1] == 0.0 and p.levels[k] == 0.0
    start = p.step_times[changes[0] - 1]
    t = np.array([start - 1.0, start, start + CIRCULATOR_TAU_S, start + 600.0])
    sp = p.setpoint(t) - KELVIN
    assert sp[0] == pytest.approx(15.0) and sp[1] == pytest.approx(15.0)
    assert sp[2] == pytest.approx(15.0 + 20.0 * (1.0 - np.exp(-1.0)))
    assert sp[3] == pytest.approx(35.0, abs=0.03)  # 20 K e^(-600/90) = 0.025 K left after a hold
    assert p.setpoint(np.array([0.0, 7000.0])) == pytest.approx(15.0 + KELVIN)  # flat within a staircase


def test_the_bench_steps_plates_that_hold_both_faces(plates_batch):
    """On liquid plates the identification run repeats the staircase at each plate temperature, so the
    mean temperature at the faces spans about the setpoints' range (40 K) rather than tenths of a kelvin."""
    out, truth = plates_batch
    exp = load_batch(out).modules["TEM1"].identification
    tavg = 0.5 * (exp.channel("T_hot_C") + exp.channel("T_cold_C")) - KELVIN
    setpoints = truth["generator"]["plate_setpoints_C"]
    assert np.percentile(tavg, 99) - np.percentile(tavg, 1) > 0.9 * (max(setpoints) - min(setpoints))
    assert setpoints == [15.0, 35.0, 55.0]
    for column in ("T_hot_liquid_C", "T_cold_liquid_C"):
        liquid = exp.channel(column) - KELVIN
        for sp in setpoints:  # each held, within the loop's offset and wobble, for most of a staircase
            assert np.mean(np.abs(liquid - sp) < 0.5) > 0.3, (column, sp)


def test_calibration_on_stepped_plates_finds_the_slopes(plates_batch):
    """With the plates stepped, the laws come out near the truth: the intercepts within 1 %, the slopes
    within 5 % (posterior sds about 0.2 %, 0.3 %, 0.3 % and 1.3 %; on the flat run S1 came out 18 times
    too large)."""
    from tembayes.calibrate.module import CalibrationOptions, calibrate_module

    out, truth = plates_batch
    batch = load_batch(out)
    options = CalibrationOptions(max_steps=2000, pilot=500, max_relinearise=1, psis_draws=100)
    res = calibrate_module(batch.modules["TEM1"], batch.datasheet, rig_config=batch.rig_config, seed=0, options=options)
    t = truth["modules"]["TEM1"]
    for k, rel in {"R0_ohm": 0.01, "S0_V_per_K": 0.01, "R1_ohm_per_K": 0.05, "S1_V_per_K2": 0.05}.items():
        assert np.mean(res.draws[k]) == pytest.approx(t[k], rel=rel), k


def test_a_held_rig_parameter_is_anchored_not_carried_as_a_given_draw(heatsink_batch, tmp_path):
    """A rig file's held parameter (here a face leak, which the carry-over spreads over its whole range)
    joins the anchoring's updated parameters, as the held depths do; the module's own held ``g_ceramic``
    does not.  As a given draw its spread reached the unpinned heat capacities through the update's
    linear correction: on a heatsink-al module out-of-model it moved ``c_legs`` to 4.7e7 J/K."""
    from tembayes.calibrate.module import CalibrationOptions, calibration_rig
    from tembayes.predict.anchor import held_draws
    from tembayes.predict.predictive import posterior_draws
    from tembayes.predict.runmodel import RunModel

    text = (
        resources.files("tembayes")
        .joinpath("rigs", "heatsink-al.toml")
        .read_text()
        .replace(
            "[boundaries]",
            'leak_face = {nominal = 0.004, low = 0.001, high = 0.01, unit = "W/K", doc = "a face to the room", '
            "held = true}\n\n[boundaries]",
        )
    )
    text += "".join(f'\n[[links]]\na = "{f}_plate"\nb = "ambient"\ng = "leak_face"\n' for f in ("hot", "cold"))
    (tmp_path / "rig.toml").write_text(text)
    rig = calibration_rig({"file": str(tmp_path / "rig.toml")}, CalibrationOptions(model="full"))
    out, truth = heatsink_batch
    t = {**truth["modules"]["TEM1"], **truth["modules"]["TEM1"]["rig"]}
    exp = load_batch(out).modules["TEM1"].identification
    rng = np.random.default_rng(4)
    n = 96
    raw = {k: t[k] * (1.0 + 1e-4 * rng.standard_normal(n)) for k in (*PAPER, *rig.parameter_names) if k in t}
    # the carry-over's draws: the face leak over its range, the load's leak moved against it (linear in the log)
    d = rig.parameter("leak_face").spread_sd * rng.standard_normal(n)
    raw["leak_face"] = 0.004 * np.exp(d)
    raw["leak"] = t["leak"] - 2 * 0.004 * d
    raw["step_shift_s"] = np.full(n, RunModel(exp, rig).fit_phase({k: v[0] for k, v in raw.items()}))
    held = held_draws(rig, raw, {}, "TEM1")
    assert set(held) == {"leak_face"} and np.array_equal(held["leak_face"], raw["leak_face"])
    assert rig.parameter("g_ceramic").held
    a = posterior_draws(raw, {}, "TEM1", exp, rig)
    assert a.anchor["TEM1"]["updated"] == ["leak_face"] and "leak_face" in a.anchor["TEM1"]["posterior_sd"]


def test_a_rig_whose_sensors_have_their_own_response_times_samples_those_and_not_the_common_one(batch3):
    """reference-faces: T2's and T3's response times sampled flat over their documented range, kept inside it
    by the carry-over, and no common ``sensor_tau_s``; the reference rig keeps the common one."""
    from tembayes.calibrate.model import StepResponseModel
    from tembayes.calibrate.module import CalibrationOptions, calibration_rig, flat_coordinates, parameter_space
    from tembayes.calibrate.stepdata import step_data

    ident = load_batch(batch3).modules["TEM1"].identification  # the reference rig's columns hold T2 and T3
    names = {}
    for preset in ("reference-faces", "reference"):
        rig = calibration_rig({"preset": preset}, CalibrationOptions())
        data = step_data(ident, face=rig.layout.face)
        space = parameter_space(rig, load_batch(batch3).datasheet, data, StepResponseModel(data, rig).shift_bound)[0]
        names[preset] = {p.name: p for p in space.priors}
        if preset == "reference-faces":
            flat = flat_coordinates(space, rig)
            for tau in ("tau_T2", "tau_T3"):
                p = names[preset][tau]
                assert p.kind == "uniform" and (p.center - p.scale, p.center + p.scale) == pytest.approx((0.1, 3.0))
                assert flat[space.index(tau)] == pytest.approx((0.1, 3.0))
    assert "sensor_tau_s" not in names["reference-faces"]
    assert "sensor_tau_s" in names["reference"] and not {"tau_T2", "tau_T3"} & set(names["reference"])
