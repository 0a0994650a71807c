"""The data layer (``docs/data-format.md``): experiment CSVs, batch folders, atomic outputs.

Everything loaded here is SI (kelvin, seconds, amperes, volts); degrees
Celsius appear only in the files.  Inputs that break the data format
(docs/data-format.md) or the physics a rig obeys (:mod:`.preflight`) are
refused with a :class:`~tembayes.errors.DataError` naming the file,
line/column and fix.
"""

from .batch import (
    BATCH_TOML,
    DEFAULT_RIG_CONFIG,
    IDENTIFICATION_CSV,
    Batch,
    Datasheet,
    LazyModule,
    Module,
    file_stem,
    load_batch,
    load_batch_toml,
    load_population_table,
    natural_key,
)
from .experiment import TEMP_MAX_C, TEMP_MIN_C, Experiment, load_experiment
from .quality import noise_estimate, summarize_experiment
from .write import (
    DEFAULT_DECIMALS,
    atomic_directory,
    atomic_write_bytes,
    atomic_write_text,
    experiment_from_arrays,
    to_jsonable,
    write_batch_toml,
    write_experiment_csv,
    write_json,
)

__all__ = [
    "Experiment",
    "load_experiment",
    "Datasheet",
    "Module",
    "LazyModule",
    "Batch",
    "load_batch",
    "load_batch_toml",
    "load_population_table",
    "natural_key",
    "file_stem",
    "summarize_experiment",
    "noise_estimate",
    "atomic_write_text",
    "atomic_write_bytes",
    "write_json",
    "to_jsonable",
    "atomic_directory",
    "write_experiment_csv",
    "write_batch_toml",
    "experiment_from_arrays",
    "BATCH_TOML",
    "IDENTIFICATION_CSV",
    "DEFAULT_RIG_CONFIG",
    "DEFAULT_DECIMALS",
    "TEMP_MIN_C",
    "TEMP_MAX_C",
]
