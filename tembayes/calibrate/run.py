"""A finished calibration run, read back from its folder (read-only view).

:func:`load_run` opens ``RUN/summary.json`` and ``RUN/posterior.nc``
(:mod:`tembayes.calibrate.results`) with every check a reader needs; the
figures, ``tembayes predict`` and the reports read runs through it.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tembayes.calibrate.runsummary import ModuleSummary, RunSummary
from tembayes.constants import MODULE_PARAMETERS
from tembayes.errors import DataError

if TYPE_CHECKING:
    from collections.abc import Sequence

    from tembayes.calibrate.module import CalibrationOptions
    from tembayes.data import Batch
    from tembayes.physics.rig import RigDescription


@dataclass
class CalibrationRun:
    """A calibration run as saved on disk (read-only view).

    Attributes
    ----------
    path : Path
        The run folder.
    idata : arviz.InferenceData
        ``posterior.nc`` (groups in :mod:`tembayes.calibrate.results`).
    summary : RunSummary
        ``summary.json``, typed.
    module_ids : tuple of str
        Modules in ``posterior.nc`` order.
    """

    path: Path
    idata: object
    summary: RunSummary
    module_ids: tuple
    _meta: dict = field(default_factory=dict, repr=False)

    # -- run-level facts --------------------------------------------------
    @property
    def has_population(self) -> bool:
        """Whether the run has a population (batch-level) fit."""
        return "population" in self.idata.groups()

    @property
    def tref_C(self) -> float:
        """Reference temperature of the laws [degC]."""
        return self.summary.tref_C

    def _check(self, module_id):
        if module_id not in self.module_ids:
            raise ValueError(
                f"module {module_id!r} is not in the run {self.path}; modules: {', '.join(self.module_ids)}"
            )

    # -- per-module summary facts -----------------------------------------
    def module_summary(self, module_id: str) -> ModuleSummary:
        """The module's entry of ``summary.json``."""
        self._check(module_id)
        return self.summary.modules[module_id]

    def outlier_prob(self, module_id: str) -> float | None:
        """Posterior probability that the module is off the population, or None without a population fit."""
        p = self.module_summary(module_id).outlier_prob
        if p is None and self.has_population:
            p = _json_attr(self.idata.population.attrs, "outlier_prob", {}).get(module_id)
        return None if p is None or not np.isfinite(float(p)) else float(p)

    def diagnostics(self, module_id: str) -> dict:
        """The module's ``diagnostics`` (``rhat_max``, ``ess_bulk_min``, ``converged``, ...)."""
        return dict(self.module_summary(module_id).diagnostics)

    def converged(self, module_id: str) -> bool | None:
        """True/False as recorded, None if the run did not record it."""
        c = self.diagnostics(module_id).get("converged")
        return None if c is None else bool(c)

    def status(self, module_id: str) -> str:
        """``"converged (R̂ 1.004, ESS 1200)"`` or ``"NOT CONVERGED (...)"``."""
        d = self.diagnostics(module_id)
        bits = []
        if d.get("rhat_max") is not None:
            bits.append(f"R̂ {d['rhat_max']:.3f}")
        if d.get("ess_bulk_min") is not None:
            bits.append(f"ESS {d['ess_bulk_min']:.0f}")
        extra = f" ({', '.join(bits)})" if bits else ""
        c = self.converged(module_id)
        if c is None:
            return "convergence not recorded" + extra
        return ("converged" if c else "NOT CONVERGED") + extra

    def hysteresis(self, module_id: str) -> dict:
        """``{"R_ohm": {"estimate", "sd", "z"}, "S_V_per_K": {...}}`` (up - down, SI), or {}."""
        return dict(self.module_summary(module_id).hysteresis)

    def options(self) -> dict:
        """The calibration options recorded in ``summary.json`` (``model`` is ``"paper"`` for runs that predate it)."""
        return {"model": "paper", **(self.summary.calibration.get("options") or {})}

    def rig_for(self, batch: Batch) -> RigDescription:
        """The calibration rig of this run on ``batch``, after checking the batch holds every module.

        Raises
        ------
        DataError
            The batch is not the one the run was calibrated on.
        """
        from tembayes.calibrate.module import calibration_rig

        missing = [m for m in self.module_ids if m not in batch.modules]
        if missing:
            raise DataError(
                batch.path,
                f"has no module folder(s) {missing} of the run",
                "Give the batch folder the run was calibrated on.",
            )
        return calibration_rig(batch.rig_config, self.calibration_options())

    def calibration_options(self) -> CalibrationOptions:
        """The run's :class:`~tembayes.calibrate.module.CalibrationOptions` (options it does not know at their defaults)."""
        from tembayes.calibrate.module import CalibrationOptions

        return CalibrationOptions.from_json(self.options())

    def priors(self, module_id: str) -> dict:
        """``name -> {"kind", "center", "scale"}`` of the module's priors (from ``posterior.nc``)."""
        self._check(module_id)
        return self._meta.get(module_id, {}).get("priors") or {}

    # -- draws --------------------------------------------------------------
    def parameters(self) -> tuple:
        """Names of the sampled parameters in ``posterior.nc``."""
        return tuple(self.idata.posterior.data_vars)

    def draws(
        self, module_id: str, params: Sequence[str] = MODULE_PARAMETERS, *, max_draws: int | None = None
    ) -> np.ndarray:
        """Posterior draws of one module, shape ``(n, len(params))``, SI.

        Parameters
        ----------
        module_id : str
        params : sequence of str
            Names in ``posterior.nc``.
        max_draws : int, optional
            Thin evenly (over draws and walkers) to at most this many rows.

        Returns
        -------
        ndarray
            Rows with a non-finite value are dropped.
        """
        self._check(module_id)
        post = self.idata.posterior
        missing = [p for p in params if p not in post]
        if missing:
            raise ValueError(
                f"{self.path / 'posterior.nc'} has no parameter(s) {missing}; it has {list(post.data_vars)}"
            )
        cols = [np.asarray(post[p].sel(module=module_id).values, dtype=float) for p in params]
        return _rows(cols, max_draws)

    def population_draws(
        self, params: Sequence[str] = MODULE_PARAMETERS, *, max_draws: int | None = None
    ) -> np.ndarray | None:
        """Population-predictive draws (a new module), ``(n, len(params))`` SI, or None.

        None when the run has no population fit or it lacks one of ``params``.
        """
        if not self.has_population:
            return None
        pop = self.idata.population
        if any(p not in pop for p in params):
            return None
        cols = [np.asarray(pop[p].values, dtype=float) for p in params]
        out = _rows(cols, max_draws)
        return out if len(out) else None

    def prior_draws(self, params: Sequence[str] = MODULE_PARAMETERS, module_id: str | None = None) -> np.ndarray | None:
        """Draws of the datasheet prior, ``(n, len(params))`` SI, or None.

        ``module_id``: the module's (default the first; a batch's modules share
        the datasheet prior).  Older runs' prior group has no ``module`` dimension.
        """
        if "prior" not in self.idata.groups():
            return None
        pr = self.idata.prior
        if any(p not in pr for p in params):
            return None
        if "module" in pr.dims:
            pr = pr.sel(module=module_id) if module_id is not None else pr.isel(module=0)
        return _rows([np.asarray(pr[p].values, dtype=float) for p in params], None)

    # -- steps ----------------------------------------------------------------
    def steps(self, module_id: str) -> dict:
        """The module's step windows, padding removed.

        Returns
        -------
        dict of ndarray
            ``t_s`` [s], ``dI_A`` [A], ``direction`` (+1 up, -1 down),
            ``Tavg_C`` [degC] and ``n_samples`` (samples in each window).
        """
        self._check(module_id)
        const = self.idata.constant_data
        t = np.asarray(const["step_time_s"].sel(module=module_id).values, dtype=float)
        ok = np.isfinite(t)
        n = int(ok.sum())
        if not np.all(ok[:n]):  # padding is at the end; anything else is kept as NaN
            n = int(np.flatnonzero(ok)[-1]) + 1 if ok.any() else 0
        out = {
            "t_s": t[:n],
            "dI_A": np.asarray(const["step_dI_A"].sel(module=module_id).values, float)[:n],
            "direction": np.asarray(const["step_direction"].sel(module=module_id).values, float)[:n],
            "Tavg_C": np.asarray(const["step_Tavg_C"].sel(module=module_id).values, float)[:n],
        }
        obs_step = np.asarray(const["obs_step"].sel(module=module_id).values, dtype=float)
        valid = obs_step[np.isfinite(obs_step) & (obs_step >= 0)].astype(int)
        out["n_samples"] = np.bincount(valid[valid < n], minlength=n)[:n] if n else np.zeros(0, int)
        return out

    def step_loglike(self, module_id: str) -> np.ndarray:
        """Log-likelihood of each step window per draw, shape ``(chain, draw, n_steps)`` [nats]."""
        n = len(self.steps(module_id)["t_s"])
        ll = np.asarray(self.idata.log_likelihood["step_response"].sel(module=module_id).values, dtype=float)
        return ll[..., :n]


def _json_attr(attrs, key, default):
    v = attrs.get(key)
    if v is None:
        return default
    if isinstance(v, str):
        try:
            return json.loads(v)
        except json.JSONDecodeError:
            return default
    return v


def _rows(cols, max_draws):
    """Stack ``(chain, draw)`` arrays into ``(n, k)`` rows (draw-major), thin, drop non-finite rows."""
    X = np.column_stack([np.asarray(c, dtype=float).T.reshape(-1) for c in cols])
    X = X[np.all(np.isfinite(X), axis=1)]
    if max_draws is not None and len(X) > max_draws:
        X = X[np.linspace(0, len(X) - 1, int(max_draws)).round().astype(int)]
    return X


def load_run(run_dir: Path | str) -> CalibrationRun:
    """Open a calibration run folder.

    Parameters
    ----------
    run_dir : str or Path
        The ``--out`` folder of ``tembayes calibrate`` (holds ``posterior.nc``
        and ``summary.json``).

    Returns
    -------
    CalibrationRun

    Raises
    ------
    tembayes.errors.DataError
        The folder or one of the two files is missing or unreadable, or the
        two files describe different modules.
    """
    from tembayes.common.arvizlib import az  # heavy; only the loader needs it

    run = Path(run_dir)
    hint = "Give the --out folder of a finished `tembayes calibrate BATCH --out RUN`."
    if not run.is_dir():
        raise DataError(run, "is not a calibration run folder (it does not exist or is not a folder)", hint)
    post_path = run / "posterior.nc"
    summ_path = run / "summary.json"
    for p in (post_path, summ_path):
        if not p.is_file():
            raise DataError(
                p,
                f"missing: the run folder has no {p.name}",
                hint + " An interrupted run writes it only at the end; rerun with --resume.",
            )
    try:
        summary = json.loads(summ_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(summ_path, f"cannot be read as JSON ({exc})", "Rerun the calibration.") from exc
    if not isinstance(summary, dict) or not isinstance(summary.get("modules"), dict):
        raise DataError(
            summ_path, "has no 'modules' table", "It is not a tembayes calibrate summary.", column="modules"
        )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "population" is not a standard arviz group
            idata = az.from_netcdf(post_path, engine="h5netcdf")
    except Exception as exc:  # h5py/xarray raise many types for a broken file
        raise DataError(
            post_path, f"cannot be read as arviz InferenceData ({type(exc).__name__}: {exc})", "Rerun the calibration."
        ) from exc
    for g in ("posterior", "log_likelihood", "constant_data"):
        if g not in idata.groups():
            raise DataError(post_path, f"has no '{g}' group", "It is not a tembayes calibrate posterior.")
    if "module" not in idata.posterior.dims:
        raise DataError(
            post_path, "the posterior has no 'module' dimension", "It is not a tembayes calibrate posterior."
        )
    mods = tuple(str(m) for m in idata.posterior["module"].values)
    missing = [m for m in mods if m not in summary["modules"]]
    if missing:
        raise DataError(
            summ_path,
            f"has no entry for module(s) {missing} of posterior.nc",
            "The two files come from different runs; rerun the calibration.",
        )
    meta = {m: _json_attr(idata.posterior.attrs, f"module_{m}", {}) for m in mods}
    return CalibrationRun(path=run, idata=idata, summary=RunSummary.from_json(summary), module_ids=mods, _meta=meta)


def load_run_batch(run: CalibrationRun, path: Path | str | None = None) -> tuple:
    """The batch a run was calibrated on, checked against the digests the run recorded.

    Parameters
    ----------
    run : CalibrationRun
    path : str or Path, optional
        The batch folder (``--batch``); default the absolute path the run
        recorded.

    Returns
    -------
    batch : tembayes.data.Batch
    notes : list of str
        What a user should know: the batch moved, validation runs were added
        or changed since, or the run is too old to have recorded digests.

    Raises
    ------
    DataError
        The recorded batch is not there, or ``batch.toml`` or an
        identification run of the run's modules differs from what the run
        was calibrated on (the message names the files).
    """
    from tembayes.data import load_batch
    from tembayes.data.digest import batch_inputs, compare_inputs

    rec = run.summary.batch
    recorded = rec.get("path")
    notes = []
    if path is None:
        candidates = (
            [Path(recorded)]
            if recorded and Path(recorded).is_absolute()
            else [Path(recorded), run.path.parent / recorded]
            if recorded
            else []
        )
        path = next((c for c in candidates if (c / "batch.toml").is_file()), None)
        if path is None:
            raise DataError(
                run.path / "summary.json",
                f"names batch folder {recorded!r}, which is not there (moved?)",
                "Give the batch the run was calibrated on with --batch BATCH.",
                column="batch.path",
            )
    batch = load_batch(path)
    inputs = rec.get("inputs")
    if not inputs:
        notes.append(
            f"the run records no digest of its batch (an older run): make sure {path} is the batch it was calibrated on"
        )
        return batch, notes
    ids = set(run.module_ids)
    now = batch_inputs(batch)
    # what the posterior depends on: batch.toml, the rig file it names, the identification runs
    rig_key = set(now) - {"batch.toml"} - {k for k in now if k.endswith(".csv")}
    key = lambda k: k == "batch.toml" or k in rig_key or (k.endswith("/identification.csv") and k.split("/")[0] in ids)  # noqa: E731
    diff = compare_inputs(inputs, now, only=key)
    if diff.changed or diff.missing:
        what = ", ".join([*(f"{k} changed" for k in diff.changed), *(f"{k} missing" for k in diff.missing)][:4])
        raise DataError(
            path,
            f"is not the batch the run was calibrated on ({what})",
            "Give the original batch with --batch, or calibrate this one",
        )
    if recorded and Path(recorded).resolve() != Path(path).resolve():
        notes.append(f"the batch moved from {recorded} to {path} (its files are the ones the run was calibrated on)")
    later = compare_inputs(inputs, now, only=lambda k: not key(k))
    if not later.same:
        notes.append(
            "validation runs "
            + "; ".join(
                f"{label} since the calibration: {', '.join(files[:3])}"
                for label, files in (("changed", later.changed), ("added", later.added), ("removed", later.missing))
                if files
            )
        )
    return batch, notes
