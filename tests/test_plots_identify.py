"""Figures of the identification (tembayes.plots.identify).

Fast tests draw from hand-built inputs (a contract CSV from ``data_factory``,
a "simulation" that is the measurement plus a known offset, step tables of a
known law).  The end-to-end tests run the real pipeline on a tiny bench batch
(2 modules, 120 s holds at 2 Hz, one 20 min validation run); identify_batch
alone takes ~40 s there, so they are marked slow.
"""

from __future__ import annotations

from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")

import matplotlib.image as mpimg  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from tembayes.constants import KELVIN, T_REF  # noqa: E402
from tembayes.data import load_batch  # noqa: E402
from tembayes.identify.fits import fit_line  # noqa: E402
from tembayes.physics.simulate import Simulation  # noqa: E402
from tembayes.plots import (  # noqa: E402
    plot_error_vs_tavg,
    plot_identification_run,
    plot_law,
    plot_validation,
    save_identify_figures,
)

# Blank (single-colour) images have pixel std 0; any figure with axes, text
# and traces is far above this.
MIN_PIXEL_STD = 0.02


def gids(ax, prefix):
    return sorted(ln.get_gid() for ln in ax.get_lines() if (ln.get_gid() or "").startswith(prefix))


def assert_labelled(ax):
    """A y label with units (x labels: only the bottom panel of shared axes has one)."""
    assert ax.get_ylabel(), "every panel needs a y label with units"
    assert "[" in ax.get_ylabel() and "]" in ax.get_ylabel(), ax.get_ylabel()


def offset_simulation(exp, offset_K):
    """A Simulation that reads ``offset_K`` below the measurement on every sensor."""
    n = exp.n
    return Simulation(
        time=exp.time.copy(),
        channels=("T1_C", "T2_C", "T3_C", "T4_C"),
        sensors=(exp.sensors - offset_K)[None],
        voltage=exp.voltage[None].copy(),
        t_hot=exp.sensors[1][None].copy(),
        t_cold=exp.sensors[2][None].copy(),
        steps=np.array([n]),
    )


def fake_identification(seed, R0=1.7, R1=0.01, S0=0.048, S1=9e-5):
    """A ModuleIdentification look-alike: step rows on a known law plus noise."""
    rng = np.random.default_rng(seed)
    T = KELVIN + np.linspace(15.0, 50.0, 16)
    R = R0 + R1 * (T - T_REF) + rng.normal(0, 0.005, T.size)
    S = S0 + S1 * (T - T_REF) + rng.normal(0, 2e-4, T.size)
    S[3] = np.nan  # a hold without usable S
    rows = []
    for k, (t, r, s) in enumerate(zip(T, R, S)):
        rows.append(
            {
                "direction": "up" if k % 2 == 0 else "down",
                "Tavg_R": t,
                "Tavg_R_sd": 0.05,
                "Tavg_R_paper": t - 1.0,
                "jump": SimpleNamespace(R=r, R_sd=0.005, R_first=r * 1.03),
                "Tavg": t,
                "Th_sd": 0.1,
                "Tc_sd": 0.1,
                "S": s,
                "S_sd": 2e-4,
                "Tavg_paper": t - 1.5,
                "S_paper": s * 0.97,
            }
        )
    ok = np.isfinite(S)
    lines = {"R": fit_line(T, R, np.full(T.size, 0.005)), "S": fit_line(T[ok], S[ok], np.full(ok.sum(), 2e-4))}
    hysteresis = {"R": {"diff": 0.0012, "sd": 0.003}, "S": {"diff": None, "sd": None}}
    return SimpleNamespace(steps=rows, lines=lines, hysteresis=hysteresis)


@pytest.fixture
def loaded_batch(data_factory):
    return load_batch(data_factory.batch(modules=("TEM1", "TEM2", "TEM3")))


# --- fast ------------------------------------------------------------------


def test_identification_run_panels(loaded_batch):
    exps = {mid: m.identification for mid, m in loaded_batch.modules.items()}
    fig = plot_identification_run(exps, face=loaded_batch.layout.face)
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 3
    for ax in fig.axes:
        assert_labelled(ax)
        assert gids(ax, "run:") == ["run:TEM1", "run:TEM2", "run:TEM3"]
    assert fig.axes[-1].get_xlabel().endswith("[h]")
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == ["TEM1", "TEM2", "TEM3"]
    # one colour per module, in the paper's order
    colours = [ln.get_color() for ln in fig.axes[0].get_lines() if ln.get_gid()]
    assert colours == ["C0", "C1", "C2"]


def test_draws_into_given_figure_and_refuses_a_used_one(loaded_batch):
    exps = {"TEM1": loaded_batch.modules["TEM1"].identification}
    fig = Figure()
    assert plot_identification_run(exps, face=("T2_C", "T3_C"), fig=fig) is fig
    with pytest.raises(ValueError, match="empty Figure, found one with 3 axes"):
        plot_identification_run(exps, face=("T2_C", "T3_C"), fig=fig)


def test_validation_residuals_and_rmse(loaded_batch):
    exp = loaded_batch.modules["TEM1"].validations[0]
    fig = plot_validation(exp, offset_simulation(exp, 0.1), title="TEM1 check")
    assert len(fig.axes) == 2
    top, bottom = fig.axes
    for ax in fig.axes:
        assert_labelled(ax)
    assert top.get_title() == "TEM1 check"
    assert bottom.get_xlabel().endswith("[h]")
    assert len(gids(top, "measured:")) == 4 and len(gids(top, "simulated:")) == 4
    assert gids(bottom, "residual:") == ["residual:T1", "residual:T2", "residual:T3", "residual:T4"]
    res = [ln for ln in bottom.get_lines() if ln.get_gid() == "residual:T3"][0]
    np.testing.assert_allclose(res.get_ydata(), 0.1, atol=1e-12)
    labels = [t.get_text() for t in bottom.get_legend().get_texts()]
    assert "T1: RMSE 0.10 K" in labels and any("0.5 K" in s for s in labels)
    # top panel in degC, not kelvin
    meas = [ln for ln in top.get_lines() if ln.get_gid() == "measured:T1"][0]
    assert np.all(meas.get_ydata() < 100.0)


def test_validation_interpolates_a_coarser_simulation(loaded_batch):
    exp = loaded_batch.modules["TEM1"].validations[0]
    sim = offset_simulation(exp, 0.2)
    coarse = Simulation(
        sim.time[::5],
        sim.channels,
        sim.sensors[:, :, ::5],
        sim.voltage[:, ::5],
        sim.t_hot[:, ::5],
        sim.t_cold[:, ::5],
        sim.steps,
    )
    fig = plot_validation(exp, coarse)
    res = [ln for ln in fig.axes[1].get_lines() if ln.get_gid() == "residual:T1"][0]
    assert res.get_ydata().shape == exp.time.shape
    assert "TEM1/validation.csv" in fig.axes[0].get_title()


def test_error_vs_tavg_one_rms_line_per_model(loaded_batch):
    exp = loaded_batch.modules["TEM1"].validations[0]
    sims = {"constant": offset_simulation(exp, 0.3), "linear": offset_simulation(exp, -0.1)}
    fig = plot_error_vs_tavg(exp, sims, face=loaded_batch.layout.face)
    assert len(fig.axes) == 1
    ax = fig.axes[0]
    assert_labelled(ax)
    assert "°C" in ax.get_xlabel()
    assert gids(ax, "rms:") == ["rms:constant", "rms:linear"]
    rms = {ln.get_gid(): ln.get_ydata() for ln in ax.get_lines() if (ln.get_gid() or "").startswith("rms:")}
    np.testing.assert_allclose(rms["rms:constant"], 0.3, rtol=1e-9)
    np.testing.assert_allclose(rms["rms:linear"], 0.1, rtol=1e-9)
    assert any(np.allclose(ln.get_xdata(), 35.0) for ln in ax.get_lines())  # the 35 degC marker
    assert len(ax.collections) == 2 and all(c.get_rasterized() for c in ax.collections)
    assert "constant (overall RMSE 0.30 K)" in [t.get_text() for t in ax.get_legend().get_texts()]


@pytest.mark.parametrize("which, ylabel", [("R", "R_m [ohm]"), ("S", "S_m [mV/K]")])
def test_law_lines_bands_and_units(which, ylabel):
    results = {"TEM1": fake_identification(1), "TEM2": fake_identification(2, R0=1.75, S0=0.047)}
    average = {"R0_ohm": 1.725, "R1_ohm_per_K": 0.01, "S0_V_per_K": 0.0475, "S1_V_per_K2": 9e-5}
    fig = plot_law(results, which, average=average)
    ax = fig.axes[0]
    assert ax.get_ylabel() == ylabel and "°C" in ax.get_xlabel()
    assert gids(ax, "law:") == ["law:TEM1", "law:TEM2", "law:average"]
    assert sum(isinstance(c, PolyCollection) for c in ax.collections) == 2  # the +-1 sd bands
    avg = [ln for ln in ax.get_lines() if ln.get_gid() == "law:average"][0]
    assert avg.get_linestyle() == "--"
    y25 = np.interp(25.0, avg.get_xdata(), avg.get_ydata())
    expected = 1.725 if which == "R" else 47.5  # S in mV/K
    assert y25 == pytest.approx(expected, rel=1e-6)
    assert len([c for c in ax.collections if c.get_gid() == "paper:TEM1"]) == 2  # hollow up and down markers
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    if which == "R":
        assert "TEM1: fitted law; up − down +0.0012 ± 0.0030 ohm" in labels
    else:  # no hysteresis estimate: nothing quoted
        assert "TEM1: fitted law" in labels
    no_paper = plot_law(results, which, average=None, paper=False).axes[0]
    assert gids(no_paper, "law:") == ["law:TEM1", "law:TEM2"]
    assert not [c for c in no_paper.collections if (c.get_gid() or "").startswith("paper:")]


def test_law_refuses_unknown_which():
    with pytest.raises(ValueError, match=r"which must be one of \['R', 'S'\]"):
        plot_law({"TEM1": fake_identification(0)}, "K")


# --- end to end on the pipeline (slow) --------------------------------------


@pytest.fixture(scope="module")
def identified(tmp_path_factory):
    from tembayes.bench import BenchConfig, simulate_batch
    from tembayes.identify.pipeline import identify_batch

    root = tmp_path_factory.mktemp("plots_identify")
    simulate_batch(
        root / "batch",
        BenchConfig(n_modules=2, hold=120, rate=2, n_validations=1, validation_duration=1200),
        progress=lambda m: None,
    )
    batch = load_batch(root / "batch")
    return batch, identify_batch(batch), root


@pytest.mark.slow
def test_law_on_pipeline_results(identified):
    from tembayes.identify.pipeline import batch_average

    batch, results, _ = identified
    for which in ("R", "S"):
        ax = plot_law(results, which, average=batch_average(results)).axes[0]
        assert gids(ax, "law:") == ["law:TEM1", "law:TEM2", "law:average"]
        assert sum(isinstance(c, PolyCollection) for c in ax.collections) == 2


@pytest.mark.slow
def test_save_identify_figures_writes_readable_pngs(identified):
    batch, results, root = identified
    out = root / "figs"
    paths = save_identify_figures(results, batch, out)
    expected = ["identification_run.png", "law_R.png", "law_S.png"]
    for mid in ("TEM1", "TEM2"):
        expected += [
            f"validation_{mid}_validation_constant.png",
            f"validation_{mid}_validation_linear.png",
            f"error_vs_tavg_{mid}_validation.png",
        ]
    assert [p.name for p in paths] == expected
    assert sorted(p.name for p in out.iterdir()) == sorted(expected)  # no temp files left behind
    for p in paths:
        assert p.stat().st_size > 10_000
        img = mpimg.imread(p)
        assert img.std() > MIN_PIXEL_STD, f"{p.name} looks blank"
    # dpi 120 on the 9 x 7.5 in identification figure
    assert mpimg.imread(out / "identification_run.png").shape[:2] == (900, 1080)
