"""No third-party warning reaches the console of ``tembayes calibrate``.

Two were seen: arviz's import-time notice of its coming refactor (a
FutureWarning, once a day per user cache) and Dask's "Sending large graph"
(a module's data put inside its task).  Both are checked at their source,
cheaply: a fresh arviz cache in a subprocess, and the Dask scale-out on an
in-process cluster with a stand-in for the module calibration and a
warning threshold far below a module's data.
"""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def test_every_arviz_import_of_tembayes_goes_through_the_one_that_keeps_the_notice_out():
    direct = [
        str(p.relative_to(ROOT))
        for p in (ROOT / "tembayes").rglob("*.py")
        if p.name != "arvizlib.py"
        and any(
            line.strip().startswith(("import arviz", "from arviz"))
            for line in p.read_text(encoding="utf-8").splitlines()
        )
    ]
    assert not direct, f"import arviz through tembayes.common.arvizlib: {direct}"


def test_importing_the_calibration_shows_no_arviz_notice_even_on_a_new_day(tmp_path):
    # a fresh cache folder: arviz has not yet shown today's notice
    env = {
        "PATH": "/usr/bin:/bin",
        "HOME": str(tmp_path),
        "XDG_CACHE_HOME": str(tmp_path / "cache"),
        "PYTHONPATH": str(ROOT),
    }
    code = "import arviz; import tembayes.calibrate.run"
    plain = subprocess.run([sys.executable, "-W", "always", "-c", code], env=env, capture_output=True, text=True)
    assert "ArviZ is undergoing a major refactor" in plain.stderr  # the notice exists: the check is not vacuous
    env["XDG_CACHE_HOME"] = str(tmp_path / "cache2")
    code = "import tembayes.calibrate.module, tembayes.calibrate.run, arviz"
    ours = subprocess.run([sys.executable, "-W", "error", "-c", code], env=env, capture_output=True, text=True)
    assert ours.returncode == 0 and "Warning" not in ours.stderr, ours.stderr


def _fake_calibrate_one(module, datasheet, rig_config, seed, options, checkpoint, resume, *, threads=None):
    from tembayes.calibrate.scaleout import ModuleOutcome

    return ModuleOutcome(module.id, result=float(np.sum(module.data)))


def test_dask_scale_out_sends_module_data_outside_the_task_graph(monkeypatch, tmp_path):
    import dask
    from distributed import Client, LocalCluster

    from tembayes.calibrate import scaleout

    monkeypatch.setattr(scaleout, "calibrate_one", _fake_calibrate_one)
    # 40 kB of data per module, the warning threshold at 10 kB: embedded in its task, each module would warn
    todo = [SimpleNamespace(id=f"M{i}", data=np.full(5000, float(i))) for i in range(5)]
    with (
        dask.config.set({"distributed.admin.large-graph-warning-threshold": "10kB"}),
        LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster,
        Client(cluster) as client,
    ):
        with warnings.catch_warnings(record=True) as embedded:
            warnings.simplefilter("always")
            client.submit(np.sum, todo[1].data).result()  # negative control: the data inside the task
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = list(
                scaleout.calibrate_modules(
                    todo, {"d": 1}, {"r": 1}, seed=0, options=None, checkpoints=tmp_path, resume=False, client=client
                )
            )
    assert any("large graph" in str(w.message) for w in embedded)
    assert not [str(w.message) for w in caught]
    assert sorted((o.module_id, o.result) for o in out) == [(f"M{i}", 5000.0 * i) for i in range(5)]
