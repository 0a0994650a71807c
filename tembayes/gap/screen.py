"""Which: the screen's refits ranked, and the candidates chosen for recalibration.

Every allowed catalogue effect is refitted on the identification run of the
module with the largest gap (:func:`~tembayes.gap.candidates.refit_job`),
the base refit the control.  The screen ranks them by their Laplace evidence
against the base refit (:class:`ScreenRow`); :func:`choose` picks the
effects worth the sampler.
"""

from __future__ import annotations

from dataclasses import dataclass

from tembayes.gap.evidence import Evidence, HeldOut, elpd_blocks, held_out_gap, held_out_windows

#: Candidates recalibrated (the screen's best; range conflicts may add one).
CANDIDATES = 2
#: Screen log evidence [nats] by which the screen's best beats a candidate
#: decisively: not recalibrated, ranked by its refit's held-out evidence.
#: On a 4-hour 5 Hz identification run (~2e5 samples) that is ~0.01 in chi2
#: per sample; measured margins: effects that can stand in for each other
#: 100 nats apart (a Thomson heat and quadratic laws), the rest 1600-190000.
SCREEN_DECISIVE = 1000.0


@dataclass(frozen=True)
class ScreenRow:
    """One effect's refit on the lead module's identification run.

    Attributes
    ----------
    effect : str
    refit : Refit or None
        None when the refit failed.
    log_bayes_factor : float or None
        Its Laplace log evidence against the base refit's [nats].
    conflicts : list of str or None
        The rig parameters its Laplace posterior puts outside their range.
    evidence : Evidence or None
        Its Laplace posterior's held-out evidence against the base model on the lead module.
    gap_after, identification_gap_after : float or None
        The lead module's gap on the validation runs [K] and on the windows [noise sds] with the effect.
    failed : str or None
        Why the refit failed.
    """

    effect: str
    refit: object = None
    log_bayes_factor: float | None = None
    conflicts: list | None = None
    evidence: Evidence | None = None
    gap_after: float | None = None
    identification_gap_after: float | None = None
    failed: str | None = None

    @classmethod
    def of(cls, outcome, *, base, lead_base):
        """A screen job's row, scored against the base refit ``base`` and the lead's base terms ``lead_base``."""
        if outcome.failed:
            return cls(effect=outcome.effect, failed=outcome.failed)
        rf = outcome.refit
        return cls(
            effect=outcome.effect,
            refit=rf,
            log_bayes_factor=rf.log_evidence - base.log_evidence,
            conflicts=outcome.conflicts,
            evidence=HeldOut(elpd_blocks(outcome.evals), rf.cv_lpd).evidence_over(lead_base),
            gap_after=held_out_gap(outcome.evals),
            identification_gap_after=held_out_windows([rf]).gap,
        )

    def to_json(self):
        """The ``gap.json`` screen row."""
        if self.failed:
            return {"effect": self.effect, "log_bayes_factor": None, "failed": self.failed}
        return {
            **self.refit.summary(),
            "module": self.refit.module_id,
            "log_bayes_factor": self.log_bayes_factor,
            "conflicts": self.conflicts,
            **self.evidence.to_json(),
            "gap_after": self.gap_after,
            "identification_gap_after": self.identification_gap_after,
        }


def screen_rows(outcomes, *, base, lead_base):
    """The screen's refits as rows, best (Laplace evidence against the base refit) first, failed last.

    Parameters
    ----------
    outcomes : dict
        ``(kind, module_id, effect) -> RefitOutcome`` of the lead module; the base refit's (effect None) is skipped.
    base : Refit
        The lead module's base refit.
    lead_base : HeldOut
        The base model's held-out terms on the lead module.

    Returns
    -------
    list of ScreenRow
    """
    rows = [
        ScreenRow.of(r, base=base, lead_base=lead_base) for (_, _, effect), r in outcomes.items() if effect is not None
    ]
    return sorted(rows, key=lambda r: (r.log_bayes_factor is None, -(r.log_bayes_factor or 0.0)))


def choose(screen, *, gapped, suspects, conflicting, candidates=CANDIDATES):
    """The effects to recalibrate.

    With a gap in the held-out data: the screen's best that gain Laplace
    evidence and are not beaten decisively (:data:`SCREEN_DECISIVE`), and one
    range-conflict suspect, unless it is beaten decisively and the best's
    refit already puts the rig back in range.  With a gap in the parameters alone: the effects whose
    refit puts them back in range, the suspects first.

    Parameters
    ----------
    screen : list of ScreenRow
        Best first.
    gapped : list of str
        The held-out datasets that show a gap.
    suspects : list of str
        The effects the range conflicts point at.
    conflicting : set of str
        The lead module's rig parameters outside their range.
    candidates : int
        Effects chosen from the screen (a suspect may add one).

    Returns
    -------
    list of str
    """
    ok = [r for r in screen if r.log_bayes_factor is not None]
    if not gapped:
        fix = [r.effect for r in ok if not conflicting & set(r.conflicts)]
        return ([e for e in fix if e in suspects] + [e for e in fix if e not in suspects])[:candidates]
    near = {r.effect for r in ok if r.log_bayes_factor >= ok[0].log_bayes_factor - SCREEN_DECISIVE}
    chosen = [r.effect for r in ok if r.log_bayes_factor > 0 and r.effect in near][:candidates]
    top_fixes = bool(ok) and not conflicting & set(ok[0].conflicts)
    return chosen + [e for e in suspects if e not in chosen and (e in near or not top_fixes)][:1]
