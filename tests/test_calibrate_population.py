"""The population (batch) stage on synthetic batches with a known population.

The generator here is the test's own: truths drawn from a known population
(type values near TEC1-12706's, unit spread ``UNIT_SPREAD``), each module's
likelihood Gaussian in the population coordinates (log R0, R1/R, log S0, S1/S,
log K) with posterior sds in the middle of realistic ranges and correlated
errors, and exact posterior draws (likelihood x interim prior, which is
Gaussian in those coordinates).

The samplers run with looser convergence targets than the defaults
(``FAST``) to keep the suite quick; ``analyses/population_checks.py`` runs the
defaults.
"""

from __future__ import annotations

import itertools

import arviz as az
import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import multivariate_normal

from tembayes.bench.bench import TEC1_12706, UNIT_SPREAD
from tembayes.calibrate.population import (
    HYPER_NAMES,
    PopulationConvergenceWarning,
    PopulationResult,
    fit_population,
    joint_fit,
)
from tembayes.calibrate.population.deviation import loo_deviation
from tembayes.calibrate.population.hyper import HyperPosterior
from tembayes.calibrate.population.membership import odd_one
from tembayes.calibrate.population.model import TAU_NAMES, Population
from tembayes.calibrate.population.terms import GaussianTerms, ImportanceTerms, module_summaries
from tembayes.calibrate.priors import LEVEL_LOG_SD, SLOPE_REL_SD, law_log_prior, law_priors
from tembayes.calibrate.sampler import Targets
from tembayes.constants import MODULE_PARAMETERS
from tembayes.errors import ModelError

DS = TEC1_12706
LEVEL = np.array([True, False, True, False, True])
REF = np.array([DS.resistance(), DS.resistance(), DS.seebeck(), DS.seebeck(), DS.conductance()])
PRIOR_SD = np.where(LEVEL, LEVEL_LOG_SD, SLOPE_REL_SD)
TYPE = np.array([1.7, 0.0085, 0.048, 9.0e-5, 0.53])
SPREAD = np.array([UNIT_SPREAD[p] for p in MODULE_PARAMETERS])
#: Posterior sd relative to the value: the middle of realistic ranges.
POST_SD = np.array([0.001, 0.02, 0.002, 0.06, 0.006])
#: The population's spreads in PopulationResult.hyper units (levels relative, slopes SI).
TRUE_TAU = {name: (SPREAD[j] if LEVEL[j] else SPREAD[j] * TYPE[j]) for j, name in enumerate(TAU_NAMES)}
#: Spreads "known from earlier batches" to +-30 %.
KNOWN_SPREADS = {k: (v, 0.3) for k, v in TRUE_TAU.items()}
FAST = Targets(tau_multiple=20, rhat_max=1.05, ess_min=300)


def to_x(theta):
    return np.where(LEVEL, np.log(np.abs(theta) / REF), theta / REF)


def to_theta(x):
    return np.where(LEVEL, REF * np.exp(x), REF * x)


def make_batch(seed, n, *, outlier=None, param=2, shift=0.04, at_centre=False, clip=None, corr=0.3, n_draws=600):
    """Draws, Gaussian likelihoods (in x) and truths of one synthetic batch.

    ``outlier``: index of a module whose parameter ``param`` is multiplied by
    ``1 + shift`` (the bench's mechanism); with ``at_centre`` its own unit
    draw of that parameter is the type value, so it sits exactly ``shift``
    off the population centre.  ``clip``: unit draws limited to +-clip
    spreads (members that are unambiguously members).
    """
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n, 5))
    theta = TYPE * (1.0 + SPREAD * (z if clip is None else np.clip(z, -clip, clip)))
    if outlier is not None:
        base = TYPE[param] if at_centre else theta[outlier, param]
        theta[outlier, param] = base * (1.0 + shift)
    R = np.full((5, 5), corr) + (1.0 - corr) * np.eye(5)
    draws, lik = {}, {}
    for i in range(n):
        sd = np.where(LEVEL, POST_SD, POST_SD * np.abs(theta[i]) / REF)
        CL = R * np.outer(sd, sd)
        mL = to_x(theta[i]) + np.linalg.cholesky(CL) @ rng.standard_normal(5)
        prec = np.linalg.inv(CL)
        Cp = np.linalg.inv(prec + np.diag(PRIOR_SD**-2.0))
        xd = Cp @ prec @ mL + rng.standard_normal((n_draws, 5)) @ np.linalg.cholesky(Cp).T
        mid = f"U{i + 1}"
        draws[mid] = to_theta(xd)
        lik[mid] = (mL, prec)
    return draws, lik, theta


def loglikes(lik):
    out = {}
    for mid, (mL, prec) in lik.items():

        def f(theta, mL=mL, prec=prec):
            d = to_x(theta) - mL
            return -0.5 * np.einsum("ni,ij,nj->n", d, prec, d)

        out[mid] = f
    return out


def fit(draws, seed=0, **kw):
    kw.setdefault("convergence", FAST)
    # the smallest deviation a small batch flags draws after the result's own draws, so leaving it out
    # changes no other number; it costs most of a three-module fit and is checked where it is asserted
    kw.setdefault("design_reach", False)
    return fit_population(draws, DS, rng=np.random.default_rng(seed), **kw)


def probs(result):
    return np.array([result.outlier_prob[m] for m in result.module_ids])


# --------------------------------------------------------------------------- the likelihood terms


def brute_force(pop, m, C, mu, tau, logeps, log1m):
    """All 3^5 member/moderate/gross patterns of one Gaussian module likelihood, by scipy."""
    lw = pop.component_log_weights(np.array([logeps]), np.array([log1m]))[0]
    vals = []
    for S in itertools.product([0, 1, 2], repeat=5):
        S = np.array(S)
        mean = np.where(S == 2, pop.gross_mean, mu)
        sd = np.choose(S, [tau, pop.lam * tau, pop.gross_sd])
        vals.append(lw[S].sum() + multivariate_normal.logpdf(m, mean, C + np.diag(sd**2)))
    total = logsumexp(vals)
    return total, vals[0] - total


@pytest.mark.parametrize("corr", [0.0, 0.5])
@pytest.mark.parametrize("offset", [0.0, 5.0, 50.0, "two"])
def test_gaussian_terms_match_brute_force(corr, offset):
    """One module, S0 0 / 5 / 50 spreads off, or S0 and S1 both 6 spreads off:
    the compiled pattern sum == all 243 patterns by scipy."""
    pop = Population(DS)
    rng = np.random.default_rng(3)
    mu = np.array([0.0, 0.005, 0.0, 0.002, 0.0])
    tau = np.array([0.02, 2.5e-4, 0.01, 1.1e-4, 0.03])
    sd = np.array([0.001, 1e-4, 0.002, 1.2e-4, 0.006])
    C = (np.full((5, 5), corr) + (1 - corr) * np.eye(5)) * np.outer(sd, sd)
    m = mu + tau * rng.standard_normal(5)
    if offset == "two":
        m[2:4] += 6.0 * tau[2:4]
    else:
        m[2] += offset * tau[2]
    le, l1 = np.log(0.03), np.log(0.97)
    want = brute_force(pop, m, C, mu, tau, le, l1)
    ll, lmem = GaussianTerms(m[None], C[None])(pop, mu[None], tau[None], np.array([le]), np.array([l1]))
    assert ll[0, 0] == pytest.approx(want[0], abs=1e-3)
    assert np.exp(lmem[0, 0]) == pytest.approx(np.exp(want[1]), abs=1e-4)
    # the importance sums converge to the same numbers
    xd = m + rng.standard_normal((100000, 5)) @ np.linalg.cholesky(C).T
    imp = ImportanceTerms([xd], [np.full(len(xd), -np.log(len(xd)))])
    ll_i, lmem_i = imp(pop, mu[None], tau[None], np.array([le]), np.array([l1]))
    assert ll_i[0, 0] == pytest.approx(want[0], abs=0.02)
    assert np.exp(lmem_i[0, 0]) == pytest.approx(np.exp(want[1]), abs=0.01)


def test_compiled_prior_matches_reference():
    """The sampler's compiled prior + Jacobian equals the numpy reference."""
    draws, _, _ = make_batch(1, 4)
    pop = Population(DS)
    summ = module_summaries(tuple(draws), list(draws.values()), pop, law_log_prior(law_priors(DS)))
    post = HyperPosterior(pop, GaussianTerms(summ.mean, summ.cov), summ.mean, summ.cov)
    u = np.random.default_rng(0).normal(0, 1, (20, 11)) + np.r_[np.zeros(5), pop.logtau_mean, -2.0]
    want = post.log_natural(post.natural(u)) + np.log(post.scale(u[:, 5:10])).sum(axis=1)
    np.testing.assert_allclose(post(u), want, rtol=1e-10)
    u[0, 6] = 50.0  # outside the box
    assert post(u)[0] == -np.inf


# --------------------------------------------------------------------------- inference


@pytest.fixture(scope="module")
def big_batch():
    draws, _, theta = make_batch(7, 30)
    return fit(draws, seed=1), theta


def test_recovers_population_centre_and_spread(big_batch):
    """30 modules, no outlier: every true centre and spread inside its 99 % interval."""
    r, _ = big_batch
    for j, p in enumerate(MODULE_PARAMETERS):
        lo, hi = np.quantile(r.hyper[f"mu_{p}"], [0.005, 0.995])
        assert lo < TYPE[j] < hi, (p, lo, TYPE[j], hi)
    for name, true in TRUE_TAU.items():
        lo, hi = np.quantile(r.hyper[name], [0.005, 0.995])
        assert lo < true < hi, (name, lo, true, hi)
    assert max(r.outlier_prob.values()) < 0.3
    # the predictive of a new member: centred on the type, about one spread wide
    s = r.summary()
    for j, p in enumerate(MODULE_PARAMETERS):
        assert s[p]["q05"] < TYPE[j] < s[p]["q95"]
        assert s[p]["sd"] == pytest.approx(SPREAD[j] * abs(TYPE[j]), rel=0.5)
    assert r.diagnostics["converged"]
    assert r.diagnostics["check"]["passed"]


@pytest.mark.parametrize("seed,sign", [(0, 1), (1, -1), (2, 1)])
def test_three_modules_flag_a_clear_outlier_with_known_spreads(seed, sign):
    """3 modules, spreads known to +-30 % (an earlier batch): an S0 outlier 10
    spreads off is the top module, above 0.5, the others below 0.3.

    At the bench's 4 % (4 spreads) three modules do not carry that much
    evidence (analyses/population_checks.py: rates and the Bayes-optimal bound).
    """
    draws, _, _ = make_batch(seed, 3, outlier=0, shift=0.10 * sign, at_centre=True)
    p = probs(fit(draws, spread_prior=KNOWN_SPREADS))
    assert np.argmax(p) == 0 and p[0] > 0.5 and p[1:].max() < 0.3, p


@pytest.mark.parametrize("seed,sign", [(3, 1), (4, -1)])
def test_eight_modules_flag_the_outlier(seed, sign):
    """8 modules (members within 2.5 spreads), default priors.

    The bench's outlier (S0 +-4 % of its unit draw) is the top module; one 10
    spreads off gets > 0.9 with every member below 0.3.
    """
    draws, _, _ = make_batch(seed, 8, outlier=5, shift=0.04 * sign, clip=2.5)
    p = probs(fit(draws))
    assert np.argmax(p) == 5, p
    draws, _, _ = make_batch(seed, 8, outlier=5, shift=0.10 * sign, at_centre=True, clip=2.5)
    p = probs(fit(draws))
    assert np.argmax(p) == 5 and p[5] > 0.9 and np.delete(p, 5).max() < 0.3, p


def test_odd_one_and_any_outlier_by_hand():
    """Known answers of the membership algebra: one hyper draw, then two averaged."""
    pm = np.array([[0.5, 0.9, 0.9]])
    odd, p_any = odd_one(np.log(pm))
    # exactly one off: 0.5*0.81, 0.1*0.5*0.9, 0.1*0.5*0.9 -> normalised
    np.testing.assert_allclose(odd, np.array([0.405, 0.045, 0.045]) / 0.495)
    assert p_any == pytest.approx(1.0 - 0.405)
    # over draws the probabilities of "exactly this one" are averaged, not their ratios
    pm2 = np.array([[0.5, 0.9, 0.9], [0.99, 0.99, 0.2]])
    odd2, p_any2 = odd_one(np.log(pm2))
    q = np.array([[0.405, 0.045, 0.045], [0.01 * 0.99 * 0.2, 0.01 * 0.99 * 0.2, 0.8 * 0.99 * 0.99]]).mean(axis=0)
    np.testing.assert_allclose(odd2, q / q.sum())
    assert p_any2 == pytest.approx(1.0 - np.mean([0.405, 0.99 * 0.99 * 0.2]))
    # a module surely off at one draw (P(member) = 0) is the only one off there
    with np.errstate(divide="ignore"):
        odd3, p_any3 = odd_one(np.log(np.array([[0.0, 0.9, 0.9], [0.5, 0.9, 0.9]])))
    q = np.array([[0.81, 0.0, 0.0], [0.405, 0.045, 0.045]]).mean(axis=0)
    np.testing.assert_allclose(odd3, q / q.sum())
    assert p_any3 == pytest.approx(1.0 - np.mean([0.0, 0.405]))


@pytest.mark.parametrize("seed,sign", [(3, 1), (4, -1)])
def test_eight_modules_name_the_odd_one_and_how_far(seed, sign):
    """8 modules, one S0 10 spreads (10 %) off the type, the members within 2.5 spreads.

    The odd one takes > 0.9 of ``odd_one_prob``; the batch surely holds one;
    its deviation from the other seven: 10 % within 1.5 % (their centre is
    known to ~0.4 %, the bench's members sit within 2.5 %), 10 spreads within
    a factor 1.6 (seven units learn the spread to ~30 %), a tail probability
    below 1e-3.  Every other level (R0, S0, K: measured to a fifth of a
    spread or better) lies within 2.5 x 8/7 x 1.6 < 5 spreads (a member's own
    weight leaves the others' centre, and the spread they learn may be 1.6
    times too small); the slopes are measured to about their spread, which
    ``spreads`` leaves out and ``p_loo`` counts, so theirs stay above 1e-3.
    """
    draws, _, _ = make_batch(seed, 8, outlier=5, shift=0.10 * sign, at_centre=True, clip=2.5)
    r = fit(draws)
    odd = np.array([r.odd_one_prob[m] for m in r.module_ids])
    assert odd.sum() == pytest.approx(1.0) and np.argmax(odd) == 5 and odd[5] > 0.9, odd
    assert r.p_any_outlier > 0.9
    d = r.deviation["U6"]["S0_V_per_K"]
    assert d["rel"] == pytest.approx(0.10 * sign, abs=0.015), d
    assert 10 / 1.6 < sign * d["spreads"] < 10 * 1.6, d
    assert d["p_loo"] < 1e-3, d
    for mid in r.module_ids:
        for p in MODULE_PARAMETERS:
            d = r.deviation[mid][p]
            if (mid, p) == ("U6", "S0_V_per_K"):
                continue
            assert abs(d["spreads"]) < 5.0 if p in ("R0_ohm", "S0_V_per_K", "K_W_per_K") else d["p_loo"] > 1e-3, (
                mid,
                p,
                d,
            )


def test_three_modules_name_the_one_that_breaks_the_symmetry():
    """3 modules, one S0 10 spreads off: it is the odd one though "is there one" stays open.

    Three units cannot learn the spread, so ``outlier_prob`` stays low; but
    under "exactly one" only the unit that leaves the other two compact fits.
    """
    draws, _, _ = make_batch(7, 3, outlier=0, shift=0.10, at_centre=True, clip=1.0)
    r = fit(draws)
    odd = np.array([r.odd_one_prob[m] for m in r.module_ids])
    assert np.argmax(odd) == 0 and odd[0] > 0.6 and odd[0] > 3 * odd[1:].max(), odd
    assert r.p_any_outlier >= max(r.outlier_prob.values())
    assert r.deviation["U1"]["S0_V_per_K"]["spreads"] > 3.0
    # a module whose reweighting is unreliable is left out by a refit, and only such a module
    k_hat = r.diagnostics["deviation_k_hat"]
    assert r.diagnostics["deviation_refit"] == [m for m in r.module_ids if k_hat[m] > 0.7]
    assert r.diagnostics["deviation_refit"] and r.diagnostics["deviation_refit_unconverged"] == []


def test_a_refit_past_the_fits_time_budget_stops_and_says_it_did_not_converge():
    """A refit gets what is left of the fit's ``max_seconds``: none left, it stops at its first check."""
    import time

    from tembayes.calibrate.population.fit import _refitter
    from tembayes.calibrate.population.sampling import POPULATION_TARGETS, Budget
    from tembayes.calibrate.population.terms import module_summaries
    from tembayes.calibrate.priors import law_log_prior, law_priors

    draws, _, _ = make_batch(7, 3, outlier=0, shift=0.10, at_centre=True, clip=1.0)
    pop = Population(TEC1_12706)
    ids = tuple(draws)
    summ = module_summaries(ids, [draws[m] for m in ids], pop, law_log_prior(law_priors(TEC1_12706)))
    budget = Budget(40000, 600.0, False, POPULATION_TARGETS)
    kw = dict(seed=1, nwalkers=32, budget=budget)
    late = _refitter(pop, summ, ids, "gaussian", 256, 400, started=time.perf_counter() - 601.0, **kw)
    with pytest.warns(PopulationConvergenceWarning):
        hyper, converged = late(0)
    assert not converged and hyper.shape == (400, 11)
    _, converged = _refitter(pop, summ, ids, "gaussian", 256, 400, started=time.perf_counter(), **kw)(0)
    assert converged


def test_a_module_the_reweighting_cannot_leave_out_is_refitted():
    """Known answer: above Pareto k 0.7 the refit's draws give the deviation, below it the batch's reweighted.

    Every batch draw has the same centre and spreads, so the reweighting
    cannot move a module's deviation; the refit's draws sit at another
    centre and twice the spreads, so the refitted row is exactly theirs.
    """
    pop = Population(TEC1_12706)
    tau = np.exp(pop.logtau_mean)
    S, rng = 2000, np.random.default_rng(0)

    def draws(centre, spread):
        return np.tile(np.concatenate([centre, np.log(spread), [-2.0]]), (S, 1))

    mean = pop.mu_mean + np.array([[0.05, 0, 0.02, 0, 0.0], [0.01, 0, 0, 0, 0], [0, 0, 0, 0, -0.01]])
    cov = np.tile(1e-6 * np.eye(5), (3, 1, 1))
    log_like = np.column_stack([5.0 * rng.standard_normal(S), 0.01 * rng.standard_normal((S, 2))])
    moved = pop.mu_mean + 0.01
    called = []

    def refitter(converged):
        def refit(i):
            called.append(i)
            return draws(moved, 2 * tau), converged

        return refit

    dev = loo_deviation(pop, mean, cov, draws(pop.mu_mean, tau), log_like, refitter(True))
    assert called == [0] and dev.refit.tolist() == [True, False, False] and dev.k_hat[0] > 0.7 > dev.k_hat[1:].max()
    # the refit's own word on its convergence, for the refitted module only
    assert dev.refit_converged.tolist() == [True, False, False]
    unconverged = loo_deviation(pop, mean, cov, draws(pop.mu_mean, tau), log_like, refitter(False))
    assert not unconverged.refit_converged.any()
    np.testing.assert_allclose(dev.spreads[0], (mean[0] - moved) / (2 * tau))
    np.testing.assert_allclose(dev.spreads[1:], (mean[1:] - pop.mu_mean) / tau)
    np.testing.assert_allclose(dev.rel[0, [0, 2, 4]], np.expm1(mean[0] - moved)[[0, 2, 4]])


@pytest.mark.parametrize("n", [3, 8])
def test_no_outlier_flags_nobody(n):
    draws, _, _ = make_batch(10 + n, n)
    assert max(fit(draws).outlier_prob.values()) < 0.3


def test_gross_outlier_does_not_inflate_the_spread():
    """A broken unit (S0 +50 %) is flagged and leaves tau_S0 where the members put it."""
    draws, _, _ = make_batch(5, 8, outlier=2, shift=0.5)
    clean = {k: v for k, v in draws.items() if k != "U3"}
    r, r_clean = fit(draws), fit(clean)
    assert r.outlier_prob["U3"] > 0.99
    med, med_clean = np.median(r.hyper["tau_S0_rel"]), np.median(r_clean.hyper["tau_S0_rel"])
    assert med == pytest.approx(med_clean, rel=0.15)


def test_two_modules_degenerate_but_defined():
    draws, _, _ = make_batch(6, 2)
    r = fit(draws)
    p = probs(r)
    assert np.all((p > 0) & (p < 0.3))
    assert abs(p[0] - p[1]) < 0.1  # the two units are exchangeable
    assert r.predictive.shape == (4000, 5) and np.all(np.isfinite(r.predictive))


def test_same_seed_same_numbers():
    draws, _, _ = make_batch(8, 3)
    a, b = fit(draws, seed=42, design_reach=True), fit(draws, seed=42, design_reach=True)
    assert a.outlier_prob == b.outlier_prob
    assert a.odd_one_prob == b.odd_one_prob and a.p_any_outlier == b.p_any_outlier
    assert a.deviation == b.deviation and a.outlier_vs_spread.to_json() == b.outlier_vs_spread.to_json()
    assert a.smallest_flagged == b.smallest_flagged and a.smallest_flagged.spreads > 1.0
    np.testing.assert_array_equal(a.predictive, b.predictive)
    for k in HYPER_NAMES:
        np.testing.assert_array_equal(a.hyper[k], b.hyper[k])
    assert a.diagnostics["emcee_seed"] == b.diagnostics["emcee_seed"]
    c = fit(draws, seed=43)
    assert not np.array_equal(a.predictive, c.predictive)


def test_without_the_leave_one_out_refits_the_batchs_draws_are_the_same():
    draws, _, _ = make_batch(12, 3)  # a module whose leave-one-out reweighting is unreliable: refitted by default
    a, b = fit(draws, seed=5), fit(draws, seed=5, loo_refits=False)
    assert a.diagnostics["deviation_refit"] and not b.diagnostics["deviation_refit"]
    for k in HYPER_NAMES:
        np.testing.assert_array_equal(a.hyper[k], b.hyper[k])
    np.testing.assert_array_equal(a.predictive, b.predictive)
    assert a.outlier_prob == b.outlier_prob


def test_two_stage_agrees_with_joint_fit():
    """Gaussian likelihoods: two-stage and joint (exact) agree within Monte Carlo error."""
    draws, lik, _ = make_batch(9, 3, outlier=0, shift=0.05)
    two = fit(draws, seed=3)
    joint = joint_fit(loglikes(lik), DS, rng=np.random.default_rng(3), convergence=FAST)
    for mid in two.module_ids:
        se = np.hypot(two.diagnostics["outlier_prob_mcse"][mid], joint.diagnostics["outlier_prob_mcse"][mid])
        assert abs(two.outlier_prob[mid] - joint.outlier_prob[mid]) < 4 * se + 0.01, mid
    for k in HYPER_NAMES:
        a, b = two.hyper[k], joint.hyper[k]
        se = np.hypot(a.std() / np.sqrt(az.ess(a)), b.std() / np.sqrt(az.ess(b)))
        assert abs(a.mean() - b.mean()) < 4 * se, k
        assert a.std() == pytest.approx(b.std(), rel=0.15), k


def test_importance_method_agrees_with_gaussian():
    draws, _, _ = make_batch(11, 3, outlier=1, param=0, shift=0.1)
    g, i = fit(draws, method="gaussian"), fit(draws, method="importance", max_draws_per_module=100)
    assert i.diagnostics["method"] == "importance" and g.diagnostics["method"] == "gaussian"
    for mid in g.module_ids:
        se = np.hypot(g.diagnostics["outlier_prob_mcse"][mid], i.diagnostics["outlier_prob_mcse"][mid])
        assert abs(g.outlier_prob[mid] - i.outlier_prob[mid]) < 4 * se + 0.03, mid


def test_non_gaussian_posterior_falls_back_to_importance_sums():
    """A bimodal module posterior (S0 at -3 % or +3 %): the 'auto' check sees
    that the Gaussian approximation changes the result and re-runs with the
    importance sums, which keep the two modes."""
    draws, _, _ = make_batch(13, 3)
    a = draws["U1"].copy()
    a[: len(a) // 2, 2] *= 0.97
    a[len(a) // 2 :, 2] *= 1.03
    draws["U1"] = a
    with pytest.warns(UserWarning, match="re-running with importance sums"):
        r = fit(draws, max_draws_per_module=80)
    assert r.diagnostics["method"] == "importance"
    assert not r.diagnostics["check"]["passed"]


def test_result_contents(big_batch):
    r, _ = big_batch
    assert isinstance(r, PopulationResult)
    assert set(r.hyper) == set(HYPER_NAMES)
    W = r.diagnostics["nwalkers"]
    assert all(v.shape[0] == W and v.ndim == 2 for v in r.hyper.values())
    assert set(r.summary()) == set(MODULE_PARAMETERS)
    assert set(r.summary()["R0_ohm"]) == {"mean", "sd", "q05", "q95"}
    assert r.predictive_with_outliers.shape == r.predictive.shape
    d = r.diagnostics
    for k in ("rhat_max", "ess_bulk_min", "tau_max", "n_steps", "converged", "weight_ess_min", "emcee_seed"):
        assert k in d
    # importance-weight ESS (of 256 draws) at the posterior-median hyperparameters
    assert 1 <= d["weight_ess_min"] <= 256 and set(d["weight_ess"]) == set(r.module_ids)
    sp = r.spread_prior()
    assert set(sp) == set(TAU_NAMES) and all(v[0] > 0 and v[1] > 0 for v in sp.values())


def test_budget_exhausted_warns_and_says_so():
    draws, _, _ = make_batch(12, 3)
    with pytest.warns(PopulationConvergenceWarning, match="not converged"):
        # what comes after the batch's draws (the refits, the design's reach) is not what is asserted here
        r = fit_population(
            draws, DS, rng=np.random.default_rng(0), max_steps=1000, design_reach=False, loo_refits=False
        )
    assert r.diagnostics["converged"] is False and r.diagnostics["n_steps"] == 1000


# --------------------------------------------------------------------------- refusals


def _good():
    return make_batch(0, 3, n_draws=50)[0]


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda d: {"U1": d["U1"]}, "at least 2 modules"),
        (lambda d: {**d, "U2": d["U2"][:, :4]}, "module 'U2'.*shape"),
        (lambda d: {**d, "U2": d["U2"][None]}, "module 'U2'.*shape"),
        (lambda d: {**d, "U3": np.where(np.arange(5) == 2, np.nan, d["U3"])}, "module 'U3'.*NaN.*S0_V_per_K"),
        (lambda d: {**d, "U1": d["U1"] * np.array([-1, 1, 1, 1, 1])}, "module 'U1'.*R0_ohm.*positive"),
        (lambda d: {**d, "U1": d["U1"][:5]}, "module 'U1'.*at least 20"),
        (lambda d: {**d, "U1": np.tile(d["U1"][:1], (50, 1))}, "module 'U1'.*do not vary"),
        (lambda d: {**d, "U1": "abc"}, "module 'U1'"),
        (lambda d: list(d.values()), "dict"),
    ],
)
def test_refuses_bad_draws(mutate, match):
    with pytest.raises(ModelError, match=match):
        fit_population(mutate(_good()), DS, rng=np.random.default_rng(0))


def test_refuses_bad_options():
    d = _good()
    with pytest.raises(ModelError, match="Generator"):
        fit_population(d, DS, rng=0)
    with pytest.raises(ModelError, match="unknown spread"):
        fit_population(d, DS, rng=np.random.default_rng(0), spread_prior={"tau_R0": (0.02, 0.3)})
    with pytest.raises(ModelError, match="method"):
        fit_population(d, DS, rng=np.random.default_rng(0), method="laplace")
    with pytest.raises(ModelError, match="convergence must be a .*Targets"):
        fit_population(d, DS, rng=np.random.default_rng(0), convergence={"rhat_max": 1.1})
    with pytest.raises(ModelError, match="interim prior is not finite"):
        fit_population(d, DS, rng=np.random.default_rng(0), log_interim_prior=lambda t: np.full(len(t), -np.inf))
    with pytest.raises(ModelError, match="module 'U2'.*callable"):
        joint_fit({"U1": lambda t: t[:, 0], "U2": 3}, DS, rng=np.random.default_rng(0))
    with pytest.raises(ModelError, match="at least 2 modules"):
        joint_fit({"U1": lambda t: t[:, 0]}, DS, rng=np.random.default_rng(0))


def test_a_tight_spread_prior_far_from_the_batch_scatter_still_converges():
    """A spread stated to 5 % (log-sd 0.05) while three modules' scatter suggests another: the walkers start inside its prior.

    The sampler's box holds the spreads within 12 prior sds; a start at the
    batch's own scatter would lie outside it (every walker at -inf, the
    chain stuck where it started).  Stated the bench's true spreads, the
    posterior spreads must stay within 3 of those sds of them.
    """
    draws, _, theta = make_batch(7, 3)
    tau = np.where(LEVEL, SPREAD, SPREAD * np.abs(TYPE))
    r = fit(draws, spread_prior={name: (float(t), 0.05) for name, t in zip(TAU_NAMES, tau)})
    assert r.diagnostics["converged"]
    for name, t in zip(TAU_NAMES, tau):
        assert abs(np.log(np.median(r.hyper[name]) / t)) < 3 * 0.05, name
