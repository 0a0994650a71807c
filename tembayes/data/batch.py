"""A batch folder (``docs/data-format.md``, 'The batch folder'): ``batch.toml`` plus one folder per module."""

from __future__ import annotations

import difflib
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from ..constants import KELVIN
from ..errors import DataError, ModelError
from .experiment import Experiment, load_experiment
from .preflight import ERROR, check_experiment

if TYPE_CHECKING:
    from ..physics.layout import Layout

__all__ = [
    "Datasheet",
    "Module",
    "LazyModule",
    "Batch",
    "load_batch",
    "load_batch_toml",
    "load_population_table",
    "natural_key",
    "file_stem",
    "BATCH_TOML",
    "IDENTIFICATION_CSV",
    "DEFAULT_RIG_CONFIG",
]

BATCH_TOML = "batch.toml"
IDENTIFICATION_CSV = "identification.csv"
#: The rig used when ``batch.toml`` has no ``[rig]`` table.
DEFAULT_RIG_CONFIG = {"preset": "reference"}

#: ``[population]`` keys: the unit-to-unit spread of each law parameter
#: (levels relative, slopes in SI), as known for the module type.
POPULATION_SPREAD_KEYS = ("spread_R0_rel", "spread_R1_ohm_per_K", "spread_S0_rel", "spread_S1_V_per_K2", "spread_K_rel")
#: Log-sd of a stated spread when ``spread_log_sd`` is not given.
DEFAULT_SPREAD_LOG_SD = 0.3

#: Plausible datasheet hot-side temperatures [degC].
TH_MIN_C = -50.0
TH_MAX_C = 150.0
#: Qmax implied by Vmax, Imax (and Th, dTmax) within this factor of the stated one.
QMAX_RATIO_MAX = 3.0
#: Tables batch.toml may hold.
BATCH_TABLES = ("module_type", "rig", "population")

# toml key -> (Datasheet attribute, unit for messages)
_DATASHEET_KEYS = {
    "th_C": ("th", "degC"),
    "imax_A": ("imax", "A"),
    "vmax_V": ("vmax", "V"),
    "dtmax_K": ("dtmax", "K"),
    "qmax_W": ("qmax", "W"),
}


def natural_key(name: str) -> tuple[tuple[int | str, ...], str]:
    """Sort key that orders embedded numbers by value (TEM2 before TEM10).

    Parameters
    ----------
    name : str
        A module id or file name (compare stems: ``validation`` sorts before
        ``validation2``).

    Returns
    -------
    tuple
        Alternating text and integer parts; the original name breaks ties.
    """
    parts = re.split(r"(\d+)", name.casefold())
    # re.split with a group alternates text/number, so positions never mix types.
    return tuple(int(p) if i % 2 else p for i, p in enumerate(parts)), name


@dataclass(frozen=True)
class Datasheet:
    """Datasheet figures of a module type, in SI units.

    Attributes
    ----------
    name : str
        Free-text module type name.
    th : float
        Hot-side temperature of the datasheet figures [K].
    imax : float
        Maximum current [A].
    vmax : float
        Voltage at ``imax`` [V].
    dtmax : float
        Maximum temperature difference [K].
    qmax : float
        Maximum heat pumped [W].
    """

    name: str
    th: float
    imax: float
    vmax: float
    dtmax: float
    qmax: float

    def seebeck(self) -> float:
        """Module Seebeck coefficient ``S = Vmax / Th`` [V/K]."""
        return self.vmax / self.th

    def resistance(self) -> float:
        """Module electrical resistance ``R = (Th - dTmax) Vmax / (Th Imax)`` [ohm]."""
        return (self.th - self.dtmax) * self.vmax / (self.th * self.imax)

    def conductance(self) -> float:
        """Module thermal conductance ``K = (Th - dTmax) Vmax Imax / (2 Th dTmax)`` [W/K]."""
        return (self.th - self.dtmax) * self.vmax * self.imax / (2.0 * self.th * self.dtmax)

    def to_table(self) -> dict:
        """The ``[module_type]`` table with contract keys and CSV units.

        Returns
        -------
        dict
            ``name``, ``th_C`` [degC], ``imax_A``, ``vmax_V``, ``dtmax_K``,
            ``qmax_W``.
        """
        return {
            "name": self.name,
            # round away the K -> degC float residue (298.15 - 273.15 != 25.0 exactly)
            "th_C": round(self.th - KELVIN, 9),
            "imax_A": self.imax,
            "vmax_V": self.vmax,
            "dtmax_K": self.dtmax,
            "qmax_W": self.qmax,
        }

    @classmethod
    def from_table(cls, table: dict, path: Path | str) -> "Datasheet":
        """Build from a ``[module_type]`` table, validating it.

        Parameters
        ----------
        table : dict
            Contract keys ``name`` (free text, optional), ``th_C`` [degC],
            ``imax_A`` [A], ``vmax_V`` [V], ``dtmax_K`` [K], ``qmax_W`` [W];
            any other key is refused with the nearest known name.
        path : str or Path
            The ``batch.toml`` the table came from (for messages).

        Returns
        -------
        Datasheet

        Raises
        ------
        DataError
            Naming ``path`` and the offending key.
        """
        path = Path(path)
        if not isinstance(table, dict):
            raise DataError(
                path, "'module_type' must be a table", "Write it as a [module_type] section", column="module_type"
            )
        _refuse_unknown(path, table, ("name", *_DATASHEET_KEYS), "module_type.")
        name = table.get("name", "")
        if not isinstance(name, str):
            raise DataError(
                path,
                f"module_type.name must be text, found {name!r}",
                'Quote it, e.g. name = "TEC1-12706"',
                column="name",
            )
        values = {}
        for key, (attr, unit) in _DATASHEET_KEYS.items():
            if key not in table:
                raise DataError(
                    path, f"[module_type] has no {key!r}", f"Add {key} = <datasheet value in {unit}>", column=key
                )
            v = table[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise DataError(
                    path,
                    f"{key} = {v!r} is not a finite number",
                    f"Give the datasheet value as a plain number in {unit}",
                    column=key,
                )
            if key != "th_C" and v <= 0:
                raise DataError(
                    path, f"{key} = {v!r} must be positive", f"Give the datasheet value in {unit}", column=key
                )
            values[attr] = float(v)
        if not TH_MIN_C <= values["th"] <= TH_MAX_C:
            kelvin = TH_MIN_C + KELVIN <= values["th"] <= TH_MAX_C + KELVIN
            raise DataError(
                path,
                f"th_C = {table['th_C']!r} is not a plausible datasheet hot-side temperature in "
                f"degC ({TH_MIN_C:g}..{TH_MAX_C:g})" + (": it looks like kelvin" if kelvin else ""),
                f"Give it in degC (e.g. {values['th'] - KELVIN:.4g})"
                if kelvin
                else "Give the datasheet's hot-side temperature in degC (usually 25 or 50)",
                column="th_C",
            )
        values["th"] += KELVIN
        if values["dtmax"] >= values["th"]:
            raise DataError(
                path,
                f"dtmax_K = {table['dtmax_K']!r} is not below Th = {values['th']:.2f} K",
                "Check dtmax_K (kelvin) and th_C (degC) against the datasheet",
                column="dtmax_K",
            )
        sheet = cls(name=name, **values)
        sheet._check_consistency(path)
        return sheet

    def qmax_expected(self) -> float:
        """Qmax [W] the other figures imply: ``S Imax Th - R Imax^2 / 2`` (zero dT, standard conversions)."""
        return self.vmax * self.imax * (self.th + self.dtmax) / (2.0 * self.th)

    def _check_consistency(self, path):
        """Refuse figures whose units disagree (mA, mV, kW): Qmax must match the other figures' order."""
        ratio = self.qmax_expected() / self.qmax
        if 1.0 / QMAX_RATIO_MAX <= ratio <= QMAX_RATIO_MAX:
            return
        if ratio > 1:  # a figure in Vmax x Imax too large, or Qmax too small
            suspects = [
                (k, u)
                for k, u, off in (
                    ("imax_A", "mA", self.imax > 100),
                    ("vmax_V", "mV", self.vmax > 1000),
                    ("qmax_W", "kW", self.qmax < 1),
                )
                if off
            ]
        else:
            suspects = [("qmax_W", "mW")] if self.qmax > 1e4 else []
        keys = [k for k, _ in suspects] or ["imax_A", "vmax_V", "qmax_W"]
        raise DataError(
            path,
            f"the datasheet figures disagree by a factor {ratio:.3g}: Vmax x Imax (with Th, "
            f"dTmax) implies Qmax = {self.qmax_expected():.4g} W, the table says {self.qmax:g} W",
            "Check the unit of "
            + (", ".join(f"{k} ({u}?)" for k, u in suspects) if suspects else "imax_A [A], vmax_V [V] and qmax_W [W]"),
            column=keys[0],
        )


@dataclass(frozen=True, eq=False)
class Module:
    """One module's experiments.

    Attributes
    ----------
    id : str
        The module folder's name.
    path : Path
        The module folder.
    identification : Experiment
        ``identification.csv``, the current staircase.
    validations : tuple of Experiment
        ``validation*.csv`` in natural order (validation, validation2, ...,
        validation10).
    """

    id: str
    path: Path
    identification: Experiment
    validations: tuple = ()


@dataclass(frozen=True, eq=False)
class LazyModule:
    """A module folder that reads its experiments when asked (large batches).

    Same attributes as :class:`Module`; each access of ``identification`` or
    ``validations`` reads the CSVs again and nothing is kept, so a batch of
    thousands of modules holds only their paths.  :func:`load_batch` with
    ``lazy=True`` has read (validated) every file once before it returns one.

    Attributes
    ----------
    id : str
    path : Path
        The module folder.
    datasheet : Datasheet
        The module type (the CSVs' unit checks).
    validation_files : tuple of Path
    layout : tembayes.physics.layout.Layout, optional
        The batch's rig columns; default the reference rig's.
    """

    id: str
    path: Path
    datasheet: "Datasheet"
    validation_files: tuple = ()
    layout: "Layout | None" = None

    @property
    def identification(self) -> Experiment:
        """The identification experiment, read from disk on each access."""
        return load_experiment(self.path / IDENTIFICATION_CSV, datasheet=self.datasheet, layout=self.layout)

    @property
    def validations(self) -> tuple:
        """The validation experiments, read from disk on each access."""
        return tuple(load_experiment(p, datasheet=self.datasheet, layout=self.layout) for p in self.validation_files)

    def load(self) -> Module:
        """The module with its experiments in memory."""
        return Module(id=self.id, path=self.path, identification=self.identification, validations=self.validations)


@dataclass(frozen=True, eq=False)
class Batch:
    """A loaded batch folder.

    Attributes
    ----------
    path : Path
        The batch folder.
    datasheet : Datasheet
        From ``[module_type]``.
    rig_config : dict
        The ``[rig]`` table: a shipped rig's ``preset`` (``"reference"``
        when absent) or a rig ``file`` (its absolute path), and parameter
        overrides.
    modules : dict of str to Module
        In natural order of the ids (TEM1, TEM2, TEM10).
    population : dict
        The optional ``[population]`` table: known unit-to-unit spreads of the
        type, ``spread_... -> (median, log_sd)`` (:func:`load_population_table`).
    findings : tuple of tembayes.data.preflight.Finding
        The preflight's warnings on the experiments (errors too when loaded
        with ``strict=False``).
    layout : tembayes.physics.layout.Layout
        The rig's columns and where its sensors sit (the reference rig's
        when not given).
    """

    path: Path
    datasheet: Datasheet
    rig_config: dict = field(default_factory=lambda: dict(DEFAULT_RIG_CONFIG))
    modules: dict = field(default_factory=dict)
    population: dict = field(default_factory=dict)
    findings: tuple = ()
    layout: "Layout | None" = None

    def __post_init__(self):
        if self.layout is None:
            object.__setattr__(self, "layout", _check_rig(self.path, self.rig_config))


def load_batch_toml(path: Path | str) -> tuple[Datasheet, dict]:
    """Read and validate ``batch.toml``.

    Parameters
    ----------
    path : str or Path
        The ``batch.toml`` file, or the batch folder holding it.

    Returns
    -------
    datasheet : Datasheet
    rig_config : dict
        The ``[rig]`` table: ``preset`` (default ``"reference"``) or ``file``
        (made absolute), and parameter overrides.

    Raises
    ------
    DataError
        Naming the file, the TOML line for syntax errors, and the key.
    """
    return _tables(*_read_batch_toml(path))[:2]


def _read_batch_toml(path):
    """``(path, parsed document)`` of a batch.toml (or its folder).

    Refuses a missing, unreadable, non-UTF-8 or malformed file.
    """
    path = Path(path)
    if path.is_dir():
        path = path / BATCH_TOML
    if not path.is_file():
        raise DataError(
            path,
            "batch.toml does not exist",
            "Every batch folder needs a batch.toml with a [module_type] table (see docs/data-format.md, 'batch.toml')",
        )
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise DataError(path, f"the file cannot be read ({e.strerror or e})", "Check the file's permissions") from None
    try:
        doc = tomllib.loads(raw.decode("utf-8-sig"))
    except UnicodeDecodeError:
        raise DataError(path, "the file is not UTF-8 text", "Save batch.toml as UTF-8") from None
    except tomllib.TOMLDecodeError as e:
        m = re.search(r"line (\d+)", str(e))
        raise DataError(
            path, f"TOML syntax error ({e})", "Fix the TOML syntax", line=int(m.group(1)) if m else None
        ) from None
    return path, doc


def _nearest(name, known):
    """``", did you mean 'x'"`` for the closest known name, or ``""``."""
    match = difflib.get_close_matches(str(name), [str(k) for k in known], n=1, cutoff=0.6)
    return f" (did you mean '{match[0]}'?)" if match else ""


def _refuse_unknown(path, table, known, prefix=""):
    """Refuse the first key of ``table`` not in ``known``, naming the nearest known one."""
    for key in table:
        if key not in known:
            raise DataError(
                path,
                f"unknown key '{prefix}{key}'{_nearest(key, known)}",
                f"Use one of {', '.join(known)}, or delete it",
                column=key,
            )


def _tables(path, doc):
    """``[module_type]`` and ``[rig]`` of a parsed batch.toml, validated."""
    for key in doc:
        if key not in BATCH_TABLES:
            raise DataError(
                path,
                f"unknown table '[{key}]'{_nearest(key, BATCH_TABLES)}",
                f"batch.toml holds the tables {', '.join(BATCH_TABLES)}; rename or delete it",
                column=key,
            )
    if "module_type" not in doc:
        raise DataError(
            path,
            "there is no [module_type] table",
            "Add [module_type] with name, th_C, imax_A, vmax_V, dtmax_K, qmax_W from the module's datasheet",
            column="module_type",
        )
    datasheet = Datasheet.from_table(doc["module_type"], path)

    rig = doc.get("rig", None)
    if rig is None:
        rig_config = dict(DEFAULT_RIG_CONFIG)
    else:
        if not isinstance(rig, dict):
            raise DataError(
                path,
                "'rig' must be a table",
                'Write it as a [rig] section, e.g. [rig] preset = "reference"',
                column="rig",
            )
        rig_config = _rig_source(path, dict(rig))
    return datasheet, rig_config, _check_rig(path, rig_config)


def load_population_table(path: Path | str) -> dict:
    """The optional ``[population]`` table of ``batch.toml``: spreads known for the type.

    With few modules the unit-to-unit spreads cannot be learned from the
    batch itself; a spread known from earlier batches of the type (e.g. the
    ``population_spreads`` of an earlier run's ``summary.json``) sharpens the
    population and ``outlier_prob``.  Keys: any of
    :data:`POPULATION_SPREAD_KEYS` (the spread's median: levels relative,
    slopes in SI units) and ``spread_log_sd`` (its uncertainty, default 0.3)::

        [population]
        spread_S0_rel = 0.01
        spread_R0_rel = 0.02
        spread_log_sd = 0.3

    Returns
    -------
    dict
        ``spread key -> (median, log_sd)``; empty without the table.

    Raises
    ------
    DataError
        Naming the file and the key at fault.
    """
    return _population(*_read_batch_toml(path))


def _population(path, doc):
    table = doc.get("population")
    if table is None:
        return {}
    if not isinstance(table, dict):
        raise DataError(path, "'population' must be a table", "Write it as a [population] section", column="population")
    allowed = POPULATION_SPREAD_KEYS + ("spread_log_sd",)
    _refuse_unknown(path, table, allowed, "population.")
    values = {}
    for key, v in table.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise DataError(
                path,
                f"population.{key} must be a positive number, found {v!r}",
                "Give the spread as a number, e.g. 0.01 for 1 %",
                column=key,
            )
        values[key] = float(v)
    log_sd = values.pop("spread_log_sd", DEFAULT_SPREAD_LOG_SD)
    return {k: (v, log_sd) for k, v in values.items()}


def _rig_source(path: Path, rig_config: dict) -> dict:
    """``preset`` (the default) or ``file``, made absolute: a rig file sits next to batch.toml."""
    if "file" not in rig_config:
        rig_config.setdefault("preset", DEFAULT_RIG_CONFIG["preset"])
    key = "file" if "file" in rig_config else "preset"
    if not isinstance(rig_config[key], str):
        raise DataError(
            path,
            f"rig.{key} must be text, found {rig_config[key]!r}",
            'Quote it, e.g. preset = "reference" or file = "rig.toml"',
            column=key,
        )
    if key == "file":
        rig_config["file"] = str((path.parent / rig_config["file"]).resolve())
    return rig_config


def _check_rig(path: Path, rig_config: dict) -> Layout:
    """The layout of the rig ``[rig]`` asks for; a rig that cannot be read refuses batch.toml."""
    from ..physics.rigread import rig_from_config  # lazy: physics is heavier than data

    try:
        return rig_from_config(rig_config).layout
    except ModelError as e:
        raise DataError(
            path, str(e), "Fix the [rig] table (or remove it to use the reference rig)", column="rig"
        ) from None


def file_stem(module_id: str) -> str:
    """The name a module's files get in every output (corner plots, export keys): letters, digits, ``_``."""
    return re.sub(r"[^A-Za-z0-9_]", "_", str(module_id)) or "_"


def _refuse_colliding_ids(path, ids):
    """Module ids that would share an output file name (``TEM 1``/``TEM_1``; case-blind file systems)."""
    seen = {}
    for mid in ids:
        key = file_stem(mid).casefold()
        if key in seen:
            raise DataError(
                path,
                f"the module folders '{seen[key]}' and '{mid}' would share output file names ('{file_stem(mid)}')",
                "Rename one of them (letters, digits and '_' keep ids apart)",
            )
        seen[key] = mid


def load_batch(path: Path | str, *, lazy: bool = False, strict: bool = True) -> Batch:
    """Load and validate a batch folder (``docs/data-format.md``, 'The batch folder').

    Parameters
    ----------
    path : str or Path
        The batch folder: ``batch.toml`` and one sub-folder per module, each
        with ``identification.csv`` and zero or more ``validation*.csv``.
        Hidden folders and ``__pycache__`` are not modules.
    lazy : bool
        Validate every file, then keep only the paths: the modules are
        :class:`LazyModule` and read their CSVs when used (memory independent
        of the batch size).
    strict : bool
        Refuse the batch on the first error-level preflight finding
        (:mod:`tembayes.data.preflight`); False keeps every finding in
        ``Batch.findings`` (``tembayes inspect``).

    Returns
    -------
    Batch
        Modules in natural order of their ids; experiments in SI units;
        ``findings`` holds the preflight's warnings (and errors, if not strict).

    Raises
    ------
    DataError
        Naming the folder or file at fault and what to do.
    """
    path = Path(path)
    if not path.exists():
        raise DataError(path, "the batch folder does not exist", "Check the path")
    if not path.is_dir():
        raise DataError(
            path, "this is not a folder", "Pass the batch folder (the one holding batch.toml and the module folders)"
        )
    toml = _read_batch_toml(path / BATCH_TOML)
    datasheet, rig_config, layout = _tables(*toml)
    population = _population(*toml)

    folders = sorted(
        (p for p in path.iterdir() if p.is_dir() and not p.name.startswith(".") and p.name != "__pycache__"),
        key=lambda p: natural_key(p.name),
    )
    if not folders:
        raise DataError(
            path,
            "the batch folder has no module folders",
            "Put each module's experiments in its own sub-folder (e.g. TEM1/identification.csv)",
        )
    _refuse_colliding_ids(path, [f.name for f in folders])
    modules, findings = {}, []
    for folder in folders:
        ident = folder / IDENTIFICATION_CSV
        if not ident.is_file():
            raise DataError(
                folder,
                "the module folder has no identification.csv",
                "Each module folder needs identification.csv (move other folders out of the batch folder)",
            )
        validation_files = tuple(
            sorted(
                (p for p in folder.glob("validation*.csv") if p.is_file()),
                key=lambda p: natural_key(p.stem),
            )
        )
        module = Module(
            id=folder.name,
            path=folder,
            identification=load_experiment(ident, datasheet=datasheet, layout=layout),
            validations=tuple(load_experiment(p, datasheet=datasheet, layout=layout) for p in validation_files),
        )
        for exp in (module.identification, *module.validations):
            found = check_experiment(
                exp, datasheet=datasheet, identification=exp is module.identification, layout=layout
            )
            if strict and any(f.severity == ERROR for f in found):
                raise next(f for f in found if f.severity == ERROR).error()
            findings += found
        # lazy: the files were read (validated) above, and are dropped here
        modules[folder.name] = (
            LazyModule(
                id=folder.name, path=folder, datasheet=datasheet, validation_files=validation_files, layout=layout
            )
            if lazy
            else module
        )
    return Batch(
        path=path,
        datasheet=datasheet,
        rig_config=rig_config,
        modules=modules,
        population=population,
        findings=tuple(findings),
        layout=layout,
    )
