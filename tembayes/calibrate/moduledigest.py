"""What the batch stage needs of a calibrated module, kept next to its file.

Reading a module's ``.nc`` back through arviz costs ~0.3 s, 50 min for 10^4
modules; the batch stage needs only the module's ``summary.json`` entry, why it
would be left out of the population, and a thinned set of its law draws.
``modules/<id>.digest.npz`` holds those, tied to the module file by its size
and modification time.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tembayes.calibrate import results as res
from tembayes.common.draws import thin
from tembayes.data.write import atomic_write_bytes, to_jsonable

if TYPE_CHECKING:
    from tembayes.calibrate.diagnostics import ModuleDiagnostics
    from tembayes.calibrate.module import ModuleCalibration

#: Law draws per module (evenly thinned) handed to the population stage: its
#: Gaussian terms need the moments, its importance check 1000 draws at most;
#: 40 kB per module whatever the sampler kept.
POPULATION_DRAWS = 1000


def exclusion_reason(diagnostics: ModuleDiagnostics) -> str | None:
    """Why a module is left out of the population (None: it is not).

    A module enters the population only if it converged
    (:attr:`~tembayes.calibrate.diagnostics.ModuleDiagnostics.converged`).
    """
    if diagnostics.converged:
        return None
    return (
        f"not converged ({', '.join(diagnostics.reasons())})"
        + f" after {diagnostics.steps} steps; rerun with a larger --max-steps, or --keep-unconverged"
    )


def _digest_path(nc):
    return nc.with_name(nc.stem + ".digest.npz")


def digest_of(r: ModuleCalibration) -> tuple[dict, str | None, np.ndarray, str]:
    """``(summary entry, exclusion reason or None, thinned law draws, rig name)`` of a module calibration."""
    return res.module_entry(r), exclusion_reason(r.diagnostics), thin(r.law_draws(), POPULATION_DRAWS), r.rig


def write_digest(nc: Path, r: ModuleCalibration) -> None:
    """Write the digest of module calibration ``r`` next to its file ``nc``."""
    entry, why, law, rig = digest_of(r)
    st = nc.stat()
    buf = io.BytesIO()
    np.savez(
        buf,
        entry=json.dumps(to_jsonable(entry)),
        why=why or "",
        law=law,
        rig=rig,
        source=np.array([st.st_size, st.st_mtime_ns]),
    )
    atomic_write_bytes(_digest_path(nc), buf.getvalue())


def digest_matches(nc: Path | str) -> bool:
    """Whether the module file ``nc`` is the one its digest was written for (same size and time)."""
    d = _digest_path(Path(nc))
    if not d.exists():
        return False
    st = Path(nc).stat()
    try:
        with np.load(d) as z:
            return list(z["source"]) == [st.st_size, st.st_mtime_ns]
    except (OSError, ValueError, KeyError):
        return False


def read_digest(nc: Path) -> tuple[dict, str | None, np.ndarray, str]:
    """``(entry, why, law, rig)`` of a module file: from its digest if it is the file's, else from the file."""
    if digest_matches(nc):
        with np.load(_digest_path(nc)) as z:
            return json.loads(str(z["entry"])), str(z["why"]) or None, z["law"].copy(), str(z["rig"])
    return digest_of(res.read_module(nc))  # an older run, or a module file replaced since
