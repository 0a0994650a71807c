"""The window sandwich (:mod:`tembayes.calibrate.discrepancy`): known answers on a linear model.

Replicated regressions with 24 windows: when every window follows the model,
the sandwich keeps the posterior (90 % intervals cover in their binomial
band); when the windows' coefficients scatter about the truth (a model that
is right on average but not in every regime), the plain posterior covers far
too rarely and the sandwich brings it back into the band.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom

from tembayes.calibrate.discrepancy import window_sandwich, window_scores

K, N, SIGMA = 24, 50, 1.0
TRUTH = np.array([1.0, -0.5])
REPS = 300


def _replicate(rng, spread):
    """Posterior draws (flat prior) and window log-likelihoods of one data set."""
    X = [np.column_stack([np.ones(N), rng.uniform(-1, 1, N) + k / K]) for k in range(K)]
    y = [x @ (TRUTH + spread * rng.standard_normal(2)) + SIGMA * rng.standard_normal(N) for x in X]
    A = np.vstack(X)
    cov = SIGMA**2 * np.linalg.inv(A.T @ A)
    mean = cov @ A.T @ np.concatenate(y) / SIGMA**2
    draws = rng.multivariate_normal(mean, cov, 2000)
    L = np.column_stack([-0.5 * np.sum((yk[None] - draws @ xk.T) ** 2, axis=1) / SIGMA**2 for xk, yk in zip(X, y)])
    return draws, L


def _coverage(spread, seed):
    rng = np.random.default_rng(seed)
    plain = wide = 0
    for _ in range(REPS):
        draws, L = _replicate(rng, spread)
        w = window_sandwich(draws, L, [0, 1])
        c = draws.mean(axis=0)
        stretched = c + (draws - c) @ w.stretch.T
        for d, hits in ((draws, "plain"), (stretched, "wide")):
            lo, hi = np.quantile(d[:, 0], [0.05, 0.95])
            if hits == "plain":
                plain += lo <= TRUTH[0] <= hi
            else:
                wide += lo <= TRUTH[0] <= hi
    return plain / REPS, wide / REPS


def _band(p=0.9, n=REPS):
    return binom.ppf(0.025, n, p) / n, binom.ppf(0.975, n, p) / n


def test_scores_are_the_gradients_of_a_quadratic_log_likelihood():
    rng = np.random.default_rng(0)
    draws, L = _replicate(rng, 0.0)
    S = window_scores(draws, L)
    # the windows' gradients sum to the total's, zero at the (flat-prior) posterior mean up to the draws' scatter
    assert np.all(np.abs(S.sum(axis=0)) < 0.05 * np.abs(S).sum(axis=0))


def test_correct_model_keeps_its_coverage():
    lo, hi = _band()
    plain, wide = _coverage(0.0, 1)
    assert lo <= plain <= hi and lo <= wide <= hi + 0.02  # flooring at 1 widens a little, never narrows


def test_windows_that_disagree_are_covered_by_the_sandwich_not_by_the_posterior():
    lo, hi = _band()
    plain, wide = _coverage(0.3, 3)
    assert plain < 0.7  # the plain posterior is overconfident (0.60 measured)
    assert lo - 0.03 <= wide <= hi  # the sandwich is honest (24 windows estimate V with some scatter)


T_LINEAR = np.linspace(0.0, 1.0, 50)


def _linear_problem(held_values, fails=()):
    """The known-answer problem ``y = a t + b + 0.3 log(q) t^2`` with rig values held at ``held_values``
    (only ``q`` enters ``y``); a probe that moves a held value named in ``fails`` comes back as NaN,
    as ``predict(strict=False)`` returns a simulation that failed.  Returns ``(model, space, J, held)``."""
    from tembayes.calibrate.priors import ParameterPrior
    from tembayes.physics.rig import RigParameter

    t = T_LINEAR

    class Space:
        priors = (ParameterPrior("a", "uniform", 0.0, 1.0), ParameterPrior("b", "uniform", 0.0, 1.0))
        fixed = dict(held_values)

        def params(self, X):
            return {"a": X[:, 0], "b": X[:, 1], **{k: np.full(len(X), v) for k, v in held_values.items()}}

    class Model:
        def predict(self, P, strict=True):
            assert not strict  # a failed probe must come back as NaN, not raise
            a, b, q = (np.asarray(P[k], float)[:, None] for k in ("a", "b", "q"))
            y = (a * t + b + 0.3 * np.log(q) * t**2)[:, None, :]
            moved = np.zeros(len(y), bool)
            for k in fails:
                moved |= np.asarray(P[k]) != held_values[k]
            return np.where(moved[:, None, None], np.nan, y)

    J = np.stack([t, np.ones_like(t)])[:, None, :]  # (p, nc, n)
    held = {k: RigParameter(k, v, v * np.exp(-0.4), v * np.exp(0.4), "1") for k, v in held_values.items()}
    return Model(), Space(), J, held


def test_a_held_parameter_moves_the_mode_as_its_linear_response_says():
    """Known answer on a linear model: y = a t + b + 0.3 log(q) t^2, q held at 2 while the data's is
    2 e^0.2: the least-squares fit of (a, b) moves by exactly the computed shift times 0.2."""
    from tembayes.calibrate.discrepancy import held_nuisance_spread

    t = T_LINEAR
    model, space, J, held = _linear_problem({"q": 2.0})
    spread = held_nuisance_spread(model, space, np.array([1.0, 0.5]), J, np.array([0.01]), held)
    assert spread.not_carried == ()
    y_true = 1.0 * t + 0.5 + 0.3 * (np.log(2.0) + 0.2) * t**2
    y_held = 1.0 * t + 0.5 + 0.3 * np.log(2.0) * t**2
    A = np.column_stack([t, np.ones_like(t)])
    move = np.linalg.lstsq(A, y_true - y_held, rcond=None)[0]
    np.testing.assert_allclose(spread.shift[:, 0] * 0.2, -move, rtol=1e-6)  # the held value errs by -0.2
    np.testing.assert_allclose(spread.sd, [0.8 / np.sqrt(12.0)])  # uniform over the log range
    xi = spread.draw(np.random.default_rng(0), 20000)
    X = spread.apply(np.zeros((20000, 2)), xi)
    np.testing.assert_allclose(X.std(axis=0), np.abs(spread.shift[:, 0]) * 0.8 / np.sqrt(12.0), rtol=0.03)
    # a positive coordinate (a resistance) is moved relatively: the same spread, never across zero
    centre = 2.0 * X[:, 1].std()
    # (X may carry more coordinates than the model's, e.g. the noise's: they are left alone)
    Y = np.column_stack([np.zeros(20000), np.full(20000, centre), np.ones(20000)])
    R = spread.apply(Y, xi, relative=[1])
    assert np.all(R[:, 2] == 1.0)
    assert np.all(R[:, 1] > 0) and np.any(X[:, 1] < -centre)  # shifted linearly, 2 % of the draws would cross zero
    np.testing.assert_allclose(np.log(R[:, 1] / centre), X[:, 1] / centre, rtol=1e-9, atol=1e-12)


def test_a_draw_keeps_the_held_value_its_laws_were_moved_for():
    """Known answer on the linear model: a draw moved by the held q's deviation xi, simulated at its own
    q = 2 e^xi, varies from the mode's prediction only by the part of 0.3 xi t^2 that (a, b) cannot take
    up (the least-squares residual); simulated at the held q = 2 it varies by the part they did take up.
    A parameter that was not carried over keeps its held value."""
    from tembayes.calibrate.discrepancy import held_nuisance_spread

    t = T_LINEAR
    model, space, J, held = _linear_problem({"q": 2.0, "r": 3.0}, fails=("r",))
    spread = held_nuisance_spread(model, space, np.array([1.0, 0.5]), J, np.array([0.01]), held)
    xi = spread.draw(np.random.default_rng(1), 20000)
    X = spread.apply(np.tile([1.0, 0.5], (20000, 1)), xi)
    values = spread.values(xi)
    np.testing.assert_allclose(values["q"], 2.0 * np.exp(xi[:, 0]), rtol=1e-12)
    assert np.all(values["r"] == 3.0)

    def predicted(q):
        return model.predict({"a": X[:, 0], "b": X[:, 1], "q": q, "r": np.full(20000, 3.0)}, strict=False)[:, 0]

    A = np.column_stack([t, np.ones_like(t)])
    taken = A @ np.linalg.lstsq(A, 0.3 * t**2, rcond=None)[0]
    sd = spread.sd[0]
    np.testing.assert_allclose(
        predicted(values["q"]).std(axis=0), sd * np.abs(0.3 * t**2 - taken), rtol=0.03, atol=1e-9
    )
    np.testing.assert_allclose(predicted(np.full(20000, 2.0)).std(axis=0), sd * np.abs(taken), rtol=0.03, atol=1e-9)


def test_a_share_is_moved_in_its_logit_never_out_of_its_range():
    """A share (a sensor's lead share) pushed by three times its value per sd stays inside its flat prior's
    range (moved relatively, some draws would pass one); pushed a little it moves as the linear shift does."""
    from tembayes.calibrate.discrepancy import HeldSpread

    for push, mean, (low, high), close in (
        (0.003, 0.001, (0.0, 1.0), False),
        (0.003, 0.001, (1e-4, 1e-2), False),
        (1e-4, 0.3, (0.0, 1.0), True),
    ):
        one = HeldSpread(names=("q",), sd=np.array([1.0]), shift=np.array([[0.0], [push]]), held_value=np.ones(1))
        X = np.column_stack([np.zeros(20000), np.full(20000, mean)])
        S = one.apply(X, one.draw(np.random.default_rng(0), 20000), shares={1: (low, high)})
        assert np.all((S[:, 1] > low) & (S[:, 1] < high))
        if close:
            np.testing.assert_allclose(S[:, 1].std(), push, rtol=0.02)
        else:  # the same draws of the held parameter, moved relatively
            xi = np.random.default_rng(0).standard_normal(20000)
            assert np.any(mean * np.exp(xi * push / mean) > high)


def test_a_held_parameter_the_model_cannot_simulate_is_named_not_fatal():
    """A posterior centre the exact model cannot simulate for one held parameter's probes (NaN, as
    ``predict(strict=False)`` returns them): that parameter is listed as not carried over, with no
    shift, and the other's shift is its known linear response, as without it."""
    from tembayes.calibrate.discrepancy import held_nuisance_spread

    t = T_LINEAR
    model, space, J, held = _linear_problem({"q": 2.0, "r": 3.0}, fails=("r",))
    spread = held_nuisance_spread(model, space, np.array([1.0, 0.5]), J, np.array([0.01]), held)
    assert spread.not_carried == ("r",)
    assert np.all(spread.shift[:, 1] == 0.0)
    A = np.column_stack([t, np.ones_like(t)])
    move = np.linalg.lstsq(A, 0.3 * 0.2 * t**2, rcond=None)[0]
    np.testing.assert_allclose(spread.shift[:, 0] * 0.2, -move, rtol=1e-6)


def test_a_held_share_is_carried_in_its_logit_and_stays_below_one():
    """A held share over 0.2-0.9 (a bottom block's tabs): moved in its log, 0.5 e^d passed one in 5.5 % of
    the carry-over's draws; in its logit every draw is a share, its logit moved by exactly the draw, and
    the anchoring's own draws of it (a run that kept none) are shares too."""
    from types import SimpleNamespace

    from tembayes.calibrate.discrepancy import held_nuisance_spread
    from tembayes.calibrate.priors import logit
    from tembayes.physics.rig import RigParameter
    from tembayes.predict.anchor import held_draws

    share = RigParameter("q", 0.5, 0.2, 0.9, "1", held=True)
    assert share.is_share
    assert share.spread_sd == pytest.approx((logit(0.9) - logit(0.2)) / np.sqrt(12.0))
    model, space, J, _ = _linear_problem({"q": 0.5})
    spread = held_nuisance_spread(model, space, np.array([1.0, 0.5]), J, np.array([0.01]), {"q": share})
    assert spread.shares == ("q",) and spread.sd[0] == pytest.approx(share.spread_sd)
    xi = spread.draw(np.random.default_rng(2), 20000)
    q = spread.values(xi)["q"]
    assert np.all((q > 0) & (q < 1))
    old = 0.5 * np.exp(xi[:, 0] / share.spread_sd * np.log(4.5) / np.sqrt(12.0))  # the same draws in the log
    assert 0.04 < np.mean(old > 1) < 0.07
    np.testing.assert_allclose(logit(q), xi[:, 0], atol=1e-9)
    # the response per unit of logit: at 0.5, d log q / d logit q = 1 - q = 0.5, so half the log's shift
    log_space = held_nuisance_spread(
        model, space, np.array([1.0, 0.5]), J, np.array([0.01]), {"q": RigParameter("q", 0.5, 0.4, 0.6, "W/K")}
    )
    np.testing.assert_allclose(spread.shift, 0.5 * log_space.shift, rtol=2e-3)
    drawn = held_draws(SimpleNamespace(parameters=(share,), depths={}), {"R0_ohm": np.ones(4000)}, {}, "TEM1")["q"]
    assert np.all((drawn > 0) & (drawn < 1))
    assert np.std(logit(drawn)) == pytest.approx(share.spread_sd, rel=0.05)
