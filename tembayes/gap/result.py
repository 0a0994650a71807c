"""The diagnosis's result, :class:`GapDiagnosis`, and ``gap.json``."""

from __future__ import annotations

from dataclasses import dataclass, field

from tembayes.gap.baseline import Baseline
from tembayes.gap.evidence import ALPHA, BLOCK_S, EVIDENCE_Z, GAP_METRIC, ID_GAP_METRIC
from tembayes.gap.ranking import EXPLAINED_SHRINK, PARTIAL_SHRINK, RankingRow
from tembayes.gap.screen import ScreenRow

__all__ = ["GapDiagnosis"]

#: What ``gap.json``'s evidence is.
EVIDENCE_NOTE = (
    "held-out ELPD difference to the base model [nats]: the validation runs in blocks of "
    f"{BLOCK_S:.0f} s plus the identification run's step windows each left out; evidence_se "
    "from the blocks and windows"
)


@dataclass(frozen=True)
class GapDiagnosis:
    """Result of :func:`~tembayes.gap.diagnose.diagnose` (a plain result object; ``to_json`` is ``gap.json``).

    Attributes
    ----------
    verdict : str
    where : list of dict
        Significant gap-map cells of the base model, worst first:
        ``{"channel", "regime", "score", "module", "run", "p"}``.
    ranking : list of RankingRow
        The candidates, best first: recalibrated on every module, then
        dropped by the race or failed, then only screened (empty without a
        gap).  ``gap.json`` holds :meth:`RankingRow.to_json
        <tembayes.gap.ranking.RankingRow.to_json>` of each.
    best : str or None
    best_group : list of str
        The candidates the data cannot tell from the best.
    screen : list of ScreenRow
        The screen's refits on the lead module, best first.
    conflicts : dict
        Module -> rig parameters outside their documented range.
    suspects : list of str
        Effects the conflicts point at.
    base : Baseline
        The base model on the held-out data: its evaluations (with the
        predictions, for figures), refits and range conflicts.
    excluded : list of str
        Effects withheld from the diagnosis.
    seconds : float
        Wall time [s].
    seed : int
    primary : str
        The held-out data whose gap ``gap_before``/``gap_after`` report:
        ``"validation"`` or ``"identification"``.
    gap_in : tuple of str
        Where the base model shows a gap: ``"validation"`` (runs),
        ``"identification"`` (windows held out), ``"parameters"`` (range
        conflicts); empty for ``no_gap``.
    recalibration : dict
        Module id -> the best effect's recalibrated
        :class:`~tembayes.calibrate.module.ModuleCalibration` (empty without
        a best effect); :func:`tembayes.gap.recalibrated.write_recalibrated_run`
        writes them as a run folder.
    recalibration_options : CalibrationOptions or None
        The options they were calibrated with (the run's, the effect added).
    """

    verdict: str
    where: list
    ranking: list[RankingRow]
    best: str | None
    best_group: list
    screen: list[ScreenRow]
    conflicts: dict
    suspects: list
    base: Baseline
    excluded: list
    seconds: float
    seed: int
    primary: str = "validation"
    gap_in: tuple = ()
    recalibration: dict = field(default_factory=dict)
    recalibration_options: object = None

    def to_json(self):
        """``gap.json`` (docs/outputs.md, 'gap.json (gap)'): the verdict and the diagnosis's details."""
        return {
            "verdict": self.verdict,
            "where": self.where,
            "ranking": [r.to_json() for r in self.ranking],
            "best": self.best,
            "best_group": self.best_group,
            "metric": GAP_METRIC if self.primary == "validation" else ID_GAP_METRIC,
            "metric_data": self.primary,
            "gap_in": list(self.gap_in),
            "metrics": {"validation": GAP_METRIC, "identification": ID_GAP_METRIC},
            "evidence": EVIDENCE_NOTE,
            "screen": [r.to_json() for r in self.screen],
            "conflicts": self.conflicts,
            "suspects": self.suspects,
            "base": self.base.to_json(),
            "excluded": self.excluded,
            "settings": {
                "alpha": ALPHA,
                "evidence_z": EVIDENCE_Z,
                "explained_shrink": EXPLAINED_SHRINK,
                "partial_shrink": PARTIAL_SHRINK,
                "block_s": BLOCK_S,
            },
            "seed": self.seed,
            "seconds": self.seconds,
        }
