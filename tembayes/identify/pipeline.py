"""The deterministic identification of a batch (``tembayes identify``).

Per module:

1. detect the current steps of the identification run;
2. at each step, R from the extrapolated voltage jump (and the paper's
   first-sample R); at the end of each hold, the steady state;
3. junction temperatures at each hold end from the rig network (pass 1:
   nominal rig values);
4. R(T) fitted to the jumps, then S = (V - R(T) I) / dT at each hold end,
   S(T) fitted -- the corrected method; the paper's method in parallel
   (sensor dT across the module's face sensors, T2 - T3 on the reference
   rig, their mean, first-sample R);
5. the rig fit (thermal parameters and K, laws fixed), then pass 2 of 3-4
   with the fitted rig values, and the rig fit again with the final laws;
6. validation runs simulated with (a) R, S constant at 35 degC (its own rig
   fit) and (b) the linear laws: RMSE and max error per sensor.

Everything is returned as plain objects; :mod:`tembayes.identify.report`
turns them into ``identify.json`` and :mod:`tembayes.plots.identify` into
figures.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from tembayes.constants import KELVIN, LAW_PARAMETERS, MODULE_PARAMETERS
from tembayes.data.preflight import TAVG_SPAN_MIN_K
from tembayes.data.steps import detect_steps
from tembayes.errors import DataError, ModelError
from tembayes.identify.estimates import hold_end, jump_resistance, junction_temperatures
from tembayes.identify.fits import LineFit, fit_line, hysteresis
from tembayes.identify.rigfit import RigFit, constant_laws, fit_rig, validation_errors
from tembayes.physics.rigread import rig_from_config

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping

    from tembayes.data import Batch, Datasheet, Experiment, LazyModule, Module
    from tembayes.physics.rig import RigDescription

#: Holds whose junction temperature difference is smaller than this give no
#: usable S (V_S / dT with dT near zero) [K].
MIN_DT_FOR_S = 2.0


@dataclass(frozen=True)
class ModuleIdentification:
    """Everything the step method finds for one module (SI inside).

    Attributes
    ----------
    module : str
    steps : list of dict
        One row per step (the ``steps`` table of docs/outputs.md,
        'identify.json (identify)'; CSV units at the edges are added when
        written).
    lines : dict of LineFit
        ``R``, ``S`` (corrected), ``R_paper``, ``S_paper``.
    hysteresis : dict
        ``R`` and ``S``: up- minus down-step residuals.
    rig_fit : RigFit
        With the linear laws.
    rig_fit_constant : RigFit
        With R, S constant at 35 degC.
    validation : dict
        File name -> {"linear": errors, "constant": errors}.
    """

    module: str
    steps: list
    lines: dict
    hysteresis: dict
    rig_fit: RigFit
    rig_fit_constant: RigFit
    validation: dict = field(default_factory=dict)

    @property
    def fit(self) -> dict[str, float]:
        """Law parameters of the corrected method (SI)."""
        return _laws(self.lines["R"], self.lines["S"])

    @property
    def fit_sd(self) -> dict[str, float]:
        """Standard errors of :attr:`fit` (SI)."""
        return _law_sds(self.lines["R"], self.lines["S"])

    @property
    def fit_paper(self) -> dict[str, float]:
        """Law parameters of the paper's literal recipe (SI)."""
        return _laws(self.lines["R_paper"], self.lines["S_paper"])

    @property
    def fit_paper_sd(self) -> dict[str, float]:
        """Standard errors of :attr:`fit_paper` (SI)."""
        return _law_sds(self.lines["R_paper"], self.lines["S_paper"])


def _laws(R: LineFit, S: LineFit):
    return {"R0_ohm": R.a, "R1_ohm_per_K": R.b, "S0_V_per_K": S.a, "S1_V_per_K2": S.b}


def _law_sds(R: LineFit, S: LineFit):
    return {"R0_ohm": R.a_sd, "R1_ohm_per_K": R.b_sd, "S0_V_per_K": S.a_sd, "S1_V_per_K2": S.b_sd}


def _step_table(exp, rig, rig_values=None, rig_sds=None, *, seed=0):
    """Per-step raw estimates (everything that does not need the laws)."""
    steps = detect_steps(exp.time, exp.current)
    if len(steps) < 3:
        raise ModelError(f"{exp.path}: found {len(steps)} current steps; the step method needs a staircase")
    rows = []
    ends = {}
    for st in steps:
        jump = jump_resistance(exp.time, exp.voltage, exp.current, st)
        for a, b in ((st.prev_start, st.index), (st.hold_start, st.hold_end)):
            if (a, b) not in ends:
                ss = hold_end(exp, a, b, face=rig.layout.face)
                # the same seed for every hold: shared rig-value draws, so the
                # draws carry the correlation between holds
                (th, tc), (sh, sc), (dh, dc) = junction_temperatures(
                    ss, rig, rig_values, sds=rig_sds, rng=np.random.default_rng(seed)
                )
                ends[(a, b)] = (ss, th, tc, sh, sc, dh, dc)
        prev = ends[(st.prev_start, st.index)]
        this = ends[(st.hold_start, st.hold_end)]
        ss = this[0]
        rows.append(
            {
                "t_s": st.t,
                "dI_A": st.dI,
                "direction": st.direction,
                "jump": jump,
                # state at the step instant: the end of the previous hold
                "Tavg_R": 0.5 * (prev[1] + prev[2]),
                "Tavg_R_sd": 0.5 * float(np.hypot(prev[3], prev[4])),
                "Tavg_R_paper": 0.5 * (prev[0].face_T[0] + prev[0].face_T[1]),
                # state at the end of this hold
                "steady": ss,
                "Th": this[1],
                "Tc": this[2],
                "Th_sd": this[3],
                "Tc_sd": this[4],
                "Tavg": 0.5 * (this[1] + this[2]),
                "dT": this[1] - this[2],
                "dT_sd": float(np.hypot(this[3], this[4])),
                "Th_draws": this[5],
                "Tc_draws": this[6],
                "Tavg_paper": 0.5 * (ss.face_T[0] + ss.face_T[1]),
                "dT_paper": ss.face_T[0] - ss.face_T[1],
            }
        )
    return rows


def _refuse_flat(exp, rows):
    """A run whose holds span too little mean temperature for a line through R(T) and S(T)."""
    tavg = [r["Tavg"] for r in rows]
    span = max(tavg) - min(tavg)
    if span < TAVG_SPAN_MIN_K:
        raise DataError(
            exp.path,
            f"the holds' mean junction temperature spans only {span:.3g} K (the step method needs "
            f"{TAVG_SPAN_MIN_K:g} K for the slopes of R(T) and S(T))",
            "Use larger currents in both directions, or on a rig whose boundaries hold the module's temperature "
            "(liquid-cooled plates) step the boundaries' temperature between holds",
        )


def _laws_from_rows(rows):
    """R and S lines, corrected and paper, from the step table (adds S to the rows)."""
    jR = np.array([r["jump"].R for r in rows])
    jRsd = np.array([r["jump"].R_sd_fit for r in rows])
    jRtime = np.array([r["jump"].R_sd_time for r in rows])
    jRf = np.array([r["jump"].R_first for r in rows])
    R = fit_line([r["Tavg_R"] for r in rows], jR, jRsd, common=jRtime)
    R_paper = fit_line([r["Tavg_R_paper"] for r in rows], jRf)
    n_draws = len(rows[0]["Th_draws"])
    S_draws = []
    for r in rows:
        ss = r["steady"]
        ok = abs(r["dT"]) >= MIN_DT_FOR_S
        if ok:
            vs = ss.voltage - R(r["Tavg"]) * ss.current
            S = vs / r["dT"]
            # independent: the hold's voltage average; correlated between
            # holds: the rig values behind the junction temperatures (shared
            # draws) and the R law
            r["S"] = float(S)
            r["S_sd_indep"] = float(abs(ss.voltage_sd / r["dT"]))
            tavg_d = 0.5 * (r["Th_draws"] + r["Tc_draws"])
            S_draws.append((ss.voltage - R(tavg_d) * ss.current) / (r["Th_draws"] - r["Tc_draws"]))
            sd_R = R.sd(r["Tavg"]) * abs(ss.current) / abs(r["dT"])
            r["S_sd"] = float(np.hypot(np.std(S_draws[-1]), np.hypot(r["S_sd_indep"], sd_R)))
        else:
            r["S"] = r["S_sd"] = r["S_sd_indep"] = np.nan
            S_draws.append(np.full(n_draws, np.nan))
        if abs(r["dT_paper"]) >= MIN_DT_FOR_S:
            r["S_paper"] = float((ss.voltage - R_paper(r["Tavg_paper"]) * ss.current) / r["dT_paper"])
            # the sensor-dT error alone (with the corrected R): isolates the
            # junction-vs-sensor bias from the first-sample R bias
            r["S_sensor_dT"] = float((ss.voltage - R(r["Tavg_paper"]) * ss.current) / r["dT_paper"])
        else:
            r["S_paper"] = r["S_sensor_dT"] = np.nan
    # the R law's own uncertainty enters every S the same way: a common term
    common_R = [R.sd(r["Tavg"]) * r["steady"].current / r["dT"] if np.isfinite(r["S"]) else np.nan for r in rows]
    S = fit_line(
        [r["Tavg"] for r in rows],
        [r["S"] for r in rows],
        [r["S_sd_indep"] for r in rows],
        common=np.nan_to_num(common_R),
        draws=np.nan_to_num(np.array(S_draws).T),
    )
    S_paper = fit_line([r["Tavg_paper"] for r in rows], [r["S_paper"] for r in rows])
    S_sensor = fit_line([r["Tavg_paper"] for r in rows], [r["S_sensor_dT"] for r in rows])
    return {"R": R, "S": S, "R_paper": R_paper, "S_paper": S_paper, "S_sensor_dT": S_sensor}


def step_estimates(
    exp: Experiment,
    rig: RigDescription,
    rig_values: Mapping[str, float] | None = None,
    rig_sds: Mapping[str, float] | None = None,
) -> dict:
    """Per-step R and S of an identification run, with the rig values given (no rig fit).

    The step method of :func:`identify_module`'s second pass: R from each
    voltage jump at the junction mean temperature before the step, S from
    each hold's steady state.  The batch report draws them under the
    posterior laws, with the rig at its posterior mean.

    Parameters
    ----------
    exp : tembayes.data.Experiment
    rig : tembayes.physics.rig.RigDescription
    rig_values, rig_sds : dict, optional
        Rig parameter values and sds (SI); default the rig's nominal values.

    Returns
    -------
    dict
        Arrays over the steps: ``t_s``, ``direction``, ``Tavg_R_C`` [degC],
        ``R_ohm``, ``R_sd``, ``Tavg_S_C`` [degC], ``S_V_per_K``, ``S_sd``
        (NaN where the hold's dT is too small for S).
    """
    rows = _step_table(exp, rig, rig_values, rig_sds)
    _laws_from_rows(rows)  # adds S to the rows
    col = lambda f: np.array([f(r) for r in rows], dtype=float)  # noqa: E731
    return {
        "t_s": col(lambda r: r["t_s"]),
        "direction": np.array([r["direction"] for r in rows]),
        "Tavg_R_C": col(lambda r: r["Tavg_R"]) - KELVIN,
        "R_ohm": col(lambda r: r["jump"].R),
        "R_sd": col(lambda r: np.hypot(r["jump"].R_sd_fit, r["jump"].R_sd_time)),
        "Tavg_S_C": col(lambda r: r["Tavg"]) - KELVIN,
        "S_V_per_K": col(lambda r: r["S"]),
        "S_sd": col(lambda r: r["S_sd"]),
    }


def identify_module(
    module: Module | LazyModule,
    datasheet: Datasheet,
    *,
    rig_config: dict | None = None,
    leg_cells: int = 0,
    rig_fit_options: dict | None = None,
    progress: Callable[[str], None] | None = None,
) -> ModuleIdentification:
    """Run the deterministic step method on one module.

    Parameters
    ----------
    module : tembayes.data.Module
    datasheet : tembayes.data.Datasheet
        Seeds the module conductance K for the rig fit.
    rig_config : dict, optional
        The batch's ``[rig]`` table.
    leg_cells : int
        Model resolution of the module's legs for the rig fit and validation
        (0 = the paper's lumped module).
    rig_fit_options : dict, optional
        Extra keyword arguments of :func:`tembayes.identify.rigfit.fit_rig`.
    progress : callable, optional

    Returns
    -------
    ModuleIdentification
    """
    say = progress or (lambda msg: None)
    rig = rig_from_config(rig_config or {}, leg_cells=leg_cells)
    exp = module.identification
    say(f"identify: {module.id} steps and pass 1")
    rows = _step_table(exp, rig)
    _refuse_flat(exp, rows)
    lines = _laws_from_rows(rows)
    say(f"identify: {module.id} rig fit")
    opts = dict(rig_fit_options or {})
    rf = fit_rig(exp, _laws(lines["R"], lines["S"]), rig=rig, K0=datasheet.conductance(), **opts)
    rig_values = {k: v for k, v in rf.values.items() if k in rig.parameter_names}
    rig_sds = {k: v for k, v in rf.sd.items() if k in rig.parameter_names}
    say(f"identify: {module.id} pass 2 with the fitted rig")
    rows = _step_table(exp, rig, rig_values, rig_sds)
    lines = _laws_from_rows(rows)
    laws = _laws(lines["R"], lines["S"])
    rf = fit_rig(exp, laws, rig=rig, K0=datasheet.conductance(), **opts)
    const = constant_laws(laws)
    rf_const = fit_rig(exp, const, rig=rig, K0=datasheet.conductance(), **opts)
    hyst = {
        "R": hysteresis(
            [r["Tavg_R"] for r in rows],
            [r["jump"].R for r in rows],
            [r["jump"].R_sd_fit for r in rows],
            [r["direction"] for r in rows],
            common=[r["jump"].R_sd_time for r in rows],
        ),
        "S": hysteresis(
            [r["Tavg"] for r in rows], [r["S"] for r in rows], [r["S_sd"] for r in rows], [r["direction"] for r in rows]
        ),
    }
    validation = {}
    for v in module.validations:
        say(f"identify: {module.id} validation {v.path.name}")
        validation[v.path.name] = {
            "linear": validation_errors(v, laws, rf.values, rig=rig),
            "constant": validation_errors(v, const, rf_const.values, rig=rig),
        }
    return ModuleIdentification(module.id, rows, lines, hyst, rf, rf_const, validation)


def identify_batch(
    batch: Batch, *, leg_cells: int = 0, progress: Callable[[str], None] | None = None
) -> dict[str, ModuleIdentification]:
    """Run :func:`identify_module` on every module of a batch.

    Returns
    -------
    dict
        Module id -> ModuleIdentification.
    """
    return {
        mid: identify_module(m, batch.datasheet, rig_config=batch.rig_config, leg_cells=leg_cells, progress=progress)
        for mid, m in batch.modules.items()
    }


def batch_average(results: Mapping[str, ModuleIdentification]) -> dict[str, float]:
    """The batch's average laws (the paper's dashed line): mean and spread of the module fits."""
    out = {}
    for k in LAW_PARAMETERS:
        vals = np.array([r.fit[k] for r in results.values()])
        out[k] = float(vals.mean())
        out[k + "_spread"] = float(vals.std(ddof=1)) if len(vals) > 1 else 0.0
    ks = np.array([r.rig_fit.values["K_W_per_K"] for r in results.values()])
    out["K_W_per_K"] = float(ks.mean())
    out["K_W_per_K_spread"] = float(ks.std(ddof=1)) if len(ks) > 1 else 0.0
    return out


def to_json(results: Mapping[str, ModuleIdentification], batch: Batch) -> dict:
    """The ``identify.json`` document (docs/outputs.md, 'identify.json (identify)') for a batch."""

    def c(T):
        return None if not np.isfinite(T) else float(T - KELVIN)

    def num(x):
        return None if x is None or not np.isfinite(x) else float(x)

    modules = {}
    for mid, r in results.items():
        steps = []
        for row in r.steps:
            steps.append(
                {
                    "t_s": row["t_s"],
                    "dI_A": row["dI_A"],
                    "direction": row["direction"],
                    "Tavg_C": c(row["Tavg"]),
                    "R_ohm": row["jump"].R,
                    "S_V_per_K": num(row["S"]),
                    "R_sd_ohm": row["jump"].R_sd,
                    "S_sd_V_per_K": num(row["S_sd"]),
                    "Tavg_R_C": c(row["Tavg_R"]),
                    "dT_K": row["dT"],
                    "dT_sd_K": row["dT_sd"],
                    "T_hot_C": c(row["Th"]),
                    "T_cold_C": c(row["Tc"]),
                    "current_A": row["steady"].current,
                    "voltage_V": row["steady"].voltage,
                    "steady_drift_K_per_s": row["steady"].drift,
                    "paper": {
                        "R_ohm": row["jump"].R_first,
                        "Tavg_R_C": c(row["Tavg_R_paper"]),
                        "Tavg_C": c(row["Tavg_paper"]),
                        "dT_K": row["dT_paper"],
                        "S_V_per_K": num(row["S_paper"]),
                    },
                }
            )
        modules[mid] = {
            "fit": r.fit | {"K_W_per_K": r.rig_fit.values["K_W_per_K"]},
            "fit_sd": r.fit_sd | {"K_W_per_K": r.rig_fit.sd["K_W_per_K"]},
            "fit_sd_note": "R: jump fits plus the step-time error shared by all steps of the run; S: hold "
            "averages plus the rig values and R law shared by all holds (propagated, not "
            "weighted); both scaled up by the scatter when it exceeds them",
            "fit_paper": r.fit_paper,
            "fit_paper_sd": r.fit_paper_sd,
            "fit_quality": {k: {"chi2_red": v.chi2_red, "n": v.n} for k, v in r.lines.items()},
            "steps": steps,
            "hysteresis": r.hysteresis,
            "rig_fit": {
                "values": r.rig_fit.values,
                "sd": r.rig_fit.sd,
                "rmse": r.rig_fit.rmse,
                "success": r.rig_fit.success,
                "sd_note": "statistical only (noise and residual autocorrelation); the model's own "
                "error (lumped module vs real legs) is not in it and can be larger",
            },
            "rig_fit_constant_35C": {"values": r.rig_fit_constant.values, "rmse": r.rig_fit_constant.rmse},
            "validation": {
                name: {model: {ch: e for ch, e in errs.items() if ch != "simulation"} for model, errs in v.items()}
                for name, v in r.validation.items()
            },
        }
    hot, cold = (c.removesuffix("_C") for c in batch.layout.face)
    return {
        "tref_C": 25.0,
        "method": {
            "fit": "R from the voltage jump extrapolated to the step instant (c0 + c1 sqrt(tau)); S from the "
            "hold's steady state with junction temperatures reconstructed through the rig network; "
            "weighted linear fits (covariance scaled by the reduced chi-square when > 1)",
            "fit_paper": f"the paper's recipe: R from the first sample after the step, S with sensor dT = {hot} - "
            f"{cold} and sensor T_mean = ({hot} + {cold})/2, unweighted linear fits",
            "Tavg_C": "mean junction temperature at the end of the hold that follows the step (where S is "
            "measured); Tavg_R_C is the one at the step instant (where R is measured)",
            "validation": "RMSE and max |error| per sensor [K] and on the voltage [V]; 'constant' = R, S fixed "
            "at their 35 degC values with their own rig fit (paper Fig. 8), 'linear' = the laws "
            "(Fig. 9)",
        },
        "modules": modules,
        "batch_average": batch_average(results),
        "module_parameters": list(MODULE_PARAMETERS),
        "datasheet": batch.datasheet.to_table(),
    }
