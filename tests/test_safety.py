"""Nothing a user has is lost, and what cannot be right is refused: the bad-input corpus.

Every case runs through the command line (``main(argv)``) and asserts the
one-line refusal names the file/line/key, that nothing was written, and that
the inputs are byte-identical afterwards.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil

import numpy as np
import pytest
from corpus import DATA_CASES, EXAMPLE, colliding_ids, good_batch, read_csv, write_csv

from tembayes.calibrate.runfolder import module_usable, partial_path
from tembayes.cli import main
from tembayes.data import load_batch, load_experiment
from tembayes.data.outputs import MARKER, RunLock, check_output, marker
from tembayes.errors import DataError


def tree(folder):
    """``{relative path: sha256}`` of every file under ``folder`` (hidden ones too)."""
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def listing(folder):
    return sorted(p.name for p in folder.iterdir())


def refused(capsys, argv, *needles):
    """Run ``argv``; assert exit 2 and a one-line error holding every needle; returns the message."""
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and err[-1].startswith("tembayes: error:"), err
    assert "Traceback" not in "\n".join(err)
    for needle in needles:
        assert needle in err[-1], (needle, err[-1])
    return err[-1]


# ---------------------------------------------------------------- data the rig cannot produce


@pytest.mark.parametrize("case", sorted(DATA_CASES))
def test_impossible_data_is_refused_by_every_command_and_nothing_is_written(case, tmp_path, capsys):
    build, words, where = DATA_CASES[case]
    batch = build(tmp_path, "b")
    before = tree(batch)
    for argv in (
        ["inspect", batch],
        ["identify", batch, "--out", tmp_path / "ident"],
        ["calibrate", batch, "--out", tmp_path / "run", "--workers", "1"],
    ):
        msg = refused(capsys, argv, words, where)
        assert str(batch) in msg
    assert tree(batch) == before
    assert listing(tmp_path) == ["b"]  # no output, no partial run, no lock


def test_inspect_lists_every_problem_and_the_clean_example_has_none(tmp_path, capsys):
    batch = DATA_CASES["stuck_T3_in_validation"][0](tmp_path, "b")
    assert main(["inspect", str(batch), "--json"]) == 2
    doc = json.loads(capsys.readouterr().out)
    assert [f["column"] for f in doc["findings"] if f["severity"] == "error"] == ["T3_C"]
    assert doc["findings"][0]["path"].endswith("validation.csv")
    assert main(["inspect", str(EXAMPLE)]) == 0
    assert "no problems found" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("keep", "words", "refusal"),
    [
        (lambda t, first: t < first + 1000.0, "calibrate refuses it (it needs at least 4", "calibrate refuses it"),
        (
            lambda t, first: t > first - 10.0,
            "calibrate refuses the run (it needs at least 30 s at rest",
            "calibrate refuses the run",
        ),
    ],
    ids=["two_steps", "ten_seconds_of_rest"],
)
def test_inspect_warns_of_runs_calibrate_refuses(keep, words, refusal, tmp_path, capsys):
    batch = good_batch(tmp_path, "b", validation=False)
    csv = batch / "TEM1" / "identification.csv"
    header, a = read_csv(csv)
    t, i = a[:, header.index("time_s")], a[:, header.index("current_A")]
    first = t[np.flatnonzero(np.abs(np.diff(i)) > 0.1)[0] + 1]  # the first step
    write_csv(csv, header, a[keep(t, first)])
    assert main(["inspect", str(batch), "--json"]) == 0  # a warning: identify may still use the run
    doc = json.loads(capsys.readouterr().out)
    assert any(words in f["problem"] for f in doc["findings"] if f["severity"] == "warning"), doc["findings"]
    refused(capsys, ["calibrate", batch, "--out", tmp_path / "run", "--workers", "1"], refusal)
    assert listing(tmp_path) == ["b"]  # refused before any work: no run folder


def test_colliding_module_ids_are_refused(tmp_path, capsys):
    batch = colliding_ids(tmp_path, "b")
    refused(capsys, ["calibrate", batch, "--out", tmp_path / "run"], "'TEM 1' and 'TEM_1'", "share output file")


def test_a_short_gap_in_a_hold_is_a_warning_and_a_stuck_coarse_logger_is_not_stuck(tmp_path):
    b = good_batch(tmp_path, "b", validation=False)
    path = b / "TEM1" / "identification.csv"
    from corpus import read_csv, write_csv

    header, a = read_csv(path)
    t = a[:, 0]
    a = a[~((t > 1000) & (t < 1005))]  # 5 s lost inside a hold
    a[:, header.index("T1_C")] = np.round(a[:, header.index("T1_C")], 1)  # a 0.1 K logger on T1
    write_csv(path, header, a)
    batch = load_batch(b)
    assert [f.severity for f in batch.findings] == ["warning"]
    assert "5.202 s gap" in batch.findings[0].problem and batch.findings[0].line == 5002


def test_the_loader_reads_big_files_in_blocks_with_the_right_line_numbers(tmp_path, monkeypatch):
    import tembayes.data.experiment as ex

    path = tmp_path / "x.csv"
    shutil.copy(EXAMPLE / "TEM1" / "validation.csv", path)
    whole = load_experiment(path)
    monkeypatch.setattr(ex, "_CHUNK_BYTES", 5000)  # ~70 rows a block
    blocks = load_experiment(path)
    for name in ("time", "current", "voltage", "sensors", "boundaries", "lines"):
        np.testing.assert_array_equal(getattr(blocks, name), getattr(whole, name))
    lines = path.read_text().splitlines()
    lines[9000] = lines[9000].replace(",", ";", 1)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match="line 9001"):
        load_experiment(path)


# ---------------------------------------------------------------- outputs


def fake_run(folder, kind="calibrate"):
    """A folder that looks like a finished run (for the output checks, which run before it is read)."""
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text("{}")
    (folder / "posterior.nc").write_bytes(b"x")
    (folder / MARKER).write_text(marker(kind, complete=True))
    return folder


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    root = tmp_path_factory.mktemp("small")
    return good_batch(root, "b", validation=False)


@pytest.mark.parametrize("where", ["batch", "parent", "inside"])
def test_calibrate_refuses_an_out_that_overlaps_the_batch_even_with_overwrite(where, small, capsys):
    out = {"batch": small, "parent": small.parent, "inside": small / "run"}[where]
    before = tree(small.parent)
    refused(capsys, ["calibrate", small, "--out", out, "--overwrite"], str(out))
    assert tree(small.parent) == before


def test_overwrite_never_deletes_a_users_files_or_another_kind_of_output(small, tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("measurements I cannot get back")
    for cmd in (["calibrate", small], ["identify", small], ["simulate"]):
        refused(
            capsys,
            [*cmd[:1], *([cmd[1]] if len(cmd) > 1 else []), *(["--out"] if len(cmd) > 1 else []), mine, "--overwrite"],
            "not a tembayes output",
        )
    run = fake_run(tmp_path / "run")
    (run / "my_plot.png").write_text("mine")
    refused(capsys, ["calibrate", small, "--out", run, "--overwrite"], "did not write", "my_plot.png")
    ident = tmp_path / "ident"
    ident.mkdir()
    (ident / "identify.json").write_text("{}")
    refused(capsys, ["calibrate", small, "--out", ident, "--overwrite"], "this is a tembayes identify output")
    assert (mine / "notes.txt").read_text() == "measurements I cannot get back"
    assert (run / "my_plot.png").exists() and (ident / "identify.json").exists()


@pytest.mark.parametrize("command", ["identify", "calibrate", "simulate"])
def test_an_out_that_is_a_file_is_refused_before_any_work(command, small, tmp_path, capsys):
    f = tmp_path / "afile"
    f.write_text("x")
    argv = [command, f] if command == "simulate" else [command, small, "--out", f]
    refused(capsys, argv, "is a file")
    refused(
        capsys,
        [command, tmp_path / "afile" / "sub"] if command == "simulate" else [command, small, "--out", f / "sub"],
        "is a file",
    )
    assert f.read_text() == "x"


def test_commands_reading_a_run_refuse_bad_outs_before_reading_it(tmp_path, capsys):
    run = fake_run(tmp_path / "run")
    exp = EXAMPLE / "TEM1" / "validation.csv"
    before = tree(run)
    for cmd in (
        ["report", run],
        ["export", run, "--format", "json"],
        ["gap", run, EXAMPLE],
        ["predict", run, exp, "--module", "TEM1"],
    ):
        refused(capsys, [*cmd, "--out", run, "--overwrite"], "the output is the run folder itself")
        refused(capsys, [*cmd, "--out", tmp_path, "--overwrite"], "holds the run folder")
    refused(capsys, ["gap", run, EXAMPLE, "--out", EXAMPLE / "gap"], "inside the batch folder")
    refused(capsys, ["predict", run, exp, "--module", "TEM1", "--out", exp], "the experiment file itself")
    (tmp_path / "other").mkdir()
    refused(capsys, ["export", run, "--out", tmp_path / "other", "--format", "json"], "is a folder")
    assert tree(run) == before


def test_export_overwrites_only_an_export_file(tmp_path, capsys):
    run = fake_run(tmp_path / "run")
    mine = tmp_path / "mine.json"
    mine.write_text('{"my": "data"}')
    refused(capsys, ["export", run, "--out", mine, "--overwrite"], "not a tembayes output")
    ours = tmp_path / "ours.json"
    ours.write_text('{"schema": "tembayes-observer-export/1", "modules": {}}')
    check_output(ours, kind="export", overwrite=True)  # accepted
    assert mine.read_text() == '{"my": "data"}'


def _as_nobody(fn):
    """Run ``fn`` in a child process as an unprivileged user (root writes anywhere); its exit status."""
    pid = os.fork()
    if pid == 0:  # pragma: no cover -- the child
        try:
            os.setgid(65534)
            os.setuid(65534)
            os._exit(fn())
        except BaseException:
            os._exit(99)
    return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])


@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions")
def test_a_read_only_out_is_refused_before_any_work():
    import tempfile

    top = tempfile.mkdtemp(prefix="tembayes-ro-", dir="/tmp")  # readable by an unprivileged user
    try:
        os.chmod(top, 0o755)
        ro = os.path.join(top, "ro")
        os.mkdir(ro, 0o555)
        os.chmod(ro, 0o555)
        out = os.path.join(ro, "ident")
        check = lambda: 0 if _refused_quickly(out) else 1  # noqa: E731
        assert (_as_nobody(check) if os.geteuid() == 0 else check()) == 0
        assert os.listdir(ro) == []
    finally:
        os.chmod(os.path.join(top, "ro"), 0o755)
        shutil.rmtree(top)


def _refused_quickly(out):
    try:
        check_output(out, kind="identify")
    except DataError as e:
        return "cannot write in" in str(e) and "Permission denied" in str(e)
    return False


def test_too_little_space_is_refused_before_any_work(small, tmp_path, capsys, monkeypatch):
    import collections

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 10**6, 10**6))
    refused(capsys, ["calibrate", small, "--out", tmp_path / "run"], "only 1 MB are free")
    assert not (tmp_path / "run").exists()


def test_no_space_mid_write_is_one_line_and_leaves_nothing_half_written(small, tmp_path, capsys, monkeypatch):
    import tembayes.data.write as w

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "ident" / "identify.json"))

    monkeypatch.setattr(w, "write_json", full)
    monkeypatch.setattr("tembayes.data.write_json", full, raising=False)
    monkeypatch.setattr("tembayes.identify.pipeline.identify_batch", lambda *a, **k: {})
    monkeypatch.setattr("tembayes.identify.pipeline.to_json", lambda *a, **k: {})
    refused(
        capsys, ["identify", small, "--out", tmp_path / "ident", "--no-figures"], "No space left", "Free some space"
    )
    assert listing(tmp_path) == []


# ---------------------------------------------------------------- the run folder: atomic, locked, resumable


class Boom(Exception):
    pass


def _fail_inside(monkeypatch):
    def boom(*a, **k):
        raise Boom("killed")
        yield  # pragma: no cover

    monkeypatch.setattr("tembayes.calibrate.scaleout.calibrate_modules", boom)


def test_a_failed_overwrite_leaves_the_previous_run_intact_and_resumable(small, tmp_path, monkeypatch):
    from tembayes.calibrate import calibrate_batch

    run = fake_run(tmp_path / "run")
    before = tree(run)
    _fail_inside(monkeypatch)
    with pytest.raises(Boom):
        calibrate_batch(load_batch(small), run, seed=3, overwrite=True)
    assert tree(run) == before
    part = partial_path(run)
    state = json.loads((part / MARKER).read_text())
    assert state["seed"] == 3 and state["complete"] is False
    assert state["batch"]["path"] == str(small.resolve()) and "TEM1/identification.csv" in state["batch"]["inputs"]
    assert not (tmp_path / ".run.lock").exists()


def test_resume_refuses_another_seed_or_a_changed_batch(small, tmp_path, monkeypatch, capsys):
    from tembayes.calibrate import calibrate_batch

    b = good_batch(tmp_path, "b", validation=False)
    _fail_inside(monkeypatch)
    run = tmp_path / "run"
    with pytest.raises(Boom):
        calibrate_batch(load_batch(b), run, seed=3)
    part = partial_path(run)
    before = tree(part)
    refused(capsys, ["calibrate", b, "--out", run], "holds an interrupted run", "Continue it with --resume")
    refused(
        capsys,
        ["calibrate", b, "--out", run, "--resume", "--seed", "4"],
        "started with --seed 3",
        "Resume it with --seed 3",
    )
    ident = b / "TEM1" / "identification.csv"
    ident.write_bytes(ident.read_bytes().replace(b"\n0.185,", b"\n0.186,", 1))
    refused(capsys, ["calibrate", b, "--out", run, "--resume", "--seed", "3"], "changed: TEM1/identification.csv")
    assert tree(part) == before


def test_one_writer_per_run_and_a_stale_lock_is_named_and_taken_over(small, tmp_path, capsys):
    run = tmp_path / "run"
    held = RunLock(run).acquire()
    try:
        refused(
            capsys, ["calibrate", small, "--out", run, "--resume", "--seed", "4"], f"being written by pid {os.getpid()}"
        )
    finally:
        held.release()
    assert not run.exists() and not partial_path(run).exists()
    (tmp_path / ".run.lock").write_text(json.dumps({"pid": 999999, "host": "gone", "started": "yesterday"}))
    lock = RunLock(run).acquire()
    assert "pid 999999 on gone since yesterday" in lock.stale_note() and "taken over" in lock.stale_note()
    lock.release()
    assert not (tmp_path / ".run.lock").exists()


def test_damaged_checkpoint_chunk_and_module_file_are_set_aside_not_fatal(tmp_path):
    import emcee

    from tembayes.calibrate.sampler import ChunkCheckpoint

    be = emcee.backends.Backend()
    be.reset(4, 2)
    be.grow(10, None)
    be.chain[:] = np.arange(80.0).reshape(10, 4, 2)
    be.log_prob[:] = 0.0
    be.iteration = 10
    be.random_state = np.random.RandomState(0).get_state()
    ck = ChunkCheckpoint(tmp_path / "TEM1.stage0")
    ck.save(be, 0)
    be.grow(5, None)
    be.iteration = 15
    ck.save(be, 10)
    second = ck.chunks()[1]
    data = open(second, "rb").read()
    open(second, "wb").write(data[: len(data) // 2])  # truncated
    with pytest.warns(RuntimeWarning, match=r"TEM1\.stage0\.00001\.npz cannot be read.*continues from chunk 0"):
        back = ck.load(4, 2)
    assert back.iteration == 10 and os.path.exists(second + ".damaged")
    nc = tmp_path / "TEM1.nc"
    nc.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 100)
    assert not module_usable(nc)


def test_a_run_records_where_its_batch_is_and_refuses_a_changed_one(run3, tmp_path, capsys):
    from tembayes.calibrate.run import load_run, load_run_batch

    out, summ, _ = run3
    run = load_run(out)
    rec = summ.batch
    assert os.path.isabs(rec["path"]) and set(rec["inputs"]) >= {"batch.toml", "TEM1/identification.csv"}
    assert json.loads((out / MARKER).read_text())["kind"] == "calibrate"
    moved = tmp_path / "moved"
    shutil.copytree(rec["path"], moved)
    batch, notes = load_run_batch(run, moved)
    assert batch.path == moved and any("the batch moved" in n for n in notes)
    (moved / "TEM2" / "validation.csv").write_bytes((moved / "TEM1" / "identification.csv").read_bytes())
    _, notes = load_run_batch(run, moved)
    assert any("validation runs added since the calibration: TEM2/validation.csv" in n for n in notes)
    ident = moved / "TEM3" / "identification.csv"
    ident.write_bytes(ident.read_bytes().rstrip(b"\n").rsplit(b"\n", 1)[0] + b"\n")  # one sample fewer
    with pytest.raises(DataError, match="TEM3/identification.csv changed"):
        load_run_batch(run, moved)


def test_a_resumed_run_reuses_only_modules_of_the_same_calibration(tmp_path):
    """A finished module is reused only under the same --model and --discrepancy, and a robust one only
    if it kept its held values: the batch's posterior joins modules that have the same variables."""
    import h5py

    from tembayes.calibrate import CalibrationOptions
    from tembayes.calibrate.runfolder import module_matches

    def module(name, meta):
        nc = tmp_path / f"{name}.nc"
        with h5py.File(nc, "w") as f:
            f.create_group("posterior").attrs["module_TEM1"] = json.dumps({"module_id": "TEM1", **meta})
        return nc

    robust = {"options": {"model": "full", "discrepancy": "robust"}, "held": ["g_ceramic"]}
    assert module_matches(module("same", robust), CalibrationOptions())
    before = module("before", {"options": {"model": "full", "discrepancy": "robust"}})  # no held values kept
    assert not module_matches(before, CalibrationOptions())
    assert module_matches(before, CalibrationOptions(discrepancy="window-sandwich")) is False
    assert not module_matches(module("paper", robust), CalibrationOptions(model="paper"))
    plain = module("plain", {"options": {"model": "full", "discrepancy": "none"}, "held": []})
    assert module_matches(plain, CalibrationOptions(discrepancy="none"))
    assert not module_matches(plain, CalibrationOptions())
    assert not module_matches(tmp_path / "missing.nc", CalibrationOptions())
