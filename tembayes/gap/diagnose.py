"""The whole diagnosis: where, which effect, how far the gap shrinks (``tembayes gap``).

For every calibrated module with held-out runs (``validation*.csv``):

1. **Where** (:mod:`~tembayes.gap.baseline`) -- the base posterior's
   predictive of each held-out run, its bands made of the parameter
   uncertainty and the run's *measurement noise* (white, its level read off
   the run itself: ``RunModel.noise``), and the gap map of
   :mod:`~tembayes.gap.where`; the base model refitted on each identification
   run, its step windows held out one at a time; and the rig parameters whose
   posterior sits outside the documented range (:mod:`~tembayes.gap.conflicts`;
   :func:`~tembayes.gap.conflicts.suspect_table` maps them to the effects they can
   stand for), each checked by a refit with it held at the range's edge: a
   conflict counts only if that refit leaves a significant and material
   held-out window or moves a law beyond its 90 % interval's half-width.
   No significant and material cell anywhere and no rig parameter out of
   range that matters: ``no_gap``, nothing screened.
2. **Which** (:mod:`~tembayes.gap.screen`) -- on the module with the largest
   gap, the base model and every catalogue effect refitted on the
   identification run (posterior mode and Laplace approximation, all from the
   same start), ranked by their Laplace evidence against the base refit, each
   refit's Laplace posterior also predicting the held-out runs; the strongest
   are chosen for recalibration.
3. **How far** (:mod:`~tembayes.gap.ranking`) -- the chosen candidates are
   *recalibrated*: the identification run sampled again with the effect's
   parameters added (:func:`~tembayes.calibrate.module.calibrate_module` with
   ``effects``), anchored, and predicted on the held-out data.  Their held-out
   evidence (:mod:`~tembayes.gap.evidence`) is the ELPD difference to the base
   model, the gap is measured before and after.  On a batch the candidates
   *race* (:mod:`~tembayes.gap.jobs`): each is recalibrated first on the
   module with the largest gap, and only those that gain held-out evidence
   there are recalibrated on the others (the rest are reported with their
   evidence on that module, ``dropped``).  The effects not recalibrated are
   ranked after them with their screen's held-out evidence.  The verdict is
   the best-ranked candidate's.

The gap before and after (``gap_before``, ``gap_after``) is measured on the
validation runs (:data:`~tembayes.gap.evidence.GAP_METRIC`) or, when only the
identification windows show one, on those
(:data:`~tembayes.gap.evidence.ID_GAP_METRIC`); ``gaps`` holds both.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from tembayes.calibrate.modelform import get_form
from tembayes.common.seeds import stream
from tembayes.constants import MODULE_PARAMETERS
from tembayes.errors import DataError, ModelError
from tembayes.gap.baseline import baseline
from tembayes.gap.candidates import Setting, candidate_job, refit_job
from tembayes.gap.conflicts import RangeCheck, is_immaterial, range_conflicts, suspect_start, suspects
from tembayes.gap.evidence import ALPHA, N_DRAWS, evaluate_run, held_out_windows
from tembayes.gap.jobs import collect, default_jobs, executor, in_order, race, submit_all
from tembayes.gap.ranking import LeadJudge, rank, verdict
from tembayes.gap.result import GapDiagnosis
from tembayes.gap.screen import CANDIDATES, choose, screen_rows
from tembayes.gap.which import WindowNoise
from tembayes.physics import effects as E
from tembayes.predict.predictive import module_raw_draws, posterior_draws
from tembayes.predict.runmodel import RunModel

__all__ = ["diagnose", "locate"]

#: Sampler budget of a recalibration [steps]: a candidate's posterior need
#: not be reported to R-hat 1.01 to predict the held-out runs (measured: a
#: correct candidate converges within it; a wrong one does not, and its
#: held-out evidence says so).
RECAL_MAX_STEPS = 20000
#: Predictive draws per held-out run of a screen refit (its Laplace posterior).
SCREEN_DRAWS = 100


@dataclass(frozen=True)
class _Plan:
    """One diagnosis's inputs: the modules, the effects allowed, the jobs' setting and where they start."""

    run: object
    batch: object
    rig: object
    ids: list
    allowed: list
    excluded: list
    setting: Setting
    raws: dict
    starts: dict
    noises: dict
    conflicts: dict
    suspects: list
    jobs: int
    cache: dict | None
    say: object

    def start(self, module_id, effect):
        """Where a refit of ``effect`` on a module starts (SI)."""
        return {**self.starts[module_id], **suspect_start(effect, self.conflicts.get(module_id, ()), self.rig)}

    def refit(self, module_id, effect, *, heldout=False):
        """A refit job, ``(fn, args)``."""
        start = self.start(module_id, effect)
        args = (self.setting, self.batch.modules[module_id], effect, start, heldout, self.noises[module_id])
        return refit_job, args

    def range_check(self, module_id, base_refit, held):
        """A range check's refit job: the base model from its refit's mode, ``held`` (SI) out of the search."""
        start = {k: v for k, v in base_refit.mode().items() if k not in held}
        return refit_job, (
            self.setting,
            self.batch.modules[module_id],
            None,
            start,
            False,
            self.noises[module_id],
            held,
        )

    def only_needed(self, outcome):
        """A copy of a refit's or recalibration's outcome without the conflicts its range checks found immaterial."""
        if outcome.conflicts is None:
            return outcome
        immaterial = {r["parameter"] for r in self.conflicts.get(outcome.module, ()) if is_immaterial(r)}
        return replace(outcome, conflicts=[n for n in outcome.conflicts if n not in immaterial])

    def recalibration(self, module_id, effect, refitted=None):
        """A recalibration job's args (:func:`~tembayes.gap.candidates.candidate_job`)."""
        start = self.start(module_id, effect)
        return self.setting, self.batch.modules[module_id], effect, start, refitted, self.noises[module_id]


@dataclass(frozen=True)
class _RaceOutcome:
    """The recalibrations the race ran, in the order they finished, and the candidates it dropped (with why)."""

    results: list
    dropped: dict


def diagnose(
    run,
    batch,
    *,
    exclude=(),
    candidates=CANDIDATES,
    n_draws=N_DRAWS,
    seed=0,
    options=None,
    jobs=None,
    progress=None,
    cache=None,
):
    """Diagnose the sim-to-real gap of a calibrated batch on its held-out data.

    Parameters
    ----------
    run : tembayes.calibrate.run.CalibrationRun
        The base calibration.
    batch : tembayes.data.Batch
        The calibrated batch; its ``validation*.csv`` runs are held out, and
        each identification run's step windows are held out one at a time.
    exclude : sequence of str
        Effects withheld from the diagnosis (it neither screens nor names them).
    candidates : int
        Candidates recalibrated.
    n_draws : int
        Predictive draws per held-out run.
    seed : int
    options : CalibrationOptions, optional
        For the recalibrations (default the run's own, the budget cut to
        :data:`RECAL_MAX_STEPS`).
    jobs : int, optional
        Refits and recalibrations at once, in worker processes (default
        :func:`~tembayes.gap.jobs.default_jobs`; 1: in this process).
    progress : callable, optional
    cache : dict, optional
        Refits and recalibrations kept between calls on the same run, batch,
        seed and settings, keyed by ``("refit", module_id, effect)``,
        ``("range", module_id, held values)`` and ``(module_id, effect)``: a
        diagnosis with an effect withheld reuses the others' (filled in place).

    Returns
    -------
    GapDiagnosis
    """
    t_start = time.perf_counter()
    plan = _plan(run, batch, exclude, n_draws, seed, options, jobs, cache, progress or (lambda msg: None))
    with executor(plan.jobs) as ex:
        base = _where(plan, ex)
        plan = replace(
            plan, conflicts=base.conflicts, suspects=suspects(base.conflicts, plan.rig, allowed=plan.allowed)
        )
        if not base.has_gap:
            return _no_gap(plan, base, t_start)
        lead = base.lead()
        screen = _screen(plan, base, lead, ex)
        chosen = _choose(plan, base, lead, screen, candidates)
        outcome = _race(plan, base, lead, screen, chosen, ex)
    for r in outcome.results:
        for msg in r.warnings:
            warnings.warn(f"recalibration with {r.effect}: {msg}", RuntimeWarning, stacklevel=2)
    return _rank(plan, base, lead, screen, chosen, outcome, t_start)


def locate(run, batch, *, n_draws=N_DRAWS, seed=0, jobs=None, progress=None, cache=None):
    """Only the diagnosis's first step, where (its range checks included), without screening an effect.

    For studies of where the gap is; the arguments are :func:`diagnose`'s.

    Returns
    -------
    Baseline
    """
    plan = _plan(run, batch, (), n_draws, seed, None, jobs, cache, progress or (lambda msg: None))
    with executor(plan.jobs) as ex:
        return _where(plan, ex)


def _plan(run, batch, exclude, n_draws, seed, options, jobs, cache, say):
    """The modules with held-out runs, the effects allowed and the jobs' setting (refusing what cannot be diagnosed)."""
    unknown = [e for e in exclude if e not in E.CATALOGUE]
    if unknown:
        raise DataError("--exclude", f"names no catalogue effect: {unknown}", f"Choose from {list(E.CATALOGUE)}.")
    base_opt = run.calibration_options()
    # the effects the run's model already contains are no candidates
    inside = {
        *get_form(base_opt.model).includes,
        *base_opt.effects,
        *(E.EFFECT_PARAMETERS[k] for k in base_opt.effect_values),
    }
    ids = [m for m in run.module_ids if batch.modules[m].validations]
    if not ids:
        raise DataError(
            batch.path,
            "has no validation*.csv in any module folder",
            "The diagnosis needs held-out runs: add at least one validation experiment per module.",
        )
    if options is None:
        options = replace(
            base_opt,
            max_steps=min(base_opt.max_steps, RECAL_MAX_STEPS),
            stage_steps=min(base_opt.stage_steps, RECAL_MAX_STEPS),
        )
    # the family-wise level split over every map: each validation run and each identification run
    alpha = ALPHA / (sum(len(batch.modules[m].validations) for m in ids) + len(ids))
    rig = run.rig_for(batch)
    raws = {mid: module_raw_draws(run, mid) for mid in ids}  # read once: anchoring, conflicts, the refits' start
    setting = Setting(
        datasheet=batch.datasheet,
        rig_config=batch.rig_config,
        base=base_opt,
        options=options,
        seed=seed,
        n_draws=n_draws,
        screen_draws=min(n_draws, SCREEN_DRAWS),
        alpha=alpha,
    )
    allowed = [e for e in E.CATALOGUE if e not in set(exclude) and e not in inside]
    conflicts = {mid: [r for r in range_conflicts(raws[mid], rig) if r["outside_sd"] > 0] for mid in ids}
    return _Plan(
        run=run,
        batch=batch,
        rig=rig,
        ids=ids,
        allowed=allowed,
        excluded=list(exclude),
        setting=setting,
        raws=raws,
        starts={mid: {k: float(np.median(raws[mid][k])) for k in MODULE_PARAMETERS} for mid in ids},
        noises={mid: WindowNoise.of_draws(raws[mid]) for mid in ids},
        conflicts=conflicts,
        suspects=suspects(conflicts, rig, allowed=allowed),
        jobs=default_jobs() if jobs is None else int(jobs),
        cache=cache,
        say=say,
    )


def _where(plan, ex):
    """Step 1: the base model on the held-out data.

    Every module's base refit (its identification run's windows held out)
    runs in the workers while this process predicts the validation runs with
    the base posterior.
    """
    s, say = plan.setting, plan.say
    futures = submit_all(ex, {("refit", mid, None): plan.refit(mid, None) for mid in plan.ids}, cache=plan.cache)
    evals = []
    for mid in plan.ids:
        module = plan.batch.modules[mid]
        say(f"{mid}: base model, anchoring on the identification run")
        try:
            draws = posterior_draws(plan.raws[mid], plan.run.priors(mid), mid, module.identification, plan.rig)
        except ModelError as exc:
            raise _unsimulatable(plan, mid, exc) from exc
        for exp in module.validations:
            say(f"{mid}: held-out {Path(str(exp.path)).name}: predictive and gap map")
            evals.append(
                evaluate_run(
                    RunModel(exp, plan.rig, start="data"),
                    draws,
                    stream(s.seed, mid, "base", exp.path),
                    stream(s.seed, mid, exp.path),
                    n_draws=s.n_draws,
                    alpha=s.alpha,
                    keep_prediction=True,
                )
            )
    say("refitting the base model on the identification runs (each step window held out in turn)")
    refits = collect(futures, cache=plan.cache, say=say, label="refitted")
    broken = [f"{k[1]}: {r.failed}" for k, r in refits.items() if r.failed]
    if broken:
        raise DataError(
            plan.batch.path,
            f"the base model cannot be refitted on the identification run ({broken[0]})",
            "Check the run with tembayes inspect; the diagnosis needs the base model to simulate it.",
        )
    refits = {mid: refits[("refit", mid, None)].refit for mid in plan.ids}
    return baseline(evals, refits, _materiality(plan, refits, ex), alpha=s.alpha)


def _materiality(plan, refits, ex):
    """Each module's range conflicts judged by refits held at the edge (:class:`~tembayes.gap.conflicts.RangeCheck`).

    The modules' checks step together, each step's refits at once.
    """
    checks = {mid: RangeCheck(plan.conflicts[mid]) for mid in plan.ids}
    base = {
        mid: {_cell_id(c) for c in held_out_windows([refits[mid]], alpha=plan.setting.alpha).cells} for mid in plan.ids
    }
    sds = {mid: {k: float(np.std(plan.raws[mid][k])) for k in MODULE_PARAMETERS} for mid in plan.ids}

    def law_shift(mid, rf):
        at, held = refits[mid].mode(), rf.mode()
        return max(abs(held[k] - at[k]) / sds[mid][k] for k in MODULE_PARAMETERS)

    asking = [mid for mid, c in checks.items() if c.next() is not None]
    if asking:
        plan.say(
            f"checking the range conflicts of {', '.join(asking)}: the base model refitted with them at their edge"
        )
    while asking:
        held = {mid: checks[mid].next() for mid in asking}
        jobs = {_range_key(mid, h): plan.range_check(mid, refits[mid], h) for mid, h in held.items()}
        done = collect(submit_all(ex, jobs, cache=plan.cache), cache=plan.cache, say=plan.say, label="checked")
        for mid, h in held.items():
            r = done[_range_key(mid, h)]
            if r.failed:
                checks[mid].record(None)
            else:
                cells = held_out_windows([r.refit], alpha=plan.setting.alpha).cells
                new = sum(_cell_id(c) not in base[mid] for c in cells)
                checks[mid].record(new, law_shift(mid, r.refit), converged=r.refit.converged)
        asking = [mid for mid in asking if checks[mid].next() is not None]
    return {mid: c.judged() for mid, c in checks.items()}


def _cell_id(cell):
    return cell["channel"], cell["family"], cell["regime"]


def _range_key(mid, held):
    return "range", mid, ", ".join(f"{k} at {v:.4g}" for k, v in sorted(held.items()))


def _unsimulatable(plan, mid, exc) -> DataError:
    """The refusal of a module whose base posterior the model cannot simulate, naming its rig values furthest out."""
    out = [
        f"{r['parameter']} {r['median']:.4g} {r['unit']} (range {r['low']:.4g} ... {r['high']:.4g})"
        for r in plan.conflicts[mid][:3]
    ]
    return DataError(
        plan.run.path,
        f"{mid}: the base posterior cannot be simulated on the identification run ({exc})"
        + (f"; its rig values furthest outside their documented ranges: {', '.join(out)}" if out else ""),
        "The model does not fit this module: see its adequacy verdict in summary.json, recalibrate with a "
        "catalogue effect that could explain it (tembayes calibrate --effect NAME) and diagnose that run.",
    )


def _no_gap(plan, base, t_start):
    """The diagnosis without a gap: nothing screened."""
    plan.say(
        "no gap: the held-out runs and step windows lie within the base model's bands and its rig "
        "within the documented ranges, or outside only where it does not matter"
    )
    return GapDiagnosis(
        verdict="no_gap",
        where=[],
        ranking=[],
        best=None,
        best_group=[],
        screen=[],
        conflicts=plan.conflicts,
        suspects=plan.suspects,
        base=base,
        excluded=plan.excluded,
        seconds=time.perf_counter() - t_start,
        seed=int(plan.setting.seed),
    )


def _screen(plan, base, lead, ex):
    """Step 2: every allowed effect refitted on the lead's identification run, the base refit the control."""
    gap_in = base.gapped + (["rig parameters"] if base.parameter_gaps else [])
    plan.say(f"gap in {', '.join(gap_in)}; screening {len(plan.allowed)} effects on {lead}'s identification run")
    jobs = {("refit", lead, e): plan.refit(lead, e, heldout=True) for e in plan.allowed}
    outcomes = collect(submit_all(ex, jobs, cache=plan.cache), cache=plan.cache, say=plan.say, label="refitted")
    outcomes = {k: plan.only_needed(o) for k, o in outcomes.items()}
    return screen_rows(outcomes, base=base.refits[lead], lead_base=base.held_out(lead))


def _choose(plan, base, lead, screen, candidates):
    """The effects to recalibrate (:func:`~tembayes.gap.screen.choose`)."""
    chosen = choose(
        screen, gapped=base.gapped, suspects=plan.suspects, conflicting=base.conflicting(lead), candidates=candidates
    )
    plan.say(
        f"recalibrating with {', '.join(chosen) or 'nothing (no catalogue effect helps on the identification run)'}"
    )
    return chosen


def _race(plan, base, lead, screen, chosen, ex):
    """Step 3: the candidates recalibrated, every one on the lead module first.

    Only those that gain held-out evidence there go on to the other modules
    (:class:`~tembayes.gap.ranking.LeadJudge`).  With one candidate there is
    no race to run: every module at once (the cores would idle).
    """
    rest = [m for m in plan.ids if m != lead]
    refitted = {r.effect: r.refit for r in screen}  # the screen's refit starts the sampler on the lead module
    judge = LeadJudge(lead=lead, rest=rest, base=base.held_out(lead), gapped=base.gapped)
    first = [(m, e) for e in chosen for m in ([lead] + rest if len(chosen) == 1 else [lead])]
    results = race(
        first,
        in_order(chosen, lead, lambda r: judge(plan.only_needed(r))),
        lambda mid, e: plan.recalibration(mid, e, refitted.get(e) if mid == lead else None),
        work=candidate_job,
        jobs=plan.jobs,
        cache=plan.cache,
        say=plan.say,
        ex=ex,
    )
    dropped = {
        e: judge.why.get(e, f"lost the race on {lead}") for e in chosen if any((m, e) not in results for m in rest)
    }

    return _RaceOutcome(results=[plan.only_needed(r) for r in results.values()], dropped=dropped)


def _rank(plan, base, lead, screen, chosen, outcome, t_start):
    """The ranking and the verdict: the diagnosis."""
    ranking = rank(
        outcome.results,
        chosen=chosen,
        dropped=outcome.dropped,
        screen=screen,
        baseline=base,
        lead=lead,
        alpha=plan.setting.alpha,
    )
    said = verdict(ranking, gapped=base.gapped, parameter_gaps=base.parameter_gaps)
    options = plan.setting.options
    return GapDiagnosis(
        verdict=said.verdict,
        where=base.where_validation + base.where_identification + base.parameter_gaps,
        ranking=list(ranking.rows),
        best=said.best,
        best_group=said.best_group,
        screen=list(screen),
        conflicts=plan.conflicts,
        suspects=plan.suspects,
        base=base,
        excluded=plan.excluded,
        seconds=time.perf_counter() - t_start,
        seed=int(plan.setting.seed),
        primary=base.primary,
        gap_in=tuple(base.gapped) + (("parameters",) if base.parameter_gaps else ()),
        # the best explanation's recalibrated modules: the run gap hands back
        recalibration={r.module: r.calibration for r in outcome.results if r.effect == said.best and not r.failed},
        recalibration_options=replace(options, effects=(*options.effects, said.best)) if said.best else None,
    )
