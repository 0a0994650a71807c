"""The fields of the export file: path, shape, unit and meaning of each (``fields`` in every format).

One table serves the file (:func:`fields_table`, written as the ``fields``
entry), the documentation (docs/outputs.md, 'The export file (export)', lists
the same paths; a test checks it) and the readers.  A path joins keys with
``.``; ``<module>`` stands for a module id or ``population``, ``<k>`` for the
operating point's index, ``<parameter>`` for a name of ``parameters``,
``<boundary>`` for a boundary column of the rig.  In NPZ
the ``.`` are ``__``.  Shapes use ``p`` (parameters), ``n`` (states), ``d``
(draws kept), ``b`` (bins of time since a step), ``ns``/``nb`` (the rig's
sensors and boundaries), ``nch = ns + 1`` (outputs); units are SI,
temperatures in K (a deviation in K is one in degC).  Channels are named by
their CSV columns everywhere (the rig's sensor columns and ``voltage_V``;
``current_A`` and the rig's boundary columns) whatever the unit of the values.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Name and version of the export's layout (the ``schema`` entry of every format).
SCHEMA = "tembayes-observer-export/3"

_T5 = "K for the sensors, V for voltage_V"


@dataclass(frozen=True)
class Field:
    """One entry of the export file.

    Attributes
    ----------
    path : str
        Keys joined by ``.``, placeholders in angle brackets.
    shape : str
        ``""`` for a scalar or text, else e.g. ``"(p, p)"``.
    unit : str
        SI unit, ``"1"`` for counts and ratios, ``"text"`` for strings.
    meaning : str
    """

    path: str
    shape: str
    unit: str
    meaning: str


_OP = "modules.<module>.linear.op<k>"
_PN = "modules.<module>.process_noise"

#: Every field of the file, in the order the documentation gives them.
FIELDS = (
    Field("schema", "", "text", f"the layout's name and version, {SCHEMA}"),
    Field("fields", "", "text", "this table: columns path, shape, unit, meaning (string arrays)"),
    Field(
        "parameters",
        "(p,)",
        "text",
        "the order of every vector and matrix over parameters: the five module "
        "parameters, then the rig parameters of the calibration",
    ),
    Field("units", "", "text", "parameter -> its unit"),
    Field("states", "(n,)", "text", "the linear model's states: the rig's node temperatures [K]"),
    Field("inputs", "(1 + nb,)", "text", "current_A, then the rig's boundary columns"),
    Field("input_units", "(1 + nb,)", "text", "units of the inputs' values: A, then K for each boundary"),
    Field("outputs", "(ns + 1,)", "text", "the rig's sensor columns, then voltage_V"),
    Field("output_units", "(ns + 1,)", "text", "units of the outputs' values: K for each sensor, then V"),
    Field("meta.run", "", "text", "the calibration run folder"),
    Field("meta.batch", "", "text", "the batch folder"),
    Field("meta.seed", "", "1", "the seed (held-out predictive of the process noise, population draws)"),
    Field("meta.room_C", "", "degC", "temperature of the room the rig leaks to at the operating points"),
    Field("meta.room_column", "", "text", "the boundary column of that room"),
    Field("meta.points", "(k, 2)", "degC, A", "the operating points (T_avg, current)"),
    Field("meta.tref_C", "", "degC", "reference temperature of the laws"),
    Field("meta.seconds", "", "s", "wall time of the export"),
    Field(
        "meta.module_ids",
        "",
        "text",
        "name in the file -> module id (differs in MAT for ids that are not MATLAB names)",
    ),
    Field(
        "meta.calibrated_range.tavg_C",
        "(2,)",
        "degC",
        "junction mean temperatures every exported module's identification run covered (its step windows)",
    ),
    Field(
        "meta.calibrated_range.current_A",
        "(2,)",
        "A",
        "hold currents every exported module's identification run covered",
    ),
    Field(
        "meta.calibrated_range.boundaries_C.<boundary>",
        "(2,)",
        "degC",
        "temperatures of this boundary column (the rig's) the identification runs saw",
    ),
    Field("meta.calibrated_range.modules", "", "text", "the modules the range is taken over"),
    Field("meta.allow_extrapolation", "", "1", "1 (true) when points outside the calibrated range were allowed"),
    Field(
        "meta.warnings",
        "",
        "text",
        "what the export extrapolates: points outside the calibrated range, boundary "
        "temperatures far from those of the identification runs (empty when none)",
    ),
    Field(
        "modules.<module>.mean",
        "(p,)",
        "units",
        "posterior mean over parameters (the rig anchored on the identification run, as predict does)",
    ),
    Field("modules.<module>.cov", "(p, p)", "units x units", "posterior covariance"),
    Field("modules.<module>.draws", "(d, p)", "units", "posterior draws, evenly thinned (--draws)"),
    Field("modules.<module>.n_posterior", "", "1", "posterior draws behind mean and cov"),
    Field(
        "modules.<module>.measurement_noise_cov",
        "(nch, nch)",
        "K^2, K V, V^2",
        "white sensor noise over the outputs, from the identification run",
    ),
    Field(f"{_PN}.channels", "(nch,)", "text", "the outputs the disturbances are on (as outputs)"),
    Field(f"{_PN}.sd", "(nch,)", _T5, "stationary sd of one Ornstein-Uhlenbeck disturbance per output"),
    Field(f"{_PN}.tau_s", "(nch,)", "s", "its correlation time"),
    Field(f"{_PN}.q_continuous", "(nch,)", "K^2/s, V^2/s", "2 sd^2 / tau_s, the spectral density of its drive"),
    Field(f"{_PN}.source", "", "text", "the residuals it was fitted to: held-out runs, or the identification run"),
    Field(f"{_PN}.corr", "(nch, nch)", "1", "(held-out runs only) the disturbances' correlation across the outputs"),
    Field(f"{_PN}.step_bins_s", "(b,)", "s", "(held-out runs only) lower edges of the bins of time since a step"),
    Field(f"{_PN}.sd_by_time_since_step", "(nch, b)", _T5, "(held-out runs only) the disturbance's sd per bin"),
    Field(f"{_PN}.corr_by_time_since_step", "(b, nch, nch)", "1", "(held-out runs only) corr per bin"),
    Field(f"{_PN}.n_by_time_since_step", "(b,)", "1", "(held-out runs only) samples behind each bin"),
    Field("modules.<module>.input_noise.current_sd_A", "", "A", "white noise of the measured current"),
    Field("modules.<module>.input_noise.sample_interval_s", "", "s", "median sampling interval"),
    Field(
        "modules.<module>.input_noise.step_instant",
        "",
        "text",
        "a step happens at an unknown instant in its sampling interval: current variance dI^2/12 over that interval",
    ),
    Field(
        f"{_OP}.tavg_C",
        "",
        "degC",
        "the point's junction mean temperature (the controlled boundaries are solved to give it)",
    ),
    Field(f"{_OP}.current_A", "", "A", "the point's current"),
    Field(f"{_OP}.x0", "(n,)", "K", "steady node temperatures"),
    Field(f"{_OP}.u0", "(1 + nb,)", "A, then K", "inputs there"),
    Field(f"{_OP}.y0", "(nch,)", "K for the sensors, V", "outputs there"),
    Field(f"{_OP}.A", "(n, n)", "1/s", "d(dx)/dt = A dx + B du"),
    Field(f"{_OP}.B", "(n, 1 + nb)", "K/(s A), then 1/s", "by input column"),
    Field(f"{_OP}.C", "(nch, n)", "1 (T rows), V/K (voltage row)", "dy = C dx + D du"),
    Field(f"{_OP}.D", "(nch, 1 + nb)", "K/A, then 1 (T rows); V/A, then V/K (voltage row)", "by input column"),
    Field(
        f"{_OP}.sensitivity.<parameter>.<X>",
        "as X",
        "unit of X / unit of parameter",
        "derivative of X (A, B, C, D, x0, u0, y0) per unit of the parameter, the point's T_avg and I held",
    ),
)


def fields_table():
    """The ``fields`` entry: ``{"path": [...], "shape": [...], "unit": [...], "meaning": [...]}``."""
    return {k: [getattr(f, k) for f in FIELDS] for k in ("path", "shape", "unit", "meaning")}
