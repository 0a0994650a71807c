"""Rig files: the shipped reference rig builds the steel it describes; malformed files are refused by key."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tembayes.bench.hifi import AREA, K_STEEL, RHO_C, SENSOR_DEPTH
from tembayes.data import load_batch_toml
from tembayes.errors import DataError, ModelError
from tembayes.physics.rigread import SHIPPED, read_rig_file, rig_from_config, shipped_rig
from tembayes.physics.rigsummary import summarise_rig

REFERENCE_TOML = shipped_rig("reference").path.read_text()


def _chain_positions(rig, net, cells):
    """Cell centres [m] from the block's first face, from the conductances (k A / d)."""
    g_face = net.Gb[0, net.index(cells[0]), 0]  # water face: cooler and half cell in series
    nom = rig.nominal()
    r_half = 1.0 / g_face - 1.0 / nom["g_cooler"]
    x = [r_half * K_STEEL * AREA]
    for a, b in zip(cells[:-1], cells[1:]):
        x.append(x[-1] + K_STEEL * AREA / net.G[0, net.index(a), net.index(b)])
    return np.array(x)


@pytest.mark.parametrize("split", [1, 3, 5])
def test_reference_file_is_the_steel_it_describes(split):
    rig = rig_from_config(None, 0, split)
    net = rig.network()
    top = [n for n in rig.node_names if n.startswith("top_")]
    assert len(top) == 2 * split
    # rho c V of the whole 10 mm block, and cells evenly spaced from face to face
    assert net.C[0, [net.index(n) for n in top]].sum() == pytest.approx(RHO_C * AREA * 0.010, rel=1e-12)
    x = _chain_positions(rig, net, top)
    assert np.diff(x) == pytest.approx(np.full(len(top) - 1, 0.010 / len(top)), rel=1e-12)
    assert x[0] == pytest.approx(0.5 * 0.010 / len(top), rel=1e-12)
    # T1 and T2 read cell centres 2.5 mm from their faces
    assert x[top.index(rig.sensors["T1_C"])] == pytest.approx(SENSOR_DEPTH, rel=1e-12)
    assert 0.010 - x[top.index(rig.sensors["T2_C"])] == pytest.approx(SENSOR_DEPTH, rel=1e-12)
    # all leaks together: the enclosure's top and bottom leaks, whatever the split
    nom = rig.nominal()
    assert net.Gb[0, :, 1].sum() == pytest.approx(nom["leak_top"] + nom["leak_bottom"], rel=1e-12)
    # the tabs' share leaves at the bottom face, whole
    last = rig.node_names.index(f"bottom_{2 * split}" if split > 1 else "bottom_lower")
    side = 0.5 * nom["leak_bottom"] * (1 - nom["tab_share"]) / split
    assert net.Gb[0, last, 1] == pytest.approx(side + nom["leak_bottom"] * nom["tab_share"], rel=1e-12)


def test_sensor_depth_moves_the_reading_by_the_cell_spacing():
    rig = rig_from_config(None, 0, 3)
    a, b, f = rig.readout(["T1_C", "T2_C"], {"depth_T1": SENSOR_DEPTH + 0.010 / 6, "depth_T2": SENSOR_DEPTH})
    # one cell spacing deeper reads the next cell inward; at nominal depth the node itself
    assert f[0].tolist() == pytest.approx([1.0, 0.0])
    assert rig.node_names[b[0]] == "top_3" and rig.node_names[a[0]] == "top_2"


def _write(tmp_path, text, name="rig.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


BAD = [
    ('hot = "hot_plate"', 'hot = "hot_plat"', "module.hot", "hot_plat"),
    ('g = "0.5*leak_top"', 'g = "0.5*leak_tpo"', "links[4].g", "leak_tpo"),
    ('a = "water"\nb = "top_upper"', 'a = "water"\nb = "top_uper"', "links[1].b", "top_uper"),
    ("g_cooler = {nominal = 12.5", "g_cooler = {nominal = -12.5", "parameters.g_cooler.nominal", "positive"),
    ("g_cooler = {nominal = 12.5", "g_cooler = {nominal = 17.5", "parameters.g_cooler", "inside its range"),
    ('T4_C = {node = "bottom_lower"', 'T4_C_x = {node = "bottom_lower"', "sensors.T4_C_x", "_C"),
    ("[module]", "[modul]", "modul", "did you mean 'module'"),
    ("spread = false", "sprad = false", "links[8].sprad", "spread"),
    (
        'T1_C = {node = "top_upper", depth = "depth_T1", toward = "top_lower"',
        'T1_C = {node = "top_upper", depth = "depth_T1", toward = "bottom_lower"',
        "sensors.T1_C.toward",
        "neighbouring cell",
    ),
    # a negative coefficient that makes a leak negative inside the parameters' ranges
    (
        '"0.5*leak_bottom + -0.5*leak_bottom*tab_share"',
        '"0.5*leak_bottom + -0.6*leak_bottom*tab_share"',
        "links",
        "not positive",
    ),
    # a node named like the cells tembayes makes when it cuts a block finer
    ("[blocks.top]", 'top_2 = "c_plate_hot"\n\n[blocks.top]', "nodes.top_2", "tembayes gives a new node"),
    ('top_upper = "c_half_block"', 'top_upper = ["c_half_block", "c_half_block"]', "nodes.top_upper", "only a link's"),
    ('g = "0.5*leak_top"', 'g = "nan*leak_top"', "links[4].g", "not a finite number"),
    ('hot = "hot_plate"', 'hot = "top_lower"', "module.hot", "a cell of a block"),
    ('a = "top_upper"\nb = "ambient"', 'a = "top_upper"\nb = "bottom_upper"', "links[4]", "joins two block cells"),
    (
        'cells = ["bottom_upper", "bottom_lower"]',
        'cells = ["bottom_upper", "top_lower"]',
        "blocks.bottom.cells",
        "is a cell of blocks",
    ),
    # a sensor without its depth: its depth parameter goes too (it would be unused)
    (
        'T4_C = {node = "bottom_lower", depth = "depth_T4", ',
        'T4_C = {node = "bottom_lower", ',
        "sensors.T4_C.centre",
        "without a depth",
        ("depth_T4 = {", "# depth_T4 = {"),
    ),
]


@pytest.mark.parametrize(
    "old, new, key, words, also", [(*b, None) if len(b) == 4 else b for b in BAD], ids=[b[2] for b in BAD]
)
def test_malformed_rig_file_names_the_key(tmp_path, old, new, key, words, also):
    assert old in REFERENCE_TOML
    text = REFERENCE_TOML.replace(old, new, 1)
    if also:  # a second edit the first one needs
        text = text.replace(*also, 1)
    path = _write(tmp_path, text)
    with pytest.raises(DataError) as err:
        read_rig_file(path)
    assert err.value.column == key
    assert words in str(err.value)
    assert str(path) in str(err.value)


def test_unused_parameter_refused(tmp_path):
    text = REFERENCE_TOML.replace(
        "[boundaries]", 'g_spare = {nominal = 1.0, low = 0.5, high = 2.0, unit = "W/K"}\n\n[boundaries]'
    )
    with pytest.raises(DataError, match="never used") as err:
        read_rig_file(_write(tmp_path, text))
    assert err.value.column == "parameters.g_spare"


HEATSINK_TOML = shipped_rig("heatsink-al").path.read_text()
LEAD = 'T_hot_C = {node = "hot_plate", lead = "lead_share"}'


def test_a_lead_share_no_sensor_names_is_unused(tmp_path):
    text = HEATSINK_TOML
    for col, node in (("T_hot_C", "hot_plate"), ("T_cold_C", "cold_plate"), ("T_load_C", "load")):
        text = text.replace(f'{col} = {{node = "{node}", lead = "lead_share"}}', f'{col} = "{node}"')
    with pytest.raises(DataError, match="never used") as err:
        read_rig_file(_write(tmp_path, text))
    assert err.value.column == "parameters.lead_share"


FACES_TOML = shipped_rig("reference-faces").path.read_text()
LAG = 'spacing = 0.005, lag = "tau_T2"}'


# (rig file, its sensor entry, the entry broken, the key named, the words)
SENSOR_PARAMETER_REFUSALS = [
    (HEATSINK_TOML, LEAD, 'T_hot_C = {node = "hot_plate", lead = "lead_shar"}', "sensors.T_hot_C.lead", "unknown parameter 'lead_shar'"),
    (HEATSINK_TOML, LEAD, 'T_hot_C = {node = "hot_plate", lead = "g_paste"}', "sensors.T_hot_C.lead", "a lead's share is a fraction"),
    (HEATSINK_TOML, LEAD, 'T_hot_C = {node = "hot_plate", lead = 0.01}', "sensors.T_hot_C.lead", "must be a name in quotes"),
    (FACES_TOML, LAG, 'spacing = 0.005, lag = "tau_T"}', "sensors.T2_C.lag", "unknown parameter 'tau_T'"),
    (FACES_TOML, LAG, 'spacing = 0.005, lag = "depth_T3"}', "sensors.T2_C.lag", "a sensor's response time is in seconds"),
    (FACES_TOML, LAG, "spacing = 0.005, lag = 1.0}", "sensors.T2_C.lag", "must be a name in quotes"),
]  # fmt: skip


@pytest.mark.parametrize(
    "text, old, new, key, words", SENSOR_PARAMETER_REFUSALS, ids=[r[4] for r in SENSOR_PARAMETER_REFUSALS]
)
def test_a_sensors_lead_must_name_a_share_and_its_lag_a_time(tmp_path, text, old, new, key, words):
    assert text.count(old) == 1
    path = _write(tmp_path, text.replace(old, new))
    with pytest.raises(DataError) as err:
        read_rig_file(path)
    assert err.value.column == key
    assert words in str(err.value) and str(path) in str(err.value)


def test_a_lag_no_sensor_names_is_unused_and_a_named_one_reaches_the_rig(tmp_path):
    rig = shipped_rig("reference-faces").build()
    assert dict(rig.lags) == {"T2_C": "tau_T2", "T3_C": "tau_T3"}
    assert summarise_rig(shipped_rig("reference-faces")).to_json()["sensor_lags"] == dict(rig.lags)  # rig.json
    with pytest.raises(DataError, match="never used") as err:
        read_rig_file(_write(tmp_path, FACES_TOML.replace(LAG, "spacing = 0.005}")))
    assert err.value.column == "parameters.tau_T2"


def test_node_without_a_path_to_a_boundary_refused(tmp_path):
    # a node joined only to a second node that is joined to nothing else: no temperature is set for them
    text = REFERENCE_TOML.replace("[blocks.top]", 'island = "c_plate_hot"\nislet = "c_plate_cold"\n\n[blocks.top]')
    text += '\n[[links]]\na = "island"\nb = "islet"\ng = "g_cooler"\n'
    with pytest.raises(DataError, match="'island' has no path to a boundary") as err:
        read_rig_file(_write(tmp_path, text))
    assert err.value.column == "nodes.island"


def test_link_from_a_node_to_itself_refused(tmp_path):
    text = REFERENCE_TOML.replace('a = "top_upper"\nb = "ambient"', 'a = "top_upper"\nb = "top_upper"', 1)
    with pytest.raises(DataError, match="joins top_upper to top_upper") as err:
        read_rig_file(_write(tmp_path, text))
    assert err.value.column == "links[4]"


def test_no_sensor_on_a_side_refused(tmp_path):
    text = REFERENCE_TOML
    for s in ("T3_C", "T4_C"):
        line = next(ln for ln in text.splitlines() if ln.startswith(s))
        text = text.replace(line + "\n", "")
    text = text.replace("depth_T3 = {", "# depth_T3 = {").replace("depth_T4 = {", "# depth_T4 = {")
    with pytest.raises(DataError, match="no sensor on the module's cold side") as err:
        read_rig_file(_write(tmp_path, text))
    assert err.value.column == "sensors"


def test_batch_points_at_a_rig_file(tmp_path, data_factory):
    folder = data_factory.batch(toml=data_factory.batch_toml(rig={"file": "rig.toml", "g_cooler": 11.0}))
    _write(folder, REFERENCE_TOML.replace('name = "reference"', 'name = "my-rig"'))
    _, config = load_batch_toml(folder)
    assert config["file"] == str((folder / "rig.toml").resolve())
    rig = rig_from_config(config, 4, 3, layers=True)
    assert rig.name == "my-rig-legs4-blocks6-layers"
    assert rig.parameter("g_cooler").nominal == 11.0
    # the same network as the shipped preset with the same override
    ref = rig_from_config({"preset": "reference", "g_cooler": 11.0}, 4, 3, layers=True).network()
    assert np.array_equal(rig.network().G, ref.G)


def test_batch_refuses_preset_and_file_together(data_factory):
    folder = data_factory.batch(toml=data_factory.batch_toml(rig={"file": "rig.toml", "preset": "reference"}))
    with pytest.raises(DataError, match="both a preset and a file") as err:
        load_batch_toml(folder)
    assert err.value.column == "rig"


def test_missing_rig_file_named(data_factory):
    folder = data_factory.batch(toml=data_factory.batch_toml(rig={"file": "nowhere.toml"}))
    with pytest.raises(DataError, match="does not exist") as err:
        load_batch_toml(folder)
    assert "nowhere.toml" in str(err.value)


def test_unknown_preset_suggests_the_nearest():
    with pytest.raises(ModelError, match="did you mean 'reference'"):
        shipped_rig("referense")


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_rig_loads_and_has_its_columns(name):
    rig = shipped_rig(name)
    desc = rig.build(4, 3, layers=True)
    assert set(desc.sensors) == set(rig.sensors) and desc.boundaries == rig.boundaries
    assert np.all(desc.network().C > 0)


def test_time_constants_and_hold_match_an_integrated_step():
    """The modal hold time against the step response integrated by scipy (an independent route)."""
    from scipy.integrate import solve_ivp

    rig = shipped_rig("heatsink-al")
    s = summarise_rig(rig, module_k=0.5)
    net = rig.build().network()
    names = net.nodes
    L = -net.G[0].copy()
    np.fill_diagonal(L, net.G[0].sum(axis=1) + net.Gb[0].sum(axis=1))
    h, c = names.index(rig.hot), names.index(rig.cold)
    L[[h, c], [h, c]] += 0.5
    L[h, c] -= 0.5
    L[c, h] -= 0.5
    C = net.C[0]
    read = [names.index(sp.node) for sp in rig.sensors.values()]
    t = np.linspace(0, 3600, 36001)
    settle = []
    for q in (
        np.where(np.arange(len(names)) == h, 1.0, 0.0) - np.where(np.arange(len(names)) == c, 1.0, 0.0),
        0.5 * np.isin(np.arange(len(names)), [h, c]),
    ):  # pumped heat, Joule heat
        sol = solve_ivp(
            lambda _, T, q=q: (q - L @ T) / C, (0, 3600), np.zeros(len(names)), t_eval=t, rtol=1e-10, atol=1e-12
        )
        y = sol.y[read]
        left = np.abs(y - y[:, -1:]).max(axis=0) / np.abs(y[:, -1]).max()
        settle.append(t[np.flatnonzero(left > 0.01)[-1] + 1])
    assert s.hold_times[0.01] == pytest.approx(max(settle), rel=0.01)
    # the slowest time constant: the late decay rate of the integrated response
    k = np.searchsorted(t, 1500.0)
    rate = -np.polyfit(t[k : k + 6000], np.log(left[k : k + 6000]), 1)[0]
    assert 1.0 / rate == pytest.approx(s.time_constants[0], rel=0.02)


def test_rig_command_writes_json_and_figure(tmp_path, capsys):
    from tembayes.cli import main

    out = tmp_path / "chk"
    assert main(["rig", "heatsink-al", "--out", str(out)]) == 0
    doc = json.loads((out / "rig.json").read_text())
    assert doc["csv_columns"] == ["time_s", "current_A", "voltage_V", "T_hot_C", "T_cold_C", "T_load_C", "T_amb_C"]
    assert doc["time_constants_s"][0] == pytest.approx(summarise_rig(shipped_rig("heatsink-al")).time_constants[0])
    assert (out / "rig.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    printed = capsys.readouterr().out
    assert "g_sink" in printed and "T_load_C" in printed and "min brings every sensor within 1 %" in printed
    # a malformed file: refused, nothing written
    bad = tmp_path / "bad.toml"
    bad.write_text(REFERENCE_TOML.replace('hot = "hot_plate"', 'hot = "hot_plat"'))
    assert main(["rig", str(bad), "--out", str(tmp_path / "none")]) == 2
    assert "module.hot" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


def test_a_batch_reads_the_columns_its_rig_names(data_factory):
    """heatsink-al: T_hot_C, T_cold_C, T_load_C and T_amb_C, in any column order; the reference columns are refused."""
    from tembayes.data import load_batch

    folder = data_factory.batch(toml=data_factory.batch_toml(rig={"preset": "heatsink-al"}), validations=())
    with pytest.raises(DataError, match="'T_hot_C'") as err:
        load_batch(folder)
    assert err.value.column == "T_hot_C" and "identification.csv" in str(err.value)
    # the reference rows as the heat-sink rig's columns: T2 on the hot plate, T3 on the cold, T4 in the load
    keep = {"time_s": 0, "current_A": 1, "voltage_V": 2, "T_load_C": 6, "T_amb_C": 8, "T_cold_C": 5, "T_hot_C": 4}
    for m, mod in enumerate(("TEM1", "TEM2")):
        rows = [[r[j] for j in keep.values()] for r in data_factory.rows(seed=m)]
        data_factory.write_csv(f"batch/{mod}/identification.csv", header=list(keep), rows=rows)
    batch = load_batch(folder)
    exp = batch.modules["TEM1"].identification
    assert exp.sensor_names == ("T_hot_C", "T_cold_C", "T_load_C") and exp.boundary_names == ("T_amb_C",)
    rows = data_factory.rows(seed=0)
    assert exp.channel("T_load_C")[3] == pytest.approx(float(rows[3][6]) + 273.15)
    assert batch.layout.face == ("T_hot_C", "T_cold_C")


def test_the_boundaries_are_read_in_the_rig_files_order(data_factory):
    from tembayes.data import load_batch

    folder = data_factory.batch(toml=data_factory.batch_toml(rig={"file": "rig.toml"}), validations=())
    swapped = REFERENCE_TOML.replace(
        'water = "T_water_C"\nambient = "T_amb_C"', 'ambient = "T_amb_C"\nwater = "T_water_C"'
    )
    assert swapped != REFERENCE_TOML
    _write(folder, swapped)
    exp = load_batch(folder).modules["TEM1"].identification
    assert exp.boundary_names == ("T_amb_C", "T_water_C")
    assert exp.boundaries[0][0] == pytest.approx(float(data_factory.rows(seed=0)[0][8]) + 273.15)


def test_split_keeps_faces_and_depth_neighbours():
    rig = rig_from_config(None, 0, 3)
    nom = rig.nominal()
    net = rig.network()
    # the module-side contact: the top block's last new cell, through a third of the half cell and the paste
    g = net.G[0, net.index("top_6"), net.index("hot_plate")]
    assert g == pytest.approx(1 / (1 / (3 * nom["g_steel_quarter"]) + 1 / nom["g_paste_hot"]), rel=1e-12)
    assert np.count_nonzero(net.G[0, net.index("hot_plate")]) == 1
    # each depth reads towards the block's inside
    a, b, _ = rig.readout(["T1_C", "T2_C", "T3_C", "T4_C"])
    assert [(rig.node_names[i], rig.node_names[j]) for i, j in zip(a, b)] == [
        ("top_2", "top_3"),
        ("top_5", "top_4"),
        ("bottom_2", "bottom_3"),
        ("bottom_5", "bottom_4"),
    ]


def test_layers_put_the_alumina_outside_the_junctions():
    rig = shipped_rig("heatsink-al").build(0, 1, layers=True)
    nom = rig.nominal()
    net = rig.network()
    c = net.C[0]
    assert c[net.index("hot_ceramic")] == pytest.approx(0.8 * nom["c_plate"], rel=1e-12)
    assert c[net.index("hot_plate")] == pytest.approx(0.2 * nom["c_plate"] + 0.5 * nom["c_legs"], rel=1e-12)
    assert c[net.index("cold_ceramic")] == pytest.approx(0.8 * nom["c_plate"], rel=1e-12)
    assert c[net.index("cold_plate")] == pytest.approx(0.2 * nom["c_plate"] + 0.5 * nom["c_legs"], rel=1e-12)
    # the series is written from a to b: the alumina's half at the plate's end (the same sum, the same rounding)
    (g,) = [g for a, b, g in rig.links if a == "cold_ceramic" and b not in ("cold_plate", "ambient")]
    assert g[0] == "2.0*g_ceramic"
    # the paste meets the alumina, the alumina the junctions (half its conductance on each side)
    g = net.G[0, net.index("sink"), net.index("hot_ceramic")]
    assert g == pytest.approx(1 / (1 / nom["g_paste"] + 1 / (2 * 50.0)), rel=1e-12)
    assert net.G[0, net.index("sink"), net.index("hot_plate")] == 0.0
    # a thermocouple on a plate touches its outside
    assert rig.sensors["T_hot_C"] == "hot_ceramic" and rig.sensors["T_cold_C"] == "cold_ceramic"
    # and so does the room at the plate's rim
    assert ("cold_ceramic", "ambient", ["2.0*g_ceramic", "leak*face_share"]) in rig.links


def test_a_value_negative_only_at_a_corner_of_the_ranges_is_refused(tmp_path):
    # c_plate_hot - 0.85 c_plate_cold: 0.675 at nominal, 0.175 and 0.25 with either at its worst end
    # alone, -0.25 with both: only the corner shows it
    expr = '"c_plate_hot + -0.85*c_plate_cold"'
    text = REFERENCE_TOML.replace('g = "0.5*leak_top"', f"g = {expr}", 1)
    with pytest.raises(DataError, match="not positive somewhere") as err:
        read_rig_file(_write(tmp_path, text))
    assert "top_upper-ambient" in str(err.value)
    read_rig_file(_write(tmp_path, text.replace("-0.85*", "-0.75*")))
    # two parameters at their high ends at once: positive at nominal and with any one parameter at an end
    three = REFERENCE_TOML.replace('g = "0.5*leak_top"', 'g = "c_plate_hot + -0.65*c_plate_cold + -0.65*c_legs"', 1)
    with pytest.raises(DataError, match="not positive somewhere"):
        read_rig_file(_write(tmp_path, three))


def test_a_folder_or_binary_is_refused_as_a_rig_file(tmp_path):
    with pytest.raises(DataError, match="cannot be read"):
        read_rig_file(tmp_path)
    (tmp_path / "bin.toml").write_bytes(b"\xff\xfe\x00name")
    with pytest.raises(DataError, match="cannot be read"):
        read_rig_file(tmp_path / "bin.toml")


def test_a_node_joined_only_to_a_boundary_is_drawn(tmp_path):
    text = REFERENCE_TOML.replace("[blocks.top]", 'spare = "c_plate_hot"\n\n[blocks.top]')
    text += '\n[[links]]\na = "spare"\nb = "ambient"\ng = "leak_top"\n'
    summary = summarise_rig(read_rig_file(_write(tmp_path, text)))
    from tembayes.plots.rig import plot_rig

    fig = plot_rig(summary)
    assert any("spare" in t.get_text() for t in fig.axes[0].texts)


def test_the_held_seats_copy_differs_from_the_shipped_reference_rig_only_in_its_name_and_two_flags():
    """analyses/rigs/reference-seats-held.toml is the reference rig as it shipped with all four seats held
    (the comparison the law-coverage records use); it must not drift from the shipped file."""
    from dataclasses import replace
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    shipped = read_rig_file(root / "tembayes" / "rigs" / "reference.toml")
    held = read_rig_file(root / "analyses" / "rigs" / "reference-seats-held.toml")
    seats = {"depth_T2", "depth_T3"}
    assert held.name == "reference-seats-held"
    assert [p.name for p in held.parameters] == [p.name for p in shipped.parameters]
    assert {p.name for p in shipped.parameters if not p.held} >= seats
    assert all(p.held for p in held.parameters if p.name in seats)
    unflagged = tuple(replace(p, held=False) if p.name in seats else p for p in held.parameters)
    assert unflagged == shipped.parameters
    for field in ("description", "hot", "cold", "boundaries", "nodes", "links", "blocks", "sensors"):
        assert getattr(held, field) == getattr(shipped, field), field
