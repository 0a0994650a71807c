"""How far: the candidates judged by held-out evidence, ranked, and the verdict.

A candidate recalibrated on every module is judged by its held-out evidence
against the base model (:class:`~tembayes.gap.evidence.Evidence`) and the
gap before and after (:class:`GapChange`); one dropped by the race
(:class:`LeadJudge`) by its evidence on the module with the largest gap;
the effects only screened by their refit's Laplace posterior there.

Verdict (the best-ranked candidate ``b``):

- ``explained``: ``b`` improves the held-out evidence by more than
  :data:`~tembayes.gap.evidence.EVIDENCE_Z` standard errors, shrinks the gap
  by :data:`EXPLAINED_SHRINK` or more and leaves no significant cell on
  every dataset that shows one, and leaves the rig in range (a gap hidden in
  the parameters alone: ``b`` puts them back in range and leaves no cell);
- ``partially_explained``: ``b`` improves the ELPD significantly and shrinks
  the gap by :data:`PARTIAL_SHRINK` or more;
- ``unexplained``: otherwise (nothing in the catalogue helps).

Candidates whose ELPD differs from the best's by less than ``EVIDENCE_Z``
paired standard errors are one group: the data cannot tell them apart
(:func:`best_group`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from tembayes.gap.baseline import where_rows
from tembayes.gap.evidence import Evidence, HeldOut, elpd_blocks, held_out_gap, held_out_windows, rmse

#: Shrink of the gap that makes an effect the explanation / a partial one.
EXPLAINED_SHRINK = 0.5
PARTIAL_SHRINK = 0.2
#: Remaining cells a recalibrated row lists, worst first.
REMAINING_LISTED = 5

#: ``evidence_kind`` of a row: recalibrated on every module (or failed there).
RECALIBRATED = "heldout_elpd"
#: Recalibrated on the lead module only (dropped by the race).
LEAD_MODULE = "heldout_elpd_lead_module"
#: Only screened: its refit's Laplace posterior on the lead module.
SCREENED = "heldout_elpd_laplace"
#: Its screen refit failed.
SCREEN_FAILED = "screen"


def _shrink(before, after):
    return 1.0 - after / before if before > 0 else 0.0


@dataclass(frozen=True)
class GapChange:
    """The gap before and after on both held-out datasets.

    Attributes
    ----------
    primary : str
        The dataset ``gap_before``/``gap_after``/``shrink`` report: ``"validation"`` or ``"identification"``.
    validation : tuple of float
        ``(before, after)`` [K].
    identification : tuple of float
        ``(before, after)`` [noise sds].
    """

    primary: str
    validation: tuple
    identification: tuple

    def on(self, dataset=None):
        """``(before, after)`` on ``dataset`` (default the primary)."""
        return getattr(self, dataset or self.primary)

    def shrink(self, dataset=None):
        """The relative shrink of the gap on ``dataset`` (default the primary)."""
        return _shrink(*self.on(dataset))

    def to_json(self):
        """The gap keys of a ``gap.json`` row."""
        g = {
            d: {"before": b, "after": a, "shrink": _shrink(b, a)}
            for d, (b, a) in (("validation", self.validation), ("identification", self.identification))
        }
        p = g[self.primary]
        return {"gap_before": p["before"], "gap_after": p["after"], "shrink": p["shrink"], "gaps": g}


@dataclass(frozen=True)
class CellsLeft:
    """The significant and material cells a recalibrated candidate leaves.

    Attributes
    ----------
    validation, identification : int
        On the validation runs and on the identification windows.
    worst : list of dict
        The worst :data:`REMAINING_LISTED`, as where-rows.
    """

    validation: int
    identification: int
    worst: list

    @property
    def total(self):
        """Cells left on both datasets."""
        return self.validation + self.identification

    def on(self, dataset):
        """Cells left on ``dataset``."""
        return getattr(self, dataset)

    def to_json(self):
        """The cell keys of a ``gap.json`` row."""
        return {
            "remaining_cells": self.total,
            "remaining": self.worst,
            "cells_left": {"validation": self.validation, "identification": self.identification},
        }


@dataclass(frozen=True)
class RankingRow:
    """One effect's row of the ranking; :meth:`to_json` is its ``gap.json`` row.

    Attributes
    ----------
    effect : str
    kind : str
        :data:`RECALIBRATED`, :data:`LEAD_MODULE`, :data:`SCREENED` or :data:`SCREEN_FAILED`.
    evidence : Evidence or None
        Held-out evidence against the base model [nats] (None: failed).
    gaps : GapChange or None
        None for a failed row, which reports ``gap_before`` alone.
    gap_before : float or None
        A failed row's validation gap before [K].
    module : str or None
        The module a lead-module or screened row was judged on.
    cells_left : CellsLeft or None
    rmse_T : tuple of float or None
        ``(before, after)`` plain RMSE over the rig's sensors [K].
    size : dict or None
        Module id -> the effect's parameters.
    conflicts_left : dict or None
        Module id -> rig parameters still outside their range.
    converged : bool or None
    seconds : float or None
        Wall time of the recalibrations [s].
    dropped : str or None
        Why the race stopped it on the lead module.
    screen_log_bayes_factor : float or None
    failed : str or None
    terms : HeldOut or None
        The held-out terms behind ``evidence`` (recalibrated rows; not in ``gap.json``).
    """

    effect: str
    kind: str
    evidence: Evidence | None = None
    gaps: GapChange | None = None
    gap_before: float | None = None
    module: str | None = None
    cells_left: CellsLeft | None = None
    rmse_T: tuple | None = None
    size: dict | None = None
    conflicts_left: dict | None = None
    converged: bool | None = None
    seconds: float | None = None
    dropped: str | None = None
    screen_log_bayes_factor: float | None = None
    failed: str | None = None
    terms: HeldOut | None = field(default=None, repr=False, compare=False)

    @property
    def conflicts_resolved(self):
        """No module's rig left outside its range."""
        return all(not c for c in self.conflicts_left.values())

    def to_json(self):
        """The ``gap.json`` ranking row (its keys depend on the kind)."""
        out = {"effect": self.effect, **(self.evidence.to_json() if self.evidence else {"evidence": None})}
        out["evidence_kind"] = self.kind
        if self.module is not None:
            out["module"] = self.module
        out |= self.gaps.to_json() if self.gaps else {"gap_before": self.gap_before, "gap_after": None, "shrink": None}
        if self.cells_left is not None:
            out |= self.cells_left.to_json()
        if self.rmse_T is not None:
            out |= {"rmse_T_before": self.rmse_T[0], "rmse_T_after": self.rmse_T[1]}
        if self.size is not None:
            out["size"] = self.size
        if self.conflicts_left is not None:
            out |= {"conflicts_left": self.conflicts_left, "conflicts_resolved": self.conflicts_resolved}
        tail = {
            "converged": self.converged,
            "seconds": self.seconds,
            "dropped": self.dropped,
            "screen_log_bayes_factor": self.screen_log_bayes_factor,
            "failed": self.failed,
        }
        return out | {k: v for k, v in tail.items() if v is not None}


def recalibrated_row(effect, recalibrations, *, baseline, alpha):
    """The row of an effect recalibrated on every module.

    Parameters
    ----------
    effect : str
    recalibrations : list of Recalibration
        One per module.
    baseline : Baseline
    alpha : float
        Level of each gap-map cell test.

    Returns
    -------
    RankingRow
    """
    rs = recalibrations
    by_module = {r.module: r for r in rs}
    by_run = {(ev.module_id, ev.source): ev for r in rs for ev in r.evals}
    evals = [by_run[(e.module_id, e.source)] for e in baseline.evals]
    windows = held_out_windows([by_module[mid].refit for mid in baseline.ids], alpha=alpha)
    terms = HeldOut(elpd_blocks(evals), windows.lpd)
    return RankingRow(
        effect=effect,
        kind=RECALIBRATED,
        evidence=terms.evidence_over(baseline.held_out()),
        gaps=GapChange(
            primary=baseline.primary,
            validation=(baseline.gap, held_out_gap(evals)),
            identification=(baseline.identification_gap, windows.gap),
        ),
        cells_left=_cells_left(evals, windows.cells),
        rmse_T=(rmse(baseline.evals), rmse(evals)),
        size={r.module: r.size for r in rs},
        conflicts_left={r.module: r.conflicts for r in rs},
        converged=all(r.converged for r in rs),
        seconds=float(sum(r.seconds for r in rs)),
        terms=terms,
    )


def _cells_left(evals, window_cells):
    windows = [
        {
            "channel": c["channel"],
            "score": c["score"],
            "regime": f"identification {c['family']}: {c['regime']}",
            "module": c["module"],
        }
        for c in window_cells
    ]
    return CellsLeft(
        validation=int(sum(len(ev.significant) for ev in evals)),
        identification=len(window_cells),
        worst=sorted(where_rows(evals) + windows, key=lambda c: -c["score"])[:REMAINING_LISTED],
    )


def _lead_gaps(baseline, lead, after, identification_after):
    """The gap before and after on the lead module alone."""
    return GapChange(
        primary=baseline.primary,
        validation=(held_out_gap(baseline.evals_of(lead)), after),
        identification=(baseline.windows[lead].gap, identification_after),
    )


def dropped_row(recalibration, *, reason, baseline, lead):
    """The row of an effect the race stopped on the lead module (its evidence there).

    Parameters
    ----------
    recalibration : Recalibration
        The lead module's.
    reason : str
        Why the race stopped it.
    baseline : Baseline
    lead : str

    Returns
    -------
    RankingRow
    """
    r = recalibration
    return RankingRow(
        effect=r.effect,
        kind=LEAD_MODULE,
        evidence=HeldOut(elpd_blocks(r.evals), r.refit.cv_lpd).evidence_over(baseline.held_out(lead)),
        gaps=_lead_gaps(baseline, lead, held_out_gap(r.evals), held_out_windows([r.refit]).gap),
        module=lead,
        size={lead: r.size},
        converged=r.converged,
        dropped=f"{reason} (the module with the largest gap): not recalibrated on the other modules",
    )


def screened_row(row, *, baseline, lead):
    """The row of an effect only screened (its refit's Laplace posterior on the lead module).

    Parameters
    ----------
    row : ScreenRow
        Not failed.
    baseline : Baseline
    lead : str

    Returns
    -------
    RankingRow
    """
    return RankingRow(
        effect=row.effect,
        kind=SCREENED,
        evidence=row.evidence,
        gaps=_lead_gaps(baseline, lead, row.gap_after, row.identification_gap_after),
        module=lead,
        size={lead: row.refit.size()},
        screen_log_bayes_factor=row.log_bayes_factor,
    )


def failed_row(effect, *, kind, failed, gap_before):
    """The row of an effect whose model failed.

    Parameters
    ----------
    effect : str
    kind : str
        :data:`RECALIBRATED` or :data:`SCREEN_FAILED`.
    failed : str
        Why.
    gap_before : float
        The validation runs' gap before [K].

    Returns
    -------
    RankingRow
    """
    return RankingRow(effect=effect, kind=kind, gap_before=gap_before, failed=failed)


@dataclass(frozen=True)
class Ranking:
    """The candidates' rows, best first.

    Attributes
    ----------
    rows : list of RankingRow
        The candidates recalibrated on every module (ranked), then those
        dropped or failed (in the order chosen), the effects only screened
        (by their evidence) and those whose screen refit failed.
    recalibrated : int
        The leading rows recalibrated on every module.
    """

    rows: list
    recalibrated: int

    def to_json(self):
        """``gap.json``'s ``ranking``."""
        return [r.to_json() for r in self.rows]


def order(rows, *, gapped):
    """Recalibrated rows, best first.

    With a gap in the held-out data, by evidence; with one in the parameters
    alone, the effects that put them back in range and leave no cell first,
    then by evidence.
    """
    if gapped:
        return sorted(rows, key=lambda r: -r.evidence.value)
    return sorted(rows, key=lambda r: (not r.conflicts_resolved, r.cells_left.total > 0, -r.evidence.value))


def rank(recalibrations, *, chosen, dropped, screen, baseline, lead, alpha):
    """Rank the candidates recalibrated and the effects only screened.

    Parameters
    ----------
    recalibrations : list of Recalibration
        Every recalibration the race ran.
    chosen : list of str
        The candidates, in the order chosen.
    dropped : dict
        Candidate -> why the race stopped it on the lead module.
    screen : list of ScreenRow
        Best first.
    baseline : Baseline
    lead : str
        The module with the largest gap.
    alpha : float
        Level of each gap-map cell test.

    Returns
    -------
    Ranking
    """
    held_back, recalibrated = [], []
    for e in chosen:
        rs = [r for r in recalibrations if r.effect == e]
        bad = [f"{r.module}: {r.failed}" for r in rs if r.failed]
        if e in dropped and not bad:
            (r,) = rs
            held_back.append(dropped_row(r, reason=dropped[e], baseline=baseline, lead=lead))
        elif bad:
            held_back.append(failed_row(e, kind=RECALIBRATED, failed="; ".join(bad), gap_before=baseline.gap))
        else:
            recalibrated.append(recalibrated_row(e, rs, baseline=baseline, alpha=alpha))
    screened = [
        screened_row(r, baseline=baseline, lead=lead)
        for r in screen
        if r.log_bayes_factor is not None and r.effect not in chosen
    ]
    failed = [
        failed_row(r.effect, kind=SCREEN_FAILED, failed=r.failed, gap_before=baseline.gap) for r in screen if r.failed
    ]
    rows = order(recalibrated, gapped=baseline.gapped) + held_back
    rows += sorted(screened, key=lambda r: -r.evidence.value) + failed
    return Ranking(rows=rows, recalibrated=len(recalibrated))


def best_group(ranking, *, gapped):
    """The best candidate and those the data cannot tell from it (their paired ELPD difference).

    Parameters
    ----------
    ranking : Ranking
        With at least one candidate recalibrated on every module.
    gapped : list of str
        The held-out datasets that show a gap (without, a member must also put the rig back in range).

    Returns
    -------
    list of str
    """
    top = ranking.rows[0]
    group = [top.effect]
    for r in ranking.rows[1 : ranking.recalibrated]:
        if top.terms.evidence_over(r.terms).indistinct() and (gapped or r.conflicts_resolved):
            group.append(r.effect)
    return group


@dataclass(frozen=True)
class Verdict:
    """The diagnosis's verdict.

    Attributes
    ----------
    verdict : str
        ``"explained"``, ``"partially_explained"`` or ``"unexplained"``.
    best : str or None
        The explanation (with either of the first two).
    best_group : list of str
        The candidates the data cannot tell from it.
    """

    verdict: str
    best: str | None = None
    best_group: list = field(default_factory=list)


def verdict(ranking, *, gapped, parameter_gaps):
    """The verdict on the best-ranked candidate (module docstring).

    Parameters
    ----------
    ranking : Ranking
    gapped : list of str
        The held-out datasets that show a gap.
    parameter_gaps : list
        The rig parameters outside their range.

    Returns
    -------
    Verdict
    """
    if not ranking.recalibrated:
        return Verdict("unexplained")
    top = ranking.rows[0]
    said = _verdict_on(top, gapped=gapped, parameter_gaps=parameter_gaps)
    if said not in ("explained", "partially_explained"):
        return Verdict(said)
    return Verdict(said, best=top.effect, best_group=best_group(ranking, gapped=gapped))


def _verdict_on(top, *, gapped, parameter_gaps):
    if not gapped:
        # the parameters back in range and the held-out data still within the bands
        return "explained" if top.conflicts_resolved and top.cells_left.total == 0 else "unexplained"
    evident = top.evidence.significant()
    closed = all(top.gaps.shrink(d) >= EXPLAINED_SHRINK and top.cells_left.on(d) == 0 for d in gapped)
    if evident and closed and (top.conflicts_resolved or not parameter_gaps):
        return "explained"
    if evident and top.gaps.shrink() >= PARTIAL_SHRINK:
        return "partially_explained"
    return "unexplained"


class LeadJudge:
    """The race's rule: which of the lead module's results go on to the other modules.

    ``decide`` of :func:`~tembayes.gap.jobs.in_order`.  With a gap in the
    held-out data, a candidate goes on when it gains held-out evidence on the
    lead module and no candidate decided before it beats it there; with a gap
    in the parameters alone, when its recalibration puts the lead's rig back
    in range.  ``why`` keeps the reason of those that stop.

    Parameters
    ----------
    lead : str
    rest : list of str
        The other modules.
    base : HeldOut
        The base model's terms on the lead module.
    gapped : list of str
        The held-out datasets that show a gap.
    """

    def __init__(self, *, lead, rest, base, gapped):
        self.lead, self.rest, self.base, self.gapped = lead, rest, base, gapped
        self.terms = {}  # the candidates decided so far (not failed), in order
        self.why = {}

    def __call__(self, r):
        """The ``(module_id, effect)`` jobs a lead result carries on."""
        if r.failed:
            return []
        carried = [(m, r.effect) for m in self.rest]
        if not self.gapped:
            self.why[r.effect] = f"its range conflicts stay on {self.lead}"
            return carried if not r.conflicts else []
        own = self.terms[r.effect] = HeldOut(elpd_blocks(r.evals), r.refit.cv_lpd)
        if not own.evidence_over(self.base).significant():
            self.why[r.effect] = f"no significant held-out gain on {self.lead}"
            return []
        for e, other in self.terms.items():  # beaten by an earlier candidate: the race is lost
            if e != r.effect and other.evidence_over(own).significant():
                self.why[r.effect] = f"beaten by {e} on {self.lead}"
                return []
        return carried
