"""Unit checks of the calibration's parts against known answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from tembayes.bench.bench import TEC1_12706
from tembayes.calibrate import sampler as smp
from tembayes.calibrate.likelihood import LevelErrors, _ExpansionSums, _window_terms, window_loglike
from tembayes.calibrate.parameters import ParameterSpace
from tembayes.calibrate.priors import ParameterPrior, law_priors, rig_prior
from tembayes.physics.rigread import REFERENCE

FACE = REFERENCE.layout.face


def test_window_loglike_matches_multivariate_normal():
    # residuals of 3 windows x 2 channels with offsets: closed form vs the
    # dense covariance sigma^2 I + beta^2 1 1^T
    rng = np.random.default_rng(1)
    starts = np.array([0, 4, 11])
    n = 15
    R = rng.normal(size=(2, 2, n))
    sigma = np.array([[0.7, 1.3], [1.1, 0.4]])
    beta = np.array([[0.5, 0.01], [2.0, 0.3]])
    got = window_loglike(R, starts, sigma, beta)
    bounds = list(starts) + [n]
    for w in range(2):
        for k in range(3):
            a, b = bounds[k], bounds[k + 1]
            want = 0.0
            for c in range(2):
                cov = sigma[w, c] ** 2 * np.eye(b - a) + beta[w, c] ** 2
                want += stats.multivariate_normal(np.zeros(b - a), cov).logpdf(R[w, c, a:b])
            assert got[w, k] == pytest.approx(want, rel=1e-10)


class _Quadratic:
    """A stand-in expansion: f0 + J d + C d^2 / 2 with random coefficients."""

    def __init__(self, rng, p, nc, n):
        self.x0 = rng.normal(size=p)
        self.f0 = rng.normal(size=(nc, n))
        self.J = rng.normal(size=(p, nc, n))
        self.C = rng.normal(size=(p, nc, n))
        self.pairs = np.array([[0, 2], [1, 3]])
        self.H = rng.normal(size=(2, nc, n))

    def predict(self, X):
        D = X - self.x0
        return (
            self.f0[None]
            + np.tensordot(D, self.J, axes=(1, 0))
            + 0.5 * np.tensordot(D * D, self.C, axes=(1, 0))
            + np.tensordot(D[:, [0, 1]] * D[:, [2, 3]], self.H, axes=(1, 0))
        )


def _banded_level_response(rng, nc, starts, n):
    """Random responses to ns + 1 hold levels, each reaching its two windows."""
    ns = len(starts)
    win = np.repeat(np.arange(ns), np.diff(np.append(starts, n)))
    G = np.zeros((ns + 1, nc, n))
    for h in range(ns + 1):
        near = (win == h) | (win == h - 1)
        G[h][:, near] = rng.normal(size=(nc, near.sum()))
    return G


def test_expansion_sums_equal_the_direct_residual_sums():
    rng = np.random.default_rng(2)
    p, nc, n = 4, 3, 40
    lin = _Quadratic(rng, p, nc, n)
    obs = rng.normal(size=(nc, n))
    starts = np.array([0, 7, 19, 33])
    lev = LevelErrors(_banded_level_response(rng, nc, starts, n), np.full(5, 0.4), starts)
    sums = _ExpansionSums(obs, lin, starts, lev)
    X = lin.x0 + 0.3 * rng.normal(size=(6, p))
    S1, S2, GR = sums.sums(X - lin.x0)
    R = obs[None] - lin.predict(X)
    assert np.allclose(S1, np.add.reduceat(R, starts, axis=2), rtol=1e-10, atol=1e-10)
    assert np.allclose(S2, np.add.reduceat(R * R, starts, axis=2), rtol=1e-10, atol=1e-10)
    assert np.allclose(GR, lev.projections(R), rtol=1e-10, atol=1e-10)
    sigma = np.full((6, nc), 0.8)
    beta = np.full((6, nc), 0.2)
    assert np.allclose(
        _window_terms(S1, S2, np.diff(np.append(starts, n)).astype(float), sigma, beta),
        window_loglike(R, starts, sigma, beta),
    )


def test_level_errors_give_the_dense_multivariate_normal():
    # residuals with window offsets *and* uncertain hold currents: the
    # tridiagonal Woodbury form vs the dense covariance
    # blockdiag(sigma^2 I + beta^2 1 1^T) + G S G^T
    rng = np.random.default_rng(4)
    nc, n = 2, 26
    starts = np.array([0, 5, 12, 20])
    G = _banded_level_response(rng, nc, starts, n)
    level_sd = rng.uniform(0.3, 1.5, len(starts) + 1)
    lev = LevelErrors(G, level_sd, starts)
    sigma = np.array([[0.7, 1.3]])
    beta = np.array([[0.5, 0.2]])
    R = rng.normal(size=(1, nc, n))
    nwin = np.diff(np.append(starts, n)).astype(float)
    got = window_loglike(R, starts, sigma, beta) + lev.terms(
        lev.projections(R), np.add.reduceat(R, starts, axis=2), nwin, sigma, beta
    )
    cov = np.zeros((nc * n, nc * n))
    bounds = list(starts) + [n]
    for c in range(nc):
        for a, b in zip(bounds[:-1], bounds[1:]):
            i = slice(c * n + a, c * n + b)
            cov[i, i] = sigma[0, c] ** 2 * np.eye(b - a) + beta[0, c] ** 2
    Gf = G.reshape(len(level_sd), nc * n).T
    cov += Gf @ np.diag(level_sd**2) @ Gf.T
    want = stats.multivariate_normal(np.zeros(nc * n), cov).logpdf(R.ravel())
    assert got.sum() == pytest.approx(want, rel=1e-10)
    assert lev.neglected == 0.0


def test_priors_are_normalised_densities_with_the_jacobian():
    pri = law_priors(TEC1_12706)
    assert [p.name for p in pri] == ["R0_ohm", "R1_ohm_per_K", "S0_V_per_K", "S1_V_per_K2", "K_W_per_K"]
    # centred on the datasheet conversions (docs/data-format.md, '[module_type]'), whatever the type
    assert pri[0].center == pytest.approx(TEC1_12706.resistance())
    assert pri[2].center == pytest.approx(TEC1_12706.seebeck())
    assert pri[4].center == pytest.approx(TEC1_12706.conductance())
    x = np.array([1.5, 1.7, 2.0])
    want = stats.lognorm(s=0.3, scale=TEC1_12706.resistance()).logpdf(x)
    assert np.allclose(pri[0].logpdf(x), want)
    # in log coordinates: a normal density
    assert np.allclose(
        pri[0].logpdf_unconstrained(np.log(x)), stats.norm(np.log(TEC1_12706.resistance()), 0.3).logpdf(np.log(x))
    )
    u = ParameterPrior("s", "uniform", 0.0, 0.1)
    assert u.logpdf_unconstrained(np.array([0.05]))[0] == pytest.approx(-np.log(0.2))
    assert u.logpdf_unconstrained(np.array([0.11]))[0] == -np.inf


def test_rig_prior_spans_the_documented_range():
    p = next(q for q in REFERENCE.parameters if q.name == "g_paste_hot")
    pr = rig_prior(p)
    # +-2 sd in log space is the documented range
    assert np.exp(np.log(pr.center) - 2 * pr.scale) == pytest.approx(
        p.low * p.nominal / np.sqrt(p.low * p.high), rel=1e-9
    )
    assert 2 * 2 * pr.scale == pytest.approx(np.log(p.high / p.low))


def test_a_share_gets_a_logit_normal_prior_that_never_leaves_zero_to_one():
    p = next(q for q in REFERENCE.parameters if q.name == "tab_share")
    pr = rig_prior(p)
    assert pr.kind == "logitnormal"
    # +-2 sd of the logit span the documented range, centred on the nominal value
    assert 4 * pr.scale == pytest.approx(np.log(p.high / (1 - p.high)) - np.log(p.low / (1 - p.low)))
    assert pr.coordinate_center == pytest.approx(np.log(p.nominal / (1 - p.nominal)))
    # a coordinate far out on either side is still a share
    assert np.all(
        (pr.from_unconstrained(np.array([-40.0, 5.2, 40.0])) >= 0)
        & (pr.from_unconstrained(np.array([-40.0, 5.2, 40.0])) <= 1)
    )
    # the density of the value: the logit's normal density times the Jacobian, zero outside (0, 1)
    x = np.array([0.1, 0.5, 0.93])
    z = (np.log(x / (1 - x)) - pr.coordinate_center) / pr.scale
    want = stats.norm.logpdf(z) - np.log(pr.scale) - np.log(x * (1 - x))
    assert np.allclose(pr.logpdf(x), want)
    assert np.all(pr.logpdf(np.array([0.0, 1.0, 1.5])) == -np.inf)
    # and it integrates to one
    grid = np.linspace(1e-6, 1 - 1e-6, 200001)
    assert np.trapezoid(np.exp(pr.logpdf(grid)), grid) == pytest.approx(1.0, abs=1e-4)
    # a heat capacity stays log-normal
    assert rig_prior(next(q for q in REFERENCE.parameters if q.name == "c_plate_hot")).kind == "lognormal"


def test_a_leak_to_the_room_is_sampled_in_its_log_a_series_path_as_its_resistance():
    """The heat share a conductance carries decides its coordinate: a shunt (little of a face's
    heat) in its log, a series path (all of it) as its resistance."""
    from tembayes.calibrate.module import SHUNT_SHARE, CalibrationOptions, calibration_rig

    plates = calibration_rig({"preset": "liquid-plates"}, CalibrationOptions())
    nominal = plates.nominal()
    # one watt at the hot face leaves by the liquid or, in parallel, by the leak
    leak_share = nominal["leak"] / (nominal["leak"] + nominal["g_liquid_hot"])
    assert plates.face_heat_share("leak") == pytest.approx(leak_share, rel=0.01)
    assert plates.face_heat_share("g_paste_hot") == pytest.approx(1.0, rel=1e-9)
    reference = calibration_rig({}, CalibrationOptions())
    sink = calibration_rig({"preset": "heatsink-al"}, CalibrationOptions())
    shunts = {
        (rig.name, p.name)
        for rig in (plates, reference, sink)
        for p in rig.parameters
        if p.unit == "W/K" and rig.face_heat_share(p.name) < SHUNT_SHARE
    }
    # the bottom block's leak is its only way out, as the heat sink's load leak is
    assert {n for _, n in shunts} == {"leak", "leak_top"} and (sink.name, "leak") not in shunts
    leak = plates.parameter("leak")
    assert rig_prior(leak, shunt=True).kind == "lognormal" and rig_prior(leak).kind == "reciprocal"
    x = np.array([0.012, 0.02, 0.035])  # the same prior density in the value, whichever coordinate
    np.testing.assert_allclose(rig_prior(leak, shunt=True).logpdf(x), rig_prior(leak).logpdf(x))

    class Data:  # the noise priors need only the channels' noise
        noise = np.array([1e-3, 4e-3, 4e-3])

    from tembayes.bench.bench import TEC1_12706 as ds
    from tembayes.calibrate.module import parameter_space

    kinds = {p.name: p.kind for p in parameter_space(plates, ds, Data, 0.1)[0].priors}
    assert kinds["leak"] == "lognormal" and kinds["g_liquid_hot"] == kinds["g_paste_hot"] == "reciprocal"


def test_the_heat_share_counts_parallel_links_apart_and_an_insulated_side_as_series():
    """A second link on a leak's node pair takes its own heat, not the leak's; a side that reaches
    no boundary but through the module is all in series (and does not make the solve singular)."""
    import dataclasses

    from tembayes.calibrate.module import CalibrationOptions, calibration_rig

    sink = calibration_rig({"preset": "heatsink-al"}, CalibrationOptions())
    # the load block's leak alone (the cold plate rim's share of it left out)
    rim = [(a, b, g) for a, b, g in sink.links if b == "ambient" and isinstance(g, list) and "leak*face_share" in g]
    load = ("load", "ambient", "leak + -1*leak*face_share")
    assert len(rim) == 1 and load in sink.links
    links = tuple(("load", "ambient", "leak") if x == load else x for x in sink.links if x not in rim)
    sink = dataclasses.replace(sink, links=links)
    nominal = sink.nominal()
    fan = dataclasses.replace(sink, links=(*sink.links, ("load", "ambient", "g_sink")))
    assert fan.face_heat_share("leak") == pytest.approx(nominal["leak"] / (nominal["leak"] + nominal["g_sink"]))
    insulated = dataclasses.replace(sink, links=tuple(link for link in sink.links if link[2] != "leak"))
    assert insulated.face_heat_share("g_paste") == 1.0


def test_a_sensors_lead_share_is_sampled_as_itself_flat_over_its_range():
    """The readings are linear in a lead share: its prior is flat over the documented range, its
    coordinate the share itself."""
    from tembayes.physics import shipped_rig

    share = next(p for p in shipped_rig("heatsink-al").parameters if p.name == "lead_share")
    pr = rig_prior(share, linear=True)
    assert pr.kind == "uniform"
    assert (pr.center - pr.scale, pr.center + pr.scale) == pytest.approx((share.low, share.high))
    x = np.array([0.5 * share.low, share.low * 1.01, 0.005, share.high * 0.99, 1.01 * share.high])
    assert np.all(np.isfinite(pr.logpdf(x[1:4]))) and np.all(pr.logpdf(x[[0, 4]]) == -np.inf)
    assert pr.to_unconstrained(np.array([0.004]))[0] == pytest.approx(0.004)
    assert rig_prior(share).kind == "logitnormal"  # a share the readings are not linear in


def test_a_conductance_is_sampled_as_its_resistance_under_the_same_log_normal_prior():
    p = next(q for q in REFERENCE.parameters if q.name == "g_paste_hot")
    pr = rig_prior(p)
    assert pr.kind == "reciprocal"
    lognormal = ParameterPrior(p.name, "lognormal", pr.center, pr.scale)
    g = np.array([22.0, 35.0, 48.0])
    # the same density of the conductance
    assert np.allclose(pr.logpdf(g), lognormal.logpdf(g))
    # in the coordinate u = 1/g: that density times |dg/du| = 1/u^2
    u = pr.to_unconstrained(g)
    assert np.allclose(u, 1.0 / g) and np.allclose(pr.from_unconstrained(u), g)
    assert np.allclose(pr.logpdf_unconstrained(u), lognormal.logpdf(g) - 2.0 * np.log(u))
    # the space's vectorised log prior agrees, and refuses a resistance <= 0
    sp = ParameterSpace((pr, ParameterPrior("shift", "uniform", 0.0, 0.1)))
    X = np.column_stack([np.append(u, [0.0, -0.01]), np.zeros(5)])
    want = np.append(pr.logpdf_unconstrained(u), [-np.inf, -np.inf]) - np.log(0.2)
    assert np.allclose(sp.log_prior(X), want)
    # clip holds a resistance pushed past zero at its floor, 8 prior sds out
    assert sp.clip(X)[:, 0] == pytest.approx(np.append(u, [np.exp(-8 * pr.scale) / pr.center] * 2))
    # prior draws are the log-normal's: their log has the prior's centre and sd
    lg = np.log(pr.sample(np.random.default_rng(1), 200_000))
    assert np.mean(lg) == pytest.approx(np.log(pr.center), abs=4 * pr.scale / np.sqrt(2e5))
    assert np.std(lg) == pytest.approx(pr.scale, rel=0.01)


def test_parameter_space_round_trip_and_clip():
    sp = ParameterSpace(tuple(law_priors(TEC1_12706)) + (ParameterPrior("shift", "uniform", 0.0, 0.1),))
    vals = {
        "R0_ohm": 1.7,
        "R1_ohm_per_K": 0.01,
        "S0_V_per_K": 0.048,
        "S1_V_per_K2": 9e-5,
        "K_W_per_K": 0.53,
        "shift": 0.02,
    }
    x = sp.to_x(vals)
    back = sp.values(x[None])
    for k, v in vals.items():
        assert back[k][0] == pytest.approx(v)
    X = np.repeat(x[None], 2, axis=0)
    X[0, -1] = 0.5
    assert sp.clip(X)[0, -1] < 0.1
    assert np.isfinite(sp.log_prior(sp.clip(X))).all()
    assert sp.log_prior(X)[0] == -np.inf


def _gauss_target(mean, cov):
    P = np.linalg.inv(cov)

    def log_prob(X):
        D = X - mean
        return -0.5 * np.einsum("wi,ij,wj->w", D, P, D)

    return log_prob


def test_sampler_recovers_a_correlated_gaussian_and_converges():
    rng = np.random.default_rng(3)
    p = 5
    A = rng.normal(size=(p, p))
    cov = A @ A.T + 0.1 * np.eye(p)
    mean = rng.normal(size=p)
    p0 = mean + 0.1 * rng.normal(size=(16, p))
    run = smp.sample(
        _gauss_target(mean, cov), p0, seed=5, monitor=range(p), thin_by=5, check_every=100, max_steps=40000
    )
    assert run.converged
    flat = run.chain.reshape(-1, p)
    ess = np.min(run.ess_bulk)
    assert ess >= smp.ESS_MIN and np.max(run.rhat) <= smp.RHAT_MAX
    assert run.chain.shape[0] * run.thin_by >= smp.MIN_TAU_MULTIPLE * np.max(run.tau)
    sd = np.sqrt(np.diag(cov))
    # the mean within 4 Monte Carlo standard errors, the sds within 10 %
    assert np.all(np.abs(flat.mean(0) - mean) < 4 * sd / np.sqrt(ess))
    assert np.allclose(flat.std(0), sd, rtol=0.1)


def test_a_run_that_converges_at_its_first_check_still_stores_the_draws_its_caller_keeps():
    """A batch's modules share one draw dimension: a module converging at the first check (80 stored
    iterations after burn-in) broke the batch's posterior.nc until the sampler ran on to ``min_stored``."""
    p = 2
    p0 = 0.1 * np.random.default_rng(1).normal(size=(16, p))
    kw = dict(seed=2, monitor=range(p), thin_by=10, check_every=100, max_steps=20000)
    quick = smp.sample(_gauss_target(np.zeros(p), np.eye(p)), p0, **kw)
    assert quick.converged and quick.chain.shape[0] < 100  # converged at its first check: the case
    kept = smp.sample(_gauss_target(np.zeros(p), np.eye(p)), p0, min_stored=100, **kw)
    assert kept.converged and kept.chain.shape[0] >= 100


def test_sampler_returns_the_variance_of_a_known_gaussian():
    # a posterior-like target: 21 dimensions, correlated, condition number 1e4,
    # walkers started *in* it.  emcee's DESnookerMove (20 % of the moves
    # before) left 75 % of the variance; any move that keeps the target
    # invariant returns 100 % up to Monte Carlo error
    rng = np.random.default_rng(0)
    p = 21
    U, _ = np.linalg.qr(rng.normal(size=(p, p)))
    cov = (U * np.logspace(-4, 0, p)) @ U.T
    L_inv = np.linalg.inv(np.linalg.cholesky(cov))
    p0 = rng.multivariate_normal(np.zeros(p), cov, size=2 * p + 2)
    # with DE alone, and with half the moves independence proposals from a
    # deliberately wrong fit (centre 0.3 sd off, widths 0.7-1.3x)
    C = np.linalg.cholesky(cov)
    A = np.diag(rng.uniform(0.7, 1.3, p))
    wrong = (C @ (0.3 * rng.normal(size=p)), C @ A @ A @ C.T)
    for proposal in (None, wrong):
        run = smp.sample(
            _gauss_target(np.zeros(p), cov), p0, seed=1, monitor=range(p), max_steps=60000, proposal=proposal
        )
        assert run.converged
        white = run.chain.reshape(-1, p) @ L_inv.T  # ~N(0, I) if the sampler is right
        var = white.var(axis=0)
        # each variance from >= 1000 effective draws: relative sd <= sqrt(2/1000) = 4.5 %;
        # the mean of 21 of them to ~1 %
        assert 0.95 < var.mean() < 1.05
        assert np.all((var > 0.8) & (var < 1.2))
        assert np.all(np.abs(white.mean(axis=0)) < 0.2)


def test_sampler_reports_a_budget_that_runs_out():
    p = 3
    p0 = np.random.default_rng(0).normal(size=(8, p))
    with pytest.warns(RuntimeWarning, match="not converged"):
        run = smp.sample(
            _gauss_target(np.zeros(p), np.eye(p)), p0, seed=1, monitor=range(p), thin_by=1, check_every=50, max_steps=50
        )
    assert not run.converged
    assert run.steps == 50


def test_sampler_is_reproducible_and_resumes_bit_identically(tmp_path):
    p = 3
    log_prob = _gauss_target(np.zeros(p), np.eye(p))
    p0 = np.random.default_rng(0).normal(size=(8, p))
    kw = dict(seed=11, monitor=range(p), thin_by=2, check_every=40)
    with pytest.warns(RuntimeWarning):
        a = smp.sample(log_prob, p0, max_steps=160, checkpoint=tmp_path / "a", **kw)
    with pytest.warns(RuntimeWarning):
        b = smp.sample(log_prob, p0, max_steps=160, **kw)
    assert np.array_equal(a.chain, b.chain)
    # an interrupted run (80 steps) continued to 160 equals the straight run
    with pytest.warns(RuntimeWarning):
        smp.sample(log_prob, p0, max_steps=80, checkpoint=tmp_path / "c", **kw)
    # a kill inside a write leaves only a temporary file, which resume ignores
    (tmp_path / "c.00002.npz.tmp999").write_bytes(b"half a chunk")
    with pytest.warns(RuntimeWarning):
        c = smp.sample(log_prob, p0, max_steps=160, checkpoint=tmp_path / "c", resume=True, **kw)
    assert c.resumed
    assert np.array_equal(a.chain, c.chain) and np.array_equal(a.log_prob, c.log_prob)
    assert np.array_equal(a.acceptance, c.acceptance)
    # resuming a converged run (killed after its last check, during the
    # caller's post-processing) returns it unchanged, without more steps
    p0w = np.random.default_rng(1).normal(size=(16, p))
    kw2 = dict(seed=5, monitor=range(p), thin_by=1, check_every=200, max_steps=100000)
    f = smp.sample(log_prob, p0w, checkpoint=tmp_path / "f", **kw2)
    assert f.converged
    g = smp.sample(log_prob, p0w, checkpoint=tmp_path / "f", resume=True, **kw2)
    assert g.resumed and g.steps == f.steps and np.array_equal(f.chain, g.chain)
    # a checkpoint of another shape is refused with what to do
    with pytest.raises(ValueError, match="delete the run's checkpoints"):
        smp.sample(log_prob, p0[:, :2], max_steps=160, checkpoint=tmp_path / "c", resume=True, **kw)
    with pytest.warns(RuntimeWarning):
        d = smp.sample(log_prob, p0, max_steps=160, **{**kw, "seed": 12})
    assert not np.array_equal(a.chain, d.chain)


def test_sampler_stop_ends_the_run_at_the_same_check_straight_or_resumed(tmp_path):
    p = 3
    log_prob = _gauss_target(np.zeros(p), np.eye(p))
    p0 = np.random.default_rng(0).normal(size=(8, p))
    kw = dict(seed=11, monitor=range(p), thin_by=2, check_every=40, max_steps=2000)
    asked = []

    def stop(post, steps):
        asked.append(steps)
        return steps >= 240

    with pytest.warns(RuntimeWarning):
        a = smp.sample(log_prob, p0, stop=stop, **kw)
    assert asked == [80, 160, 240] and a.steps == 240 and not a.converged
    # the run up to the stop is the run without one (the stop draws nothing)
    with pytest.warns(RuntimeWarning):
        b = smp.sample(log_prob, p0, **{**kw, "max_steps": 240})
    assert np.array_equal(a.chain, b.chain)
    # interrupted at 160 steps and resumed: it stops at the same check
    with pytest.warns(RuntimeWarning):
        smp.sample(log_prob, p0, checkpoint=tmp_path / "c", **{**kw, "max_steps": 160})
    with pytest.warns(RuntimeWarning):
        c = smp.sample(
            log_prob, p0, checkpoint=tmp_path / "c", resume=True, stop=lambda post, steps: steps >= 240, **kw
        )
    assert c.resumed and c.steps == 240 and np.array_equal(a.chain, c.chain)


def _example_model(module="TEM1"):
    """The calibration's step-response model of an example module."""
    from pathlib import Path

    from tembayes.calibrate.model import StepResponseModel
    from tembayes.calibrate.module import CalibrationOptions, calibration_rig
    from tembayes.calibrate.stepdata import step_data
    from tembayes.data import load_batch

    batch = load_batch(Path(__file__).resolve().parents[1] / "data" / "example")
    data = step_data(batch.modules[module].identification, face=FACE)
    rig = calibration_rig(batch.rig_config, CalibrationOptions())
    return batch, data, rig, StepResponseModel(data, rig)


def test_step_response_model_reads_no_unset_memory():
    """Every grid point is set before the boundaries are read there.

    Regression: the step-pair points of the base grid were left as
    ``np.empty`` garbage, so the water and ambient temperatures read at them
    (and the whole simulation) depended on the heap's history: a run could
    differ from the same run in another process, or after a resume.  Freeing
    a NaN-filled block of the grid's size right before the model is built
    makes the allocator hand that block back: NaNs would show.
    """
    from tembayes.calibrate.model import StepResponseModel

    _, data, rig, first = _example_model()
    n = first._base_grid.shape[0]
    for _ in range(3):
        junk = np.full(n, np.nan)
        del junk
        again = StepResponseModel(data, rig)
        for name in ("_base_grid", "_bounds", "_current"):
            assert np.all(np.isfinite(getattr(again, name))), name
            assert np.array_equal(getattr(again, name), getattr(first, name)), name


def test_a_wild_parameter_draw_fails_fast_instead_of_hanging():
    """A draw far outside the priors (S1 = 0.01 V/K^2, a hundred times a real one) made
    the adaptive integrator crawl for 29 million steps; now it gives up at
    its step budget: NaN with ``strict=False``, a ModelError otherwise."""
    from tembayes.calibrate.model import SHIFT
    from tembayes.calibrate.module import parameter_space
    from tembayes.errors import ModelError
    from tembayes.physics import kernel as K

    batch, data, rig, model = _example_model()
    ms, _ = parameter_space(rig, batch.datasheet, data, model.shift_bound)
    x = np.array([pr.to_unconstrained(pr.center) for pr in ms.priors]) + 0.01
    x[ms.index(SHIFT)] = 0.01
    X = np.stack([np.array([pr.to_unconstrained(pr.center) for pr in ms.priors]), x])
    X[0, ms.index(SHIFT)] = 0.0
    sim = model.simulate(ms.params(X), strict=False)
    n = model._base_grid.shape[0] + 2 * data.n_steps
    assert np.isfinite(sim["voltage"][0]).all() and np.isnan(sim["voltage"][1]).any()
    assert sim["steps"][1] <= K.MAX_STEPS_PER_POINT * n + K.MIN_STEP_BUDGET + 1
    with pytest.raises(ModelError, match="step budget"):
        model.simulate(ms.params(X))


def test_expansion_pulls_a_probe_the_model_cannot_simulate_back_and_stays_exact():
    """A probe where the model fails (here: a > 0.7, as a plate or paste pushed where the rig
    cannot be simulated) is pulled halfway back to the expansion point; the expansion of a
    quadratic model is still exact there (the parabola through the points actually simulated)
    and fails loudly only when the expansion point itself cannot be simulated."""
    from tembayes.calibrate.model import LinearisedModel
    from tembayes.errors import ModelError

    t = np.linspace(0.0, 1.0, 7)

    class Quadratic:
        def predict(self, params, strict=True):
            a, b = np.atleast_1d(params["a"])[:, None, None], np.atleast_1d(params["b"])[:, None, None]
            y = np.broadcast_to(1.0 + 2.0 * a + 3.0 * a * a * t + b - 0.5 * b * b, (len(a), 2, len(t))).copy()
            y[a[:, 0, 0] > 0.7] = np.nan
            return y

    sp = ParameterSpace((ParameterPrior("a", "normal", 0.0, 1.0), ParameterPrior("b", "normal", 0.0, 1.0)))
    x0 = np.array([0.5, 0.1])
    lin = LinearisedModel(Quadratic(), sp, x0, np.array([0.4, 0.2]))  # a + 0.4 = 0.9 fails, 0.7 does not
    X = np.array([[0.3, 0.0], [0.65, 0.25], [0.9, -0.1]])
    want = Quadratic().predict(sp.params(X), strict=False)
    want[2] = 1.0 + 2.0 * 0.9 + 3.0 * 0.81 * t - 0.1 - 0.005  # the model fails there; the parabola does not
    assert lin.predict(X) == pytest.approx(want, rel=1e-9, abs=1e-9)
    with pytest.raises(ModelError, match="expansion point"):
        LinearisedModel(Quadratic(), sp, np.array([0.8, 0.0]), np.array([0.1, 0.1]))


def test_nested_rhat_passes_a_mixed_ensemble_and_fails_walkers_that_stay_apart():
    rng = np.random.default_rng(0)
    mixed = rng.standard_normal((2000, 54))
    assert smp.nested_rhat(mixed) < 1.005
    # every walker moves only around its own start (a start spread of one posterior sd): the
    # ensemble has not mixed, although each walker's chain looks stationary
    stuck = rng.standard_normal(54) + 0.1 * rng.standard_normal((2000, 54))
    assert smp.nested_rhat(stuck) > 1.01
    # one group of walkers half a posterior sd off the rest
    shifted = mixed.copy()
    shifted[:, :14] += 0.5
    assert smp.nested_rhat(shifted) > 1.01


def test_step_data_assumes_no_less_noise_than_the_data_and_the_model_resolve(monkeypatch):
    import dataclasses

    from tembayes.bench import bench
    from tembayes.bench.hifi import hifi_rig
    from tembayes.bench.protocols import identification_staircase
    from tembayes.calibrate.stepdata import NOISE_FLOOR, step_data
    from tembayes.data.quality import noise_estimate

    module = bench.draw_truth(bench.BenchConfig(n_modules=1), np.random.default_rng(0))["modules"]["TEM1"]

    def run():
        return bench.run_experiment(
            identification_staircase(hold=300.0),
            module,
            {},
            np.random.default_rng(1),
            rate=1.0,
            rig=hifi_rig(layers=True),
        )

    noisy = step_data(run(), face=FACE)  # the floors leave a run with the bench's noise alone
    assert noisy.noise[1] == pytest.approx(np.sqrt(2) * bench.NOISE["temperature_K"], rel=0.15)
    monkeypatch.setattr(bench, "NOISE", {k: 0.0 for k in bench.NOISE})
    exp = run()
    clean = step_data(exp, face=FACE)
    assert np.all(
        clean.noise
        >= [
            NOISE_FLOOR["voltage_V"],
            np.sqrt(2) * NOISE_FLOOR["temperature_K"],
            NOISE_FLOOR["temperature_K"] / np.sqrt(2),
        ]
    ) and np.all(clean.level_sd > 0)
    # a logger at 10 mK, 1 mV and 1 mA: its quiet holds repeat values, the second differences' noise
    # estimate is ~0, and the rounding error (q / sqrt(12)) is what the likelihood must assume
    q = {"sensors": 0.01, "voltage": 1e-3, "current": 1e-3}
    coarse = dataclasses.replace(exp, **{k: np.round(getattr(exp, k) / v) * v for k, v in q.items()})
    assert noise_estimate(coarse.sensors[1]) < 1e-3
    rounded = step_data(coarse, face=FACE)
    assert rounded.noise[1] == pytest.approx(np.sqrt(2) * 0.01 / np.sqrt(12), rel=1e-6)
    assert rounded.noise[0] >= 1e-3 / np.sqrt(12)  # the voltage keeps moving with the temperatures


def test_a_resume_state_of_other_coordinates_is_not_read_as_this_versions(tmp_path, monkeypatch):
    """A state written when g was sampled as log g must not be resumed as 1/g: refused with a warning,
    its chain chunks removed, the module started again from its mode; a state of the same coordinates resumes."""
    import json
    from types import SimpleNamespace

    from tembayes.calibrate import module as M

    space = ParameterSpace(
        (
            rig_prior(next(q for q in REFERENCE.parameters if q.name == "g_paste_hot")),
            ParameterPrior("step_shift_s", "uniform", 0.0, 0.1),
        )
    )
    prob = SimpleNamespace(
        module_id="TEM1",
        space=space,
        model_space=space,
        model=None,
        data=None,
        experiment=None,
        rig_config={},
        options=M.CalibrationOptions(),
    )
    monkeypatch.setattr(M, "step_method_laws", lambda *a: {})
    monkeypatch.setattr(M, "fit_map", lambda *a, **kw: (np.array([1 / 40, 0.0]), np.eye(2), SimpleNamespace(nfev=7)))
    state_file, chunk = tmp_path / "TEM1.json", tmp_path / "TEM1.stage0.00000.npz"
    old = {"coordinates": {"g_paste_hot": "lognormal", "step_shift_s": "uniform"}, "x_map": [3.56, 0.0], "stage": 1}
    state_file.write_text(json.dumps(old))
    chunk.write_bytes(b"chain in log g")
    with pytest.warns(RuntimeWarning, match="samples other coordinates"):
        state = M._start_state(prob, str(state_file), True, None, lambda msg: None)
    assert state["x_map"] == [1 / 40, 0.0] and state["stage"] == 0 and not chunk.exists()
    assert json.loads(state_file.read_text())["coordinates"] == {"g_paste_hot": "reciprocal", "step_shift_s": "uniform"}
    # written by this version: resumed as stored
    assert M._start_state(prob, str(state_file), True, None, lambda msg: None) == state


def test_boundary_smoothing_keeps_a_curve_and_takes_the_noise_of_a_10_s_average():
    """A liquid plate sent to a new setpoint (circulator time constant 90 s) under 4 mK of white noise at
    5 Hz: the local quadratic follows the curve to well under a millikelvin where a 10 s moving average
    is off by ~T'' w^2 / 24 = 10 mK, and leaves the noise of a 10 s average (sd / sqrt(50): 0.57 mK)
    within 30 %."""
    from tembayes.calibrate.stepdata import smooth_boundary

    t = np.arange(0.0, 1200.0, 0.2)
    curve = 308.0 + 20.0 * (1.0 - np.exp(-np.clip(t - 300.0, 0.0, None) / 90.0))
    rng = np.random.default_rng(11)
    noise = 0.004 * rng.standard_normal(len(t))
    smooth = smooth_boundary(t, curve + noise)
    ramp = (t > 330.0) & (t < 600.0)  # away from the kink, where any smoother smears
    assert np.max(np.abs(smooth_boundary(t, curve)[ramp] - curve[ramp])) < 1e-3
    moving = np.convolve(curve, np.ones(50) / 50, mode="same")
    assert np.max(np.abs(moving[ramp] - curve[ramp])) > 5e-3  # the bias the quadratic removes
    flat = t > 1000.0
    sd = np.std(smooth[flat] - curve[flat])
    assert 0.7 * 0.004 / np.sqrt(50) < sd < 1.3 * 0.004 / np.sqrt(50)


def test_the_step_model_adds_grid_points_where_a_boundary_moves_fast():
    """Linear between the grid's points a boundary must stay within the mean temperature's noise sd of
    the measured one: a plate ramp gets points until it does; a slow drift gets none."""
    from types import SimpleNamespace

    from tembayes.calibrate.model import KNOT_TOL, boundary_knots

    t = np.arange(0.0, 3000.0, 0.2)
    grid = np.concatenate([[0.0], np.arange(0.0, 3000.0, 20.0)[1:], [2999.8]])
    noise = np.array([1e-3, 5.6e-3, 2.8e-3])
    ramp = 308.0 + 20.0 * (1.0 - np.exp(-np.clip(t - 1000.0, 0.0, None) / 90.0))
    drift = 298.0 + 0.05 * np.sin(2 * np.pi * t / 600.0)
    data = SimpleNamespace(boundary_time=t, boundary_values=np.vstack([ramp, drift]), noise=noise)
    knots = boundary_knots(data, grid)
    assert len(knots) > 10 and np.all((knots > 1000.0) & (knots < 1600.0))  # only on the ramp's curve
    pts = np.union1d(grid, knots)
    err = np.abs(np.interp(t, pts, np.interp(pts, t, ramp)) - ramp)
    assert err.max() <= KNOT_TOL * noise[2]
    before = np.abs(np.interp(t, grid, np.interp(grid, t, ramp)) - ramp)
    assert before.max() > 20 * KNOT_TOL * noise[2]  # the test is not vacuous
    slow = SimpleNamespace(boundary_time=t, boundary_values=drift[None], noise=noise)
    assert len(boundary_knots(slow, grid)) == 0


def test_the_pasted_population_table_never_states_a_spread_more_precisely_than_learned():
    from tembayes.calibrate.batch import population_table

    for sd in (0.510360968, 0.51, 0.0995, 2.345):
        stated = float(population_table({"tau_S0_rel": (0.01, sd)}).splitlines()[-1].split("=")[1])
        # rounded up to three significant digits: at least what was learned, by under one in a hundred
        assert sd <= stated <= sd * 1.01
