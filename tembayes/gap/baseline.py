"""Where: the base model on the held-out data.

The base posterior predicts each validation run (:func:`~tembayes.gap.evidence.evaluate_run`:
its gap map), the base model refitted on each identification run predicts
its step windows one at a time (:func:`~tembayes.gap.evidence.held_out_windows`),
and the rig parameters are checked against their documented ranges
(:mod:`~tembayes.gap.conflicts`).  A gap is wherever either held-out dataset
shows a significant and material cell, or a rig parameter lies outside its
range where it matters (:class:`~tembayes.gap.conflicts.RangeCheck`);
:class:`Baseline` holds all three and what the diagnosis reads off
them: which datasets show a gap, and the module with the largest.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tembayes.gap.conflicts import is_gap
from tembayes.gap.evidence import HeldOut, block_se, elpd_blocks, held_out_gap, held_out_windows, rmse

#: The held-out datasets, in the order the gap is reported on.
DATASETS = ("validation", "identification")


def where_rows(evals):
    """The significant and material cells of some evaluations as ``gap.json`` where-rows, worst first."""
    out = []
    for e in evals:
        for c in e.significant:
            out.append(
                {
                    "channel": c["channel"],
                    "regime": f"{c['family']}: {c['regime']}",
                    "score": c["score"],
                    "module": e.module_id,
                    "run": Path(e.source).name,
                    "p": c["p"],
                    "outside90": c["outside90"],
                }
            )
    return sorted(out, key=lambda c: -c["score"])


def window_rows(windows):
    """The identification windows' cells (``module -> WindowCheck``) as where-rows, worst first."""
    rows = (
        {
            "channel": c["channel"],
            "regime": f"{c['family']}: {c['regime']}",
            "score": c["score"],
            "module": mid,
            "run": "identification (step windows held out)",
            "p": c["p"],
            "outside90": c["outside90"],
        }
        for mid, w in windows.items()
        for c in w.cells
    )
    return sorted(rows, key=lambda c: -c["score"])


def parameter_rows(conflicts):
    """The rig parameters outside their range that matter (``module -> conflict rows``) as where-rows, worst first."""
    out = []
    for mid, rows in conflicts.items():
        for r in rows:
            if is_gap(r):
                out.append(
                    {
                        "channel": r["parameter"],
                        "kind": "parameter",
                        "module": mid,
                        "regime": f"calibrated {r['median']:.4g} {r['unit']}, documented range "
                        f"{r['low']:.4g}-{r['high']:.4g} {r['unit']}",
                        "score": r["outside_sd"],
                    }
                )
    return sorted(out, key=lambda c: -c["score"])


@dataclass(frozen=True)
class Baseline:
    """The base model on the held-out data (:func:`baseline`).

    Attributes
    ----------
    evals : list of RunEvaluation
        Every module's validation runs (their predictions kept, for figures).
    refits : dict
        Module id -> the base model's :class:`~tembayes.gap.which.Refit` of
        its identification run, in the diagnosis's module order.
    windows : dict
        Module id -> its refit's :class:`~tembayes.gap.evidence.WindowCheck` (with cells).
    conflicts : dict
        Module id -> its rig parameters' range-conflict rows (those outside, or straddling, the
        range; a conflict's ``material`` from its range checks).
    where_validation, where_identification, parameter_gaps : list of dict
        The where-rows of the validation runs, the identification windows and the rig parameters.
    """

    evals: list
    refits: dict
    windows: dict
    conflicts: dict
    where_validation: list
    where_identification: list
    parameter_gaps: list

    @property
    def ids(self):
        """The modules diagnosed, in order."""
        return list(self.refits)

    @property
    def has_gap(self):
        """A significant and material cell on either held-out dataset, or a rig parameter out of range that matters."""
        return bool(self.where_validation or self.where_identification or self.parameter_gaps)

    @property
    def gapped(self):
        """The held-out datasets that show a gap, in :data:`DATASETS` order."""
        where = {"validation": self.where_validation, "identification": self.where_identification}
        return [d for d in DATASETS if where[d]]

    @property
    def primary(self):
        """The dataset whose gap ``gap_before``/``gap_after`` report: the first that shows one."""
        gapped = self.gapped
        return gapped[0] if gapped else "validation"

    @property
    def gap(self):
        """:data:`~tembayes.gap.evidence.GAP_METRIC` of every module's validation runs [K]."""
        return held_out_gap(self.evals)

    @property
    def identification_gap(self):
        """:data:`~tembayes.gap.evidence.ID_GAP_METRIC` of every module's windows [noise sds]."""
        return held_out_windows(list(self.refits.values())).gap

    def evals_of(self, module_id):
        """One module's validation runs."""
        return [e for e in self.evals if e.module_id == module_id]

    def held_out(self, module_id=None):
        """The base model's :class:`~tembayes.gap.evidence.HeldOut` terms: one module's, or every module's."""
        if module_id is not None:
            return HeldOut(elpd_blocks(self.evals_of(module_id)), self.refits[module_id].cv_lpd)
        return HeldOut(elpd_blocks(self.evals), np.concatenate([self.refits[m].cv_lpd for m in self.ids]))

    def conflicting(self, module_id):
        """The rig parameters of a module outside their range that matter (:func:`~tembayes.gap.conflicts.is_gap`)."""
        return {r["parameter"] for r in self.conflicts[module_id] if is_gap(r)}

    def lead(self):
        """The module with the largest gap: on the validation runs, else the windows, else the most conflicts."""
        if self.where_validation:
            score = {mid: held_out_gap(self.evals_of(mid)) for mid in self.ids}
        elif self.where_identification:
            score = {mid: self.windows[mid].gap for mid in self.ids}
        else:
            score = {mid: sum(is_gap(r) for r in self.conflicts[mid]) for mid in self.ids}
        return max(self.ids, key=lambda m: score[m])

    def to_json(self):
        """``gap.json``'s ``base``: the gap, ELPD and residual tests per run and the refits."""
        elpd = elpd_blocks(self.evals)
        return {
            "gap": self.gap,
            "rmse_T": rmse(self.evals),
            "elpd": float(elpd.sum()),
            "elpd_se": block_se(elpd),
            "identification_gap": self.identification_gap,
            "runs": [_run_json(e) for e in self.evals],
            "refits": {
                mid: {**rf.summary(), "significant_cells": len(self.windows[mid].cells)}
                for mid, rf in self.refits.items()
            },
        }


def _run_json(e):
    return {
        "module": e.module_id,
        "run": Path(e.source).name,
        "rmse_T": float(np.sqrt(e.sse / e.n)),
        "phase_s": e.phase,
        "significant_cells": len(e.significant),
        "channels": e.gap_map.channels,
    }


def baseline(evals, refits, conflicts, *, alpha):
    """The base model's :class:`Baseline` from its evaluations, refits and range conflicts.

    Parameters
    ----------
    evals : list of RunEvaluation
    refits : dict
        Module id -> base refit, in the diagnosis's module order.
    conflicts : dict
        Module id -> range-conflict rows.
    alpha : float
        Level of each gap-map cell test.

    Returns
    -------
    Baseline
    """
    windows = {mid: held_out_windows([rf], alpha=alpha) for mid, rf in refits.items()}
    return Baseline(
        evals=evals,
        refits=refits,
        windows=windows,
        conflicts=conflicts,
        where_validation=where_rows(evals),
        where_identification=window_rows(windows),
        parameter_gaps=parameter_rows(conflicts),
    )
