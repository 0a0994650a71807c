"""Batch calibration on Dask: same bits whatever the workers, resume, failures.

A cheap module calibration (a 24-min staircase at 1 Hz, the paper-sized
rig model, 1000 sampler steps: ~5 s) keeps these tests about the scale-out
machinery; whether a calibration is right is tested in
``test_calibrate_pipeline``.  The modules end "not converged" by the
sampler's 1000-ESS target, so the population stage is run with
``keep_unconverged`` where it is needed.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from tembayes.calibrate import calibrate_batch
from tembayes.calibrate import results as res
from tembayes.calibrate.batch import finish_run
from tembayes.calibrate.diagnostics import ModuleDiagnostics, PsisCheck
from tembayes.calibrate.module import CalibrationOptions
from tembayes.calibrate.moduledigest import exclusion_reason
from tembayes.calibrate.run import load_run
from tembayes.calibrate.runfolder import partial_path
from tembayes.constants import MODULE_PARAMETERS
from tembayes.data import LazyModule, load_batch

CHEAP = CalibrationOptions(max_steps=1000, pilot=500, max_relinearise=1, psis_draws=100, leg_cells=2, block_split=1)
CHEAP_KW = "max_steps=1000, pilot=500, max_relinearise=1, psis_draws=100, leg_cells=2, block_split=1"


@pytest.fixture(scope="module")
def serial4(batch4, tmp_path_factory):
    """``batch4`` calibrated in this process (the reference)."""
    out = tmp_path_factory.mktemp("s4") / "run"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # "not converged": the cheap budget
        summ = calibrate_batch(load_batch(batch4), out, seed=5, options=CHEAP, workers=1, keep_unconverged=True)
    return out, summ


def _same_run(a, b):
    """Two run folders hold the same numbers (summaries and every array of posterior.nc)."""
    sa, sb = (json.loads((Path(r) / "summary.json").read_text()) for r in (a, b))
    for s in (sa, sb):
        s["calibration"].pop("seconds")
        s["calibration"].pop("executor")
        s["calibration"].pop("command")
        for m in s["modules"].values():
            m["diagnostics"].pop("seconds")
        s["batch"].pop("path")
        for k in ("sampling_s", "elapsed_s"):
            s["population_diagnostics"].pop(k, None)
    assert sa == sb
    ra, rb = load_run(a), load_run(b)
    assert ra.module_ids == rb.module_ids
    for g in ("posterior", "log_likelihood", "sample_stats", "observed_data", "constant_data", "population"):
        da, db = getattr(ra.idata, g), getattr(rb.idata, g)
        for k in da.data_vars:
            np.testing.assert_array_equal(da[k].values, db[k].values, err_msg=f"{g}/{k}")


def test_lazy_batch_validates_every_file_and_keeps_paths(batch4, tmp_path):
    lazy = load_batch(batch4, lazy=True)
    eager = load_batch(batch4)
    assert all(isinstance(m, LazyModule) for m in lazy.modules.values())
    m = lazy.modules["TEM2"]
    np.testing.assert_array_equal(m.identification.voltage, eager.modules["TEM2"].identification.voltage)
    # a broken file is refused at load time, naming it, as for an eager load
    bad = tmp_path / "bad"
    shutil.copytree(batch4, bad)
    p = bad / "TEM3" / "identification.csv"
    lines = p.read_text().splitlines()
    lines[5] = lines[5].replace(",", ",x", 1)
    p.write_text("\n".join(lines) + "\n")
    from tembayes.errors import DataError

    with pytest.raises(DataError, match=r"TEM3.*identification\.csv"):
        load_batch(bad, lazy=True)


@pytest.mark.slow  # a LocalCluster and two worker pools: ~2 min
def test_two_workers_and_a_scheduler_give_the_serial_bits(batch4, serial4, tmp_path):
    from distributed import LocalCluster

    out_ref, summ = serial4
    assert summ.population is not None and not summ.population_excluded
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        calibrate_batch(
            load_batch(batch4, lazy=True), tmp_path / "w2", seed=5, options=CHEAP, workers=2, keep_unconverged=True
        )
        _same_run(out_ref, tmp_path / "w2")
        # an existing cluster, reached by its address (what --scheduler does)
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cl:
            s = calibrate_batch(
                load_batch(batch4, lazy=True),
                tmp_path / "sch",
                seed=5,
                options=CHEAP,
                scheduler=cl.scheduler_address,
                keep_unconverged=True,
            )
    assert s.calibration["executor"]["scheduler"].startswith("tcp://")
    _same_run(out_ref, tmp_path / "sch")


_SCRIPT = """
import sys, warnings
from tembayes.calibrate import calibrate_batch
from tembayes.calibrate.module import CalibrationOptions
from tembayes.data import load_batch
if __name__ == "__main__":
    warnings.simplefilter("ignore", RuntimeWarning)
    calibrate_batch(load_batch(sys.argv[1], lazy=True), sys.argv[2], seed=5, workers=2,
                    keep_unconverged=True, resume=sys.argv[3] == "resume",
                    options=CalibrationOptions({kw}), progress=lambda m: print(m, flush=True))
""".format(kw=CHEAP_KW)


def _start(tmp_path, batch, out, mode):
    script = tmp_path / "run.py"
    script.write_text(_SCRIPT)
    env = dict(
        os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).parents[1]), os.environ.get("PYTHONPATH", "")])
    )
    log = open(tmp_path / f"{mode}.log", "w")
    return subprocess.Popen(
        [sys.executable, str(script), str(batch), str(out), mode],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=env,
        start_new_session=True,
    ), tmp_path / f"{mode}.log"


def _wait(pred, timeout, what):
    t = time.time()
    while not pred():
        if time.time() - t > timeout:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


def _workers(pid):
    import psutil

    return [
        p
        for p in psutil.Process(pid).children(recursive=True)
        if "spawn_main" in " ".join(p.cmdline()) and "resource_tracker" not in " ".join(p.cmdline())
    ]


@pytest.mark.slow  # three cluster runs, one with a worker killed and one killed whole: ~5 min
def test_a_killed_worker_is_replaced_and_a_killed_run_resumes_with_the_missing_modules(batch4, serial4, tmp_path):
    out_ref, _ = serial4
    # 1. a worker killed mid-module: Dask reruns its module, the batch finishes with the same bits
    out = tmp_path / "killed_worker"
    proc, log = _start(tmp_path, batch4, out, "fresh")
    # a sampler checkpoint: the workers are inside their first modules (the run is built in RUN.partial)
    _wait(lambda: any((partial_path(out) / "checkpoints").glob("*.json")), 120, "a module under way")
    victims = _workers(proc.pid)
    assert len(victims) >= 2, [p.cmdline() for p in victims]
    victims[0].send_signal(signal.SIGKILL)
    assert proc.wait(timeout=300) == 0, log.read_text()
    assert not list((out / "modules").glob("*.failed.json"))
    _same_run(out_ref, out)

    # 2. the whole run killed after its first modules: --resume calibrates only the others
    out = tmp_path / "killed_run"
    part = partial_path(out)
    proc, log = _start(tmp_path, batch4, out, "first")
    _wait(lambda: len(list((part / "modules").glob("*.nc"))) >= 1, 300, "a first module")
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    done = sorted(p.stem for p in (part / "modules").glob("*.nc"))
    assert 1 <= len(done) < 4 and not (part / "summary.json").exists() and not out.exists()
    proc, log = _start(tmp_path, batch4, out, "resume")
    assert proc.wait(timeout=300) == 0, log.read_text()
    text = log.read_text()
    assert f"{4 - len(done)} module(s) to calibrate" in text
    for mid in done:
        assert f"{mid}: finished earlier, reused" in text
    _same_run(out_ref, out)


def test_a_failing_or_unconverged_module_does_not_sink_the_batch(batch4, tmp_path, quick_population, monkeypatch):
    # a fifth module whose run has no current steps: its calibration raises
    b = tmp_path / "batch"
    shutil.copytree(batch4, b)
    shutil.rmtree(b / "TEM3")  # three calibrated modules are enough: two converged, one not
    (b / "TEM5").mkdir()
    lines = (b / "TEM1" / "identification.csv").read_text().splitlines()
    head, rows = lines[0], [r.split(",") for r in lines[1:301]]
    for r in rows:
        r[1] = "0.50000"  # a constant current
    (b / "TEM5" / "identification.csv").write_text("\n".join([head] + [",".join(r) for r in rows]) + "\n")
    out = tmp_path / "run"
    with pytest.warns(RuntimeWarning, match=r"TEM5: calibration failed"):
        summ = calibrate_batch(load_batch(b, lazy=True), out, seed=5, options=CHEAP, workers=2)
    assert "TEM5" in summ.failed_modules and "TEM5" not in summ.modules
    assert json.loads((out / "modules" / "TEM5.failed.json").read_text())["error"] == summ.failed_modules["TEM5"]
    assert summ.converged is False
    # the cheap budget converges nobody: all left out, each with its reason, no population
    assert set(summ.population_excluded) == {"TEM1", "TEM2", "TEM4", "TEM5"}
    assert "bulk ESS" in summ.population_excluded["TEM1"] and "--max-steps" in summ.population_excluded["TEM1"]
    assert summ.population is None
    assert load_run(out).module_ids == ("TEM1", "TEM2", "TEM4")
    # mark two of them converged: the population is fitted on those two only
    for mid in ("TEM2", "TEM4"):
        r = res.read_module(out / "modules" / f"{mid}.nc")
        passed = (PsisCheck(stage=1, k_hat=0.3, weight_ess_fraction=0.9, max_logw_dev=1.0),)
        r = dataclasses.replace(r, diagnostics=dataclasses.replace(r.diagnostics, sampler_converged=True, psis=passed))
        res.write_netcdf(res.to_inference_data([r]), out / "modules" / f"{mid}.nc")
    # which modules enter the population is asserted, not its spreads: two cheap modules' fit need not converge
    from tembayes.calibrate import population

    fit = population.fit_population
    monkeypatch.setattr(population, "fit_population", lambda *a, **kw: fit(*a, **{**kw, "max_steps": 4000}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", population.PopulationConvergenceWarning)
        summ = finish_run(load_batch(b, lazy=True), out, seed=5, options=CHEAP)
    assert set(summ.population_excluded) == {"TEM1", "TEM5"}
    assert summ.population is not None
    ops = {m: e.outlier_prob for m, e in summ.modules.items()}
    assert ops["TEM1"] is None and ops["TEM2"] is not None and ops["TEM4"] is not None
    # the outlier answer covers the population's modules only
    odd = {m: e.odd_one_prob for m, e in summ.modules.items()}
    assert odd["TEM1"] is None and odd["TEM2"] + odd["TEM4"] == pytest.approx(1.0)
    assert summ.modules["TEM1"].deviation is None and set(summ.modules["TEM2"].deviation) == set(MODULE_PARAMETERS)
    pop = load_run(out).idata.population.attrs["outlier_prob"]
    assert set(json.loads(pop)) == {"TEM2", "TEM4"}


def test_exclusion_reason_names_every_failed_target():
    d = ModuleDiagnostics.from_json(
        {
            "rhat_max": 1.05,
            "ess_bulk_min": 400.0,
            "chain_over_tau": 20.0,
            "steps": 9000,
            "sampler_converged": False,
            "psis": [{"stage": 1, "k_hat": 0.9, "weight_ess_fraction": 0.1, "max_logw_dev": 5.0}],
        }
    )
    why = exclusion_reason(d)
    for s in ("R-hat 1.050 > 1.01", "bulk ESS 400 < 1000", "20 autocorrelation times < 50", "k_hat 0.90", "9000 steps"):
        assert s in why
    # the sampler's targets met but the expansion off: still left out, for that reason alone
    off = dataclasses.replace(d, rhat_max=1.005, ess_bulk_min=1500.0, chain_over_tau=60.0, sampler_converged=True)
    assert off.reasons() == ["expansion PSIS k_hat 0.90 >= 0.7"]
    good = dataclasses.replace(off, psis=(PsisCheck(stage=2, k_hat=0.4, weight_ess_fraction=0.8, max_logw_dev=1.0),))
    assert good.converged and exclusion_reason(good) is None


def test_posterior_nc_streamed_module_by_module_equals_the_in_memory_one(run3, tmp_path):
    import arviz as az

    out, _, _ = run3
    rs = [res.read_module(out / "modules" / f"TEM{i}.nc") for i in (1, 2, 3)]
    # make the modules ragged: TEM2 loses its last 5 steps and their samples
    r = rs[1]
    k = len(r.steps["t_s"]) - 5
    keep = r.observed["step"] < k
    rs[1] = dataclasses.replace(
        r,
        step_loglike=r.step_loglike[..., :k],
        steps={key: v[:k] for key, v in r.steps.items()},
        observed={key: (v[..., keep] if key != "noise" else v) for key, v in r.observed.items()},
    )
    files = []
    for r in rs:
        files.append(res.write_netcdf(res.to_inference_data([r]), tmp_path / "m" / f"{r.module_id}.nc"))
    attrs = {"tembayes_seed": 5, "tembayes_command": "tembayes calibrate x"}
    res.write_netcdf(res.to_inference_data(rs, attrs=attrs), tmp_path / "memory.nc")
    res.write_run_posterior(tmp_path / "streamed.nc", files, attrs=attrs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = az.from_netcdf(tmp_path / "memory.nc", engine="h5netcdf")
        b = az.from_netcdf(tmp_path / "streamed.nc", engine="h5netcdf")
    assert a.groups() == b.groups()
    for g in a.groups():
        ga, gb = getattr(a, g), getattr(b, g)
        assert set(ga.data_vars) == set(gb.data_vars) and ga.attrs == gb.attrs
        for v in ga.data_vars:
            assert ga[v].dims == gb[v].dims
            np.testing.assert_array_equal(ga[v].values, gb[v].values, err_msg=f"{g}/{v}")
    assert np.isnan(b.constant_data["step_time_s"].sel(module="TEM2").values[k:]).all()
    assert (b.constant_data["obs_step"].sel(module="TEM2").values[keep.sum() :] == -1).all()
    assert set(MODULE_PARAMETERS) <= set(b.posterior.data_vars)


def test_real_run_posterior_nc_has_units_and_a_prior_shaped_like_the_posterior(run3):
    import arviz as az

    out, _, _ = run3
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        idata = az.from_netcdf(out / "posterior.nc", engine="h5netcdf")
    missing = [
        f"{g}/{v}" for g in idata.groups() for v, da in getattr(idata, g).data_vars.items() if not da.attrs.get("units")
    ]
    assert not missing, f"variables without units: {missing}"
    for k in MODULE_PARAMETERS:
        assert idata.prior[k].dims == idata.posterior[k].dims


def test_cli_refuses_an_unreachable_scheduler_and_writes_nothing(batch4, tmp_path, capsys):
    from tembayes.cli import main

    out = tmp_path / "run"
    t = time.time()
    assert main(["calibrate", str(batch4), "--out", str(out), "--scheduler", "tcp://127.0.0.1:9"]) == 2
    assert time.time() - t < 60
    err = capsys.readouterr().err
    assert "cannot reach the Dask scheduler 'tcp://127.0.0.1:9'" in err and "dask scheduler" in err
    assert not out.exists()
