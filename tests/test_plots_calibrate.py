"""Figures of a calibration run (tembayes.plots.calibrate).

The runs are built by hand: :class:`ModuleCalibration` objects with known
Gaussian draws, step tables and log-likelihoods, written with the real
writers (:func:`results.to_inference_data`, :func:`results.write_netcdf`,
:func:`results.summary`), so the tests read exactly the files
``tembayes calibrate`` writes, without sampling anything.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.image as mpimg  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from tembayes.calibrate import results  # noqa: E402
from tembayes.calibrate.diagnostics import ModuleDiagnostics, PsisCheck  # noqa: E402
from tembayes.calibrate.module import ModuleCalibration  # noqa: E402
from tembayes.calibrate.population import PopulationResult  # noqa: E402
from tembayes.constants import KELVIN, MODULE_PARAMETERS  # noqa: E402
from tembayes.data import write_json  # noqa: E402
from tembayes.errors import DataError, TembayesError  # noqa: E402
from tembayes.plots.calibrate import (  # noqa: E402
    MAX_OVERLAY_MODULES,
    load_run,
    plot_corner_module,
    plot_corner_population,
    plot_hysteresis,
    plot_laws,
    plot_step_loglike,
    save_calibration_figures,
)

# Blank (single-colour) images have pixel std 0; a figure with axes and traces is far above.
MIN_PIXEL_STD = 0.02
MIN_PNG_BYTES = 10_000

TRUTH = {"R0_ohm": 1.75, "R1_ohm_per_K": 0.0103, "S0_V_per_K": 0.0467, "S1_V_per_K2": 9.1e-5, "K_W_per_K": 0.54}
POST_SD = {"R0_ohm": 1e-3, "R1_ohm_per_K": 2e-5, "S0_V_per_K": 4e-5, "S1_V_per_K2": 2.5e-7, "K_W_per_K": 5e-4}
PER_STEP = 20  # samples per step window
NW, KEEP = 8, 40  # walkers, kept draws


def make_module(mid, rng, *, n_steps=6, offset=0.0, converged=True, hyst_z=0.5):
    """A ModuleCalibration with Gaussian draws around TRUTH (R0 and S0 shifted by ``offset`` relative)."""
    centre = dict(TRUTH)
    centre["R0_ohm"] *= 1 + offset
    centre["S0_V_per_K"] *= 1 - offset
    names = MODULE_PARAMETERS + ("step_shift_s",)
    draws = {k: centre[k] + POST_SD[k] * rng.standard_normal((NW, KEEP)) for k in MODULE_PARAMETERS}
    draws["step_shift_s"] = 0.05 * rng.standard_normal((NW, KEEP))
    tavg_C = np.linspace(15.0, 50.0, n_steps)
    # the fit gets worse at high temperature: -0.05 nats/sample per 10 K
    per_sample = 13.7 - 0.005 * (tavg_C - 15.0)
    step_ll = PER_STEP * per_sample + 0.5 * rng.standard_normal((NW, KEEP, n_steps))
    n_obs = n_steps * PER_STEP
    step = np.repeat(np.arange(n_steps), PER_STEP)
    t_s = 120.0 * np.arange(n_steps)
    time_s = t_s[step] + np.tile(np.arange(PER_STEP) * 2.0, n_steps)
    priors = {k: {"kind": "lognormal", "center": TRUTH[k], "scale": 0.3} for k in ("R0_ohm", "S0_V_per_K", "K_W_per_K")}
    priors.update(
        {k: {"kind": "normal", "center": TRUTH[k], "scale": 0.2 * TRUTH[k]} for k in ("R1_ohm_per_K", "S1_V_per_K2")}
    )
    priors["step_shift_s"] = {"kind": "uniform", "center": 0.0, "scale": 1.0}
    diag = ModuleDiagnostics(
        rhat={},
        ess_bulk={},
        ess_tail={},
        tau_steps={},
        rhat_max=1.002 if converged else 1.09,
        rhat_walkers_max=1.01,
        ess_bulk_min=900.0 if converged else 120.0,
        tau_max_steps=50.0,
        tau_max_all_steps=50.0,
        chain_over_tau=60.0,
        steps=3000,
        burn_in_steps=750,
        nwalkers=NW,
        acceptance_mean=0.3,
        acceptance_min=0.2,
        sampler_converged=converged,
        psis=(PsisCheck(stage=1, k_hat=0.3, weight_ess_fraction=0.9, max_logw_dev=1.0),),
        resumed=False,
        map_nfev=10,
        level_band_neglected=0.0,
        discrepancy={"method": "none"},
        adequacy={},
        timings={"total_s": 1.0},
    )
    hyst = {
        "R_ohm": {"estimate": hyst_z * 1e-4, "sd": 1e-4, "z": hyst_z},
        "S_V_per_K": {"estimate": -hyst_z * 2e-7, "sd": 2e-7, "z": -hyst_z},
    }
    return ModuleCalibration(
        module_id=mid,
        names=names,
        draws=draws,
        log_prob=rng.normal(-100, 1, (NW, KEEP)),
        step_loglike=step_ll,
        priors=priors,
        map={k: centre[k] for k in MODULE_PARAMETERS},
        diagnostics=diag,
        steps={
            "t_s": t_s,
            "dI_A": 0.5 * np.where(np.arange(n_steps) % 2 == 0, 1.0, -1.0),
            "direction": np.where(np.arange(n_steps) % 2 == 0, 1, -1),
            "Tavg_K": tavg_C + KELVIN,
        },
        observed={
            "time_s": time_s,
            "step": step,
            "since_s": time_s - t_s[step],
            "obs": rng.normal(0, 1, (3, n_obs)),
            "noise": np.array([1e-4, 1e-3, 1e-3]),
        },
        hysteresis=hyst,
        seed={"run": 0, "emcee": 1},
        rig="test",
        options={},
    )


def make_population(mods, outlier_prob, rng, nw=4, nd=50):
    centre = np.array([TRUTH[k] for k in MODULE_PARAMETERS])
    pred = centre * (1 + 0.02 * rng.standard_normal((nw * nd, len(centre))))
    hyper = {f"mu_{k}": TRUTH[k] * (1 + 1e-3 * rng.standard_normal((nw, nd))) for k in MODULE_PARAMETERS}
    hyper["outlier_fraction"] = rng.uniform(0, 0.2, (nw, nd))
    return PopulationResult(
        module_ids=tuple(m.module_id for m in mods),
        outlier_prob=dict(outlier_prob),
        predictive=pred,
        hyper=hyper,
        diagnostics={"converged": True, "rhat_max": 1.01},
    )


def write_run(path, mods, pop=None, rng=None):
    rng = rng or np.random.default_rng(0)
    prior = {k: TRUTH[k] * np.exp(0.3 * rng.standard_normal(500)) for k in MODULE_PARAMETERS}
    idata = results.to_inference_data(mods, population=pop, prior_draws=prior)
    results.write_netcdf(idata, path / "posterior.nc")
    write_json(path / "summary.json", results.summary(mods, pop))
    return path


@pytest.fixture(scope="module")
def run3(tmp_path_factory):
    """Three modules with a population fit: TEM2 is an outlier (p 0.91) with 4 steps (NaN padding), TEM3 not converged."""
    rng = np.random.default_rng(1)
    mods = [
        make_module("TEM1", rng),
        make_module("TEM2", rng, n_steps=4, offset=0.03, hyst_z=3.0),
        make_module("TEM3", rng, converged=False, offset=-0.01),
    ]
    pop = make_population(mods, {"TEM1": 0.02, "TEM2": 0.91, "TEM3": 0.10}, rng)
    return write_run(tmp_path_factory.mktemp("run3"), mods, pop, rng)


@pytest.fixture(scope="module")
def run1(tmp_path_factory):
    """One module, no population group."""
    rng = np.random.default_rng(2)
    return write_run(tmp_path_factory.mktemp("run1"), [make_module("M-only", rng)], None, rng)


def all_texts(fig):
    out = [t.get_text() for t in fig.texts]
    for leg in fig.legends:
        out += [t.get_text() for t in leg.get_texts()]
    for ax in fig.axes:
        out.append(ax.get_title())
        if ax.get_legend() is not None:
            out += [t.get_text() for t in ax.get_legend().get_texts()]
    return out


# --------------------------------------------------------------------------- loading


def test_load_run_reads_modules_population_and_padding(run3):
    run = load_run(run3)
    assert run.module_ids == ("TEM1", "TEM2", "TEM3")
    assert run.has_population
    assert run.outlier_prob("TEM2") == pytest.approx(0.91)
    assert run.converged("TEM3") is False and "NOT CONVERGED" in run.status("TEM3")
    st = run.steps("TEM2")  # 4 of the 6 padded steps
    assert len(st["Tavg_C"]) == 4 and np.all(np.isfinite(st["Tavg_C"]))
    assert np.all(st["n_samples"] == PER_STEP)
    assert run.step_loglike("TEM2").shape == (NW, KEEP, 4)
    X = run.draws("TEM1", max_draws=100)
    assert X.shape == (100, 5)
    assert np.allclose(X.mean(axis=0), [TRUTH[k] for k in MODULE_PARAMETERS], rtol=1e-3)
    assert run.population_draws().shape == (200, 5)
    with pytest.raises(ValueError, match="TEM9"):
        run.draws("TEM9")


def test_missing_posterior_is_a_data_error_naming_the_file(tmp_path, run1):
    (tmp_path / "summary.json").write_text((run1 / "summary.json").read_text())
    with pytest.raises(DataError, match="posterior.nc") as exc:
        load_run(tmp_path)
    assert isinstance(exc.value, TembayesError)
    assert exc.value.path == tmp_path / "posterior.nc"
    with pytest.raises(DataError, match="posterior.nc"):
        save_calibration_figures(tmp_path)


def test_missing_summary_missing_folder_and_broken_file(tmp_path, run1):
    (tmp_path / "posterior.nc").write_bytes((run1 / "posterior.nc").read_bytes())
    with pytest.raises(DataError, match="summary.json"):
        load_run(tmp_path)
    with pytest.raises(DataError, match="not a calibration run folder"):
        load_run(tmp_path / "nope")
    (tmp_path / "summary.json").write_text((run1 / "summary.json").read_text())
    (tmp_path / "posterior.nc").write_bytes(b"not a netcdf file")
    with pytest.raises(DataError, match="cannot be read"):
        load_run(tmp_path)


# --------------------------------------------------------------------------- corner plots


def test_corner_module_titles_units_and_quantiles(run3):
    run = load_run(run3)
    fig = plot_corner_module(run, "TEM2")
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 25
    title = fig._suptitle.get_text()
    assert "TEM2" in title and "0.91" in title and "converged" in title
    diag_titles = [fig.axes[6 * j].get_title() for j in range(5)]
    assert "mΩ/K" in diag_titles[1] and "mV/K" in diag_titles[2] and "µV/K²" in diag_titles[3]
    # the R0 title quotes the posterior median, 4 decimals for a ~1e-3 ohm width
    med = np.median(run.draws("TEM2")[:, 0])
    assert f"{med:.4f}" in diag_titles[0]
    # R1 shown in mohm/K: the diagonal's x range sits around 10.3
    lo, hi = fig.axes[6].get_xlim()
    assert 10.0 < lo < TRUTH["R1_ohm_per_K"] * 1e3 < hi < 10.6


def test_corner_module_marks_non_convergence_and_prior(run3):
    fig = plot_corner_module(run3, "TEM3", show_prior=True, params=("R0_ohm", "K_W_per_K"))
    assert len(fig.axes) == 4
    assert "NOT CONVERGED" in fig._suptitle.get_text()
    assert matplotlib.colors.same_color(fig._suptitle.get_color(), "C3")
    prior_lines = [ln for ax in fig.axes for ln in ax.get_lines() if (ln.get_gid() or "").startswith("prior:")]
    assert len(prior_lines) == 2
    assert all(np.all(np.isfinite(ln.get_ydata())) and np.max(ln.get_ydata()) > 0 for ln in prior_lines)


def test_corner_population_legend_and_shared_ranges(run3):
    run = load_run(run3)
    fig = plot_corner_population(run)
    assert len(fig.axes) == 25
    labels = all_texts(fig)
    for mid, p in (("TEM1", "0.02"), ("TEM2", "0.91"), ("TEM3", "0.10")):
        assert any(mid in t and p in t for t in labels), (mid, labels)
    assert any("population predictive" in t for t in labels)
    assert any("TEM3" in t and "NOT CONVERGED" in t for t in labels)
    axes = np.array(fig.axes).reshape(5, 5)
    # shared ranges: a column's panels have the diagonal's x range, and they cover the population
    pop = run.population_draws()[:, 0]
    for i in range(1, 5):
        assert axes[i, 0].get_xlim() == pytest.approx(axes[0, 0].get_xlim())
    assert axes[0, 0].get_xlim()[0] < np.quantile(pop, 0.01) and axes[0, 0].get_xlim()[1] > np.quantile(pop, 0.99)
    assert axes[0, 0].get_yscale() == "log"


def test_corner_population_many_modules_stays_readable(tmp_path):
    rng = np.random.default_rng(3)
    n = MAX_OVERLAY_MODULES + 8
    mods = [make_module(f"U{i:02d}", rng, n_steps=3) for i in range(n)]
    probs = {m.module_id: p for m, p in zip(mods, np.linspace(0.0, 0.95, n))}
    run = load_run(write_run(tmp_path, mods, make_population(mods, probs, rng), rng))
    fig = plot_corner_population(run)
    labels = [t for t in all_texts(fig) if ": outlier prob" in t]
    assert len(labels) == MAX_OVERLAY_MODULES
    # the highest outlier probabilities are the ones shown
    top = sorted(probs, key=probs.get, reverse=True)[:MAX_OVERLAY_MODULES]
    assert {t.split(":")[0] for t in labels} == set(top)
    assert any("other 8 modules" in t for t in all_texts(fig))
    laws = plot_laws(run)
    assert (
        len([ln for ln in laws.axes[0].get_lines() if (ln.get_gid() or "").startswith("law:U")]) == MAX_OVERLAY_MODULES
    )
    assert len(plot_step_loglike(run).axes) == MAX_OVERLAY_MODULES


# --------------------------------------------------------------------------- laws, hysteresis, step fit


def test_laws_medians_match_the_draws(run3):
    run = load_run(run3)
    fig = plot_laws(run)
    assert len(fig.axes) == 4
    axR, axS = fig.axes[0], fig.axes[1]
    lines = {ln.get_gid(): ln for ln in axR.get_lines() if ln.get_gid()}
    assert {"law:TEM1", "law:TEM2", "law:TEM3", "law:population"} <= set(lines)
    # at Tref the law is R0: the plotted median equals the median of the R0 draws
    T, y = lines["law:TEM2"].get_data()
    assert np.interp(25.0, T, y) == pytest.approx(np.median(run.draws("TEM2")[:, 0]), rel=2e-4)
    # the x range is the steps' temperature range (15-50 degC)
    assert T[0] == pytest.approx(15.0) and T[-1] == pytest.approx(50.0)
    Ts, yS = [ln for ln in axS.get_lines() if ln.get_gid() == "law:TEM1"][0].get_data()
    assert np.interp(25.0, Ts, yS) == pytest.approx(TRUTH["S0_V_per_K"] * 1e3, rel=1e-3)  # mV/K
    assert "[mV/K]" in axS.get_ylabel() and "[Ω]" in axR.get_ylabel()


def test_hysteresis_values_and_flags(run3):
    fig = plot_hysteresis(run3)
    assert len(fig.axes) == 2
    axR = fig.axes[0]
    pts = {}
    for coll in axR.containers:  # ErrorbarContainer
        x, y = coll.lines[0].get_data()
        color = coll.lines[0].get_color()
        for xi, yi in zip(x, y):
            pts[int(xi)] = (yi, color)
    assert pts[0][0] == pytest.approx(0.5 * 0.1)  # TEM1: 0.5e-4 ohm = 0.05 mohm
    assert pts[1][0] == pytest.approx(3.0 * 0.1)  # TEM2: z = 3
    assert matplotlib.colors.same_color(pts[1][1], "C3") and matplotlib.colors.same_color(pts[0][1], "C0")
    assert any(ln.get_ydata()[0] == 0 for ln in axR.get_lines())  # the zero line
    assert [t.get_text() for t in fig.axes[1].get_xticklabels()] == ["TEM1", "TEM2", "TEM3"]


def test_step_loglike_per_sample_and_padding(run3):
    run = load_run(run3)
    fig = plot_step_loglike(run)
    assert len(fig.axes) == 3
    ax2 = fig.axes[1]
    assert "TEM2" in ax2.get_title() and "0.91" in ax2.get_title()
    assert "NOT CONVERGED" in fig.axes[2].get_title()
    pts = [ln for ln in ax2.get_lines() if ln.get_gid() == "steploglike:TEM2"]
    x = np.concatenate([ln.get_xdata() for ln in pts])
    y = np.concatenate([ln.get_ydata() for ln in pts])
    assert len(x) == 4  # the padded steps are not drawn
    expect = run.step_loglike("TEM2").mean(axis=(0, 1)) / PER_STEP
    assert np.sort(y) == pytest.approx(np.sort(expect))
    assert {tuple(matplotlib.colors.to_rgb(ln.get_color())) for ln in pts} == {
        matplotlib.colors.to_rgb("C3"),
        matplotlib.colors.to_rgb("C0"),
    }  # up and down steps


# --------------------------------------------------------------------------- without a population, saving


def test_single_module_without_population(run1):
    run = load_run(run1)
    assert not run.has_population and run.outlier_prob("M-only") is None
    fig = plot_corner_population(run)
    assert len(fig.axes) == 25
    assert "no population fit" in fig._suptitle.get_text()
    assert any("M-only" in t and "n/a" in t for t in all_texts(fig))
    assert len(plot_laws(run).axes) == 4
    assert len(plot_hysteresis(run).axes) == 2
    assert len(plot_step_loglike(run).axes) == 1
    assert "outlier prob n/a" in plot_corner_module(run, "M-only")._suptitle.get_text()


def test_save_calibration_figures_writes_nontrivial_pngs(run3):
    paths = save_calibration_figures(run3, dpi=50)
    names = [p.name for p in paths]
    assert names == [
        "corner_TEM1.png",
        "corner_TEM2.png",
        "corner_TEM3.png",
        "corner_population.png",
        "laws.png",
        "hysteresis.png",
        "step_loglike.png",
    ]
    for p in paths:
        assert p.parent == run3 / "figures" and p.is_file()
        assert p.stat().st_size > MIN_PNG_BYTES, p
        img = mpimg.imread(p)
        assert img.ndim == 3 and float(np.std(img[..., :3])) > MIN_PIXEL_STD, p
    assert not [f for f in (run3 / "figures").iterdir() if f.name.startswith(".")]  # no temporary files left


def test_plots_draw_into_the_figure_given(run3):
    from matplotlib.figure import Figure

    run = load_run(run3)
    for plot in (plot_laws, plot_hysteresis, plot_step_loglike, plot_corner_population):
        fig = Figure()
        assert plot(run, fig=fig) is fig and len(fig.axes) >= 2, plot.__name__
    fig = Figure()
    assert plot_corner_module(run, "TEM1", fig=fig) is fig
    assert len(fig.axes) == len(MODULE_PARAMETERS) ** 2
    # a corner plot lays out its own grid: a figure that already holds axes is refused
    with pytest.raises(ValueError, match="empty figure"):
        plot_corner_module(run, "TEM1", fig=fig)
