"""The gap loop closed: the best explanation's recalibrated modules as a run folder.

``tembayes gap`` recalibrates its strongest candidates; when one explains the
gap, its recalibrated modules are written as ``DIR/run/`` -- a complete run
folder, as ``tembayes calibrate --effect NAME`` writes it (the modules, the
population, ``summary.json``, ``posterior.nc``) -- which ``predict``,
``report`` and ``export`` accept, and ``gap.json`` says so under
``recalibrated`` with the laws before and after.
"""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path

from tembayes.calibrate import results as res
from tembayes.calibrate.batch import finish_run
from tembayes.calibrate.moduledigest import write_digest
from tembayes.constants import MODULE_PARAMETERS
from tembayes.data.digest import batch_inputs
from tembayes.data.outputs import MARKER, marker
from tembayes.data.write import atomic_write_text

__all__ = ["write_recalibrated_run"]


def write_recalibrated_run(diag, run, batch, folder, *, seed=0, progress=None):
    """Write ``diag``'s recalibrated modules as a run folder; the ``recalibrated`` block of ``gap.json``.

    Parameters
    ----------
    diag : tembayes.gap.result.GapDiagnosis
        With a ``best`` effect and its ``recalibration``.
    run : tembayes.calibrate.run.CalibrationRun
        The run the diagnosis started from (its laws are "before").
    batch : tembayes.data.Batch
    folder : Path
        The run folder to create (inside the gap output being built).
    seed : int

    Returns
    -------
    dict or None
        ``{"effects", "run", "laws_before", "laws_after", "modules_not_recalibrated"}``;
        None when there is nothing to write.
    """
    if not diag.best or not diag.recalibration:
        return None
    folder = Path(folder)
    (folder / "modules").mkdir(parents=True)
    for mid, cal in diag.recalibration.items():
        nc = res.write_netcdf(res.to_inference_data([cal]), folder / "modules" / f"{mid}.nc")
        write_digest(nc, cal)
    record = {"path": os.path.abspath(batch.path), "inputs": batch_inputs(batch)}
    opt = diag.recalibration_options
    # the spreads the run started from that batch.toml does not state came from --population-prior
    earlier = {
        k: (v["median"], v["log_sd"]) for k, v in run.summary.population_prior.items() if k not in batch.population
    }
    summ = finish_run(
        batch,
        folder,
        seed=seed,
        options=opt,
        progress=progress,
        batch_record=record,
        argv=None,
        population_prior=earlier or None,
    )
    atomic_write_text(folder / MARKER, marker("calibrate", complete=True, seed=int(seed), batch=record))
    before = {m: {p: asdict(e.laws[p]) for p in MODULE_PARAMETERS} for m, e in run.summary.modules.items()}
    after = {m: {p: asdict(e.laws[p]) for p in MODULE_PARAMETERS} for m, e in summ.modules.items()}
    return {
        "effects": list(opt.effects),
        "run": folder.name,
        "laws_before": before,
        "laws_after": after,
        "modules_not_recalibrated": sorted(set(before) - set(after)),
    }
