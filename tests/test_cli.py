"""The ``tembayes`` command end to end, through ``main(argv)``."""

import hashlib
import json

import pytest

from tembayes.cli import build_parser, main
from tembayes.data import load_batch

SHORT = ["--modules", "2", "--hold", "60", "--rate", "0.5", "--validation-hours", "0.2"]


def _tree_digest(folder):
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(p.relative_to(folder).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "b"
    assert main(["simulate", str(out), *SHORT, "--outlier", "TEM2", "--effect", "sensor_lag=5", "--seed", "7"]) == 0
    return out


def test_simulate_writes_a_batch_the_loader_reads(batch):
    b = load_batch(batch)
    assert list(b.modules) == ["TEM1", "TEM2"]
    assert all(len(m.validations) == 1 for m in b.modules.values())
    truth = json.loads((batch / "truth.json").read_text())
    assert truth["outlier"] == "TEM2" and truth["modules"]["TEM2"]["outlier"] is True
    assert truth["effects"] == {"sensor_lag": {"sensor_tau_s": 5.0}}
    assert truth["generator"]["seed"] == 7


def test_simulate_is_reproducible_by_seed(batch, tmp_path):
    again = tmp_path / "again"
    assert main(["simulate", str(again), *SHORT, "--outlier", "TEM2", "--effect", "sensor_lag=5", "--seed", "7"]) == 0
    assert _tree_digest(again) == _tree_digest(batch)
    other = tmp_path / "other"
    assert main(["simulate", str(other), *SHORT, "--outlier", "TEM2", "--effect", "sensor_lag=5", "--seed", "8"]) == 0
    assert _tree_digest(other) != _tree_digest(batch)


def test_simulate_refuses_existing_output_and_writes_nothing(batch, capsys):
    before = _tree_digest(batch)
    assert main(["simulate", str(batch), *SHORT]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tembayes: error:") and str(batch) in err and err.count("\n") == 1
    assert _tree_digest(batch) == before


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--effect", "no_such_effect"], "the catalogue has: k_temperature"),
        (["--effect", "sensor_lag=fast"], "VALUE must be a number"),
        (["--outlier", "TEM9"], "TEM9"),
        (["--rate", "500"], "rate"),
    ],
)
def test_simulate_bad_requests_fail_with_one_line(tmp_path, capsys, extra, needle):
    out = tmp_path / "never"
    assert main(["simulate", str(out), *SHORT, *extra]) == 2
    err = capsys.readouterr().err
    assert needle in err and err.count("\n") == 1
    assert not out.exists()
    assert not list(tmp_path.iterdir())  # no temporary folder left behind either


def test_simulate_other_datasheet(tmp_path):
    ds = tmp_path / "type.toml"
    ds.write_text(
        '[module_type]\nname = "SMALL-03"\nth_C = 27.0\nimax_A = 3.0\nvmax_V = 8.6\ndtmax_K = 68.0\nqmax_W = 15.0\n'
    )
    out = tmp_path / "small"
    assert main(["simulate", str(out), *SHORT, "--datasheet", str(ds)]) == 0
    b = load_batch(out)
    assert b.datasheet.name == "SMALL-03"
    truth = json.loads((out / "truth.json").read_text())
    # the truth is drawn around this type's datasheet values, not TEC1-12706's
    r0 = truth["population"]["R0_ohm"]
    assert abs(r0 / b.datasheet.resistance() - 1) < 0.2
    # the staircase scales with Imax: 1.6 A * 3.0 / 6.4 = 0.75 A at the bottom
    i = b.modules["TEM1"].identification.current
    assert -0.80 < i.min() < -0.70


def test_inspect_prints_quality_and_json(batch, capsys):
    assert main(["inspect", str(batch)]) == 0
    out = capsys.readouterr().out
    assert "TEM1" in out and "identification.csv" in out and "noise T3" in out
    assert main(["inspect", str(batch), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    q = report["modules"]["TEM1"]["identification.csv"]
    assert q["n_samples"] > 100
    # 4 mK sensor noise on the bench, estimated from the data
    assert 0.002 < q["T3_C_noise"] < 0.008


def test_inspect_refuses_bad_batch_with_one_line(tmp_path, capsys):
    (tmp_path / "b").mkdir()
    assert main(["inspect", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert "batch.toml" in err and err.count("\n") == 1


def _commands():
    import argparse

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return list(sub.choices)


@pytest.mark.parametrize("command", _commands())
def test_every_command_has_help_with_an_example(command, capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args([command, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "example" in out and f"tembayes {command} " in out


def test_identify_refuses_negative_leg_cells(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["identify", str(tmp_path), "--out", str(out), "--leg-cells", "-1"]) == 2
    assert "leg_cells" in capsys.readouterr().err and not out.exists()
