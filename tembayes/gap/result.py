"""The diagnosis's result, :class:`GapDiagnosis`, and ``gap.json``."""

from __future__ import annotations

from dataclasses import dataclass, field

from tembayes.gap.evidence import ALPHA, BLOCK_S, EVIDENCE_Z, GAP_METRIC, ID_GAP_METRIC
from tembayes.gap.ranking import EXPLAINED_SHRINK, PARTIAL_SHRINK

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
    ranking : list of dict
        Recalibrated candidates, best first: ``{"effect", "evidence",
        "evidence_se", "gap_before", "gap_after", "shrink", "size",
        "remaining_cells", "converged"}`` (evidence: held-out ELPD difference
        to the base model [nats]); without a gap the screen's ranking
        (:meth:`tembayes.gap.ranking.RankingRow.to_json`).
    best : str or None
    best_group : list of str
        The candidates the data cannot tell from the best.
    screen : list of dict
        The screen's refits, best first (:meth:`tembayes.gap.screen.ScreenRow.to_json`).
    conflicts : dict
        Module -> rig parameters outside their documented range.
    suspects : list of str
        Effects the conflicts point at.
    base : dict
        The base model's held-out gap, ELPD and residual tests per run
        (:meth:`tembayes.gap.baseline.Baseline.to_json`).
    excluded : list of str
        Effects withheld from the diagnosis.
    seconds : float
        Wall time [s].
    seed : int
    evaluations : dict
        ``"base"`` -> list of RunEvaluation (with the predictions, for figures).
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
    ranking: list
    best: str | None
    best_group: list
    screen: list
    conflicts: dict
    suspects: list
    base: dict
    excluded: list
    seconds: float
    seed: int
    evaluations: dict
    primary: str = "validation"
    gap_in: tuple = ()
    recalibration: dict = field(default_factory=dict)
    recalibration_options: object = None

    def to_json(self):
        """``gap.json`` (docs/outputs.md, 'gap.json (gap)'): the verdict and the diagnosis's details."""
        return {
            "verdict": self.verdict,
            "where": self.where,
            "ranking": self.ranking,
            "best": self.best,
            "best_group": self.best_group,
            "metric": GAP_METRIC if self.primary == "validation" else ID_GAP_METRIC,
            "metric_data": self.primary,
            "gap_in": list(self.gap_in),
            "metrics": {"validation": GAP_METRIC, "identification": ID_GAP_METRIC},
            "evidence": EVIDENCE_NOTE,
            "screen": self.screen,
            "conflicts": self.conflicts,
            "suspects": self.suspects,
            "base": self.base,
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
