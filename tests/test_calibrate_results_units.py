"""posterior.nc is arviz-native: a ``units`` attribute on every variable, a
``prior`` group shaped like the posterior (tembayes.calibrate.results).

The runs are the hand-built ones of test_plots_calibrate (no sampling), written
with both writers: :func:`results.to_inference_data` (in memory) and
:func:`results.write_run_posterior` (streamed from the per-module files, what
``tembayes calibrate`` writes).
"""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")

import arviz as az  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from test_plots_calibrate import TRUTH, make_module, make_population  # noqa: E402

from tembayes.calibrate import results  # noqa: E402
from tembayes.calibrate.likelihood import NOISE_PARAMETERS  # noqa: E402
from tembayes.calibrate.model import SHIFT  # noqa: E402
from tembayes.calibrate.modelform import FORMS  # noqa: E402
from tembayes.calibrate.module import parameter_space  # noqa: E402
from tembayes.calibrate.population import HYPER_NAMES  # noqa: E402
from tembayes.calibrate.run import load_run  # noqa: E402
from tembayes.calibrate.stepdata import CHANNELS  # noqa: E402
from tembayes.constants import MODULE_PARAMETERS  # noqa: E402
from tembayes.data import write_json  # noqa: E402
from tembayes.physics.effects import CATALOGUE  # noqa: E402
from tembayes.physics.rigread import rig_from_config  # noqa: E402


def assert_units_everywhere(idata):
    """Every data variable of every group has a non-empty ``units``; raise naming those that lack one."""
    missing = [
        f"{g}/{v}" for g in idata.groups() for v, da in getattr(idata, g).data_vars.items() if not da.attrs.get("units")
    ]
    assert not missing, f"variables without units: {missing}"


@pytest.mark.parametrize(
    "name, unit",
    [
        ("R0_ohm", "ohm"),
        ("R1_ohm_per_K", "ohm/K"),
        ("S0_V_per_K", "V/K"),
        ("S1_V_per_K2", "V/K^2"),
        ("K_W_per_K", "W/K"),
        ("step_shift_s", "s"),
        ("offset_sd_dT_K", "K"),
        ("offset_sd_voltage_V", "V"),
        ("noise_scale_voltage", "1"),
        ("g_cooler", "W/K"),
        ("c_legs", "J/K"),
        ("tab_share", "1"),
        ("g_ceramic", "W/K"),
        ("depth_T1", "m"),
        ("K1_per_K", "1/K"),
        ("sensor_tau_s", "s"),
        ("thomson_fraction", "1"),
        ("R2_rel_per_K2", "1/K^2"),
        ("contact_R_cold_K_per_W", "K/W"),
        ("current_offset_A", "A"),
        ("hyper_mu_S1_V_per_K2", "V/K^2"),
        ("hyper_tau_R0_rel", "1"),
        ("hyper_tau_R1_ohm_per_K", "ohm/K"),
        ("hyper_outlier_fraction", "1"),
        ("voltage_V", "V"),
        ("Tmean_K", "K"),
        ("obs_time_s", "s"),
        ("obs_step", "1"),
        ("step_dI_A", "A"),
        ("step_direction", "1"),
        ("step_Tavg_C", "degC"),
        ("step_response", "nat"),
        ("lp", "nat"),
        ("noise_sd", "per channel: V, K, K"),
        ("mystery", None),
        ("legs", None),
        ("x_per_legs", None),
    ],
)
def test_variable_unit(name, unit):
    assert results.variable_unit(name) == unit


def test_every_sampled_parameter_of_every_model_has_a_unit():
    """The names parameter_space gives for each model form with every catalogue effect, and the population's."""
    ds = SimpleNamespace(resistance=lambda: 1.7, seebeck=lambda: 0.05, conductance=lambda: 0.5)
    data = SimpleNamespace(noise=np.array([1e-4, 1e-3, 1e-3]))
    names = set()
    for form in FORMS.values():
        effects = [e for e in CATALOGUE if e not in form.includes]
        _, space = parameter_space(rig_from_config(None, layers=form.layers), ds, data, 5.0, effects, form.name)
        names |= {p.name for p in space.priors}
    assert set(MODULE_PARAMETERS) | {SHIFT} | set(NOISE_PARAMETERS) <= names
    names |= {f"hyper_{k}" for k in HYPER_NAMES} | set(CHANNELS)
    assert {n: results.variable_unit(n) for n in names if results.variable_unit(n) is None} == {}


def _modules():
    rng = np.random.default_rng(7)
    mods = [make_module("TEM1", rng), make_module("TEM2", rng, n_steps=4, offset=0.03)]
    pop = make_population(mods, {"TEM1": 0.05, "TEM2": 0.6}, rng)
    prior = {k: TRUTH[k] * np.exp(0.3 * rng.standard_normal(300)) for k in MODULE_PARAMETERS}
    return mods, pop, prior


def _read(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return az.from_netcdf(path, engine="h5netcdf")


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """posterior.nc of two modules with a population and the prior, from both writers."""
    tmp = tmp_path_factory.mktemp("units")
    mods, pop, prior = _modules()
    memory = results.write_netcdf(
        results.to_inference_data(mods, population=pop, prior_draws=prior), tmp / "memory" / "posterior.nc"
    )
    files = [results.write_netcdf(results.to_inference_data([m]), tmp / "modules" / f"{m.module_id}.nc") for m in mods]
    streamed = results.write_run_posterior(tmp / "streamed" / "posterior.nc", files, population=pop, prior_draws=prior)
    write_json(tmp / "streamed" / "summary.json", results.summary(mods, pop))
    return {"memory": memory, "streamed": streamed, "prior": prior, "files": files}


@pytest.mark.parametrize("writer", ["memory", "streamed"])
def test_every_variable_of_posterior_nc_has_units(written, writer):
    idata = _read(written[writer])
    assert {
        "posterior",
        "prior",
        "population",
        "sample_stats",
        "log_likelihood",
        "observed_data",
        "constant_data",
    } <= set(idata.groups())
    assert_units_everywhere(idata)
    assert idata.posterior["R1_ohm_per_K"].attrs["units"] == "ohm/K"
    assert idata.log_likelihood["step_response"].attrs["units"] == "nat"
    # "s" is not a CF time unit: the times stay float seconds
    assert idata.constant_data["obs_time_s"].dtype == np.float64
    assert idata.posterior["step_shift_s"].dtype == np.float64


def test_module_files_have_units(written):
    for f in written["files"]:
        assert_units_everywhere(_read(f))


@pytest.mark.parametrize("writer", ["memory", "streamed"])
def test_prior_group_is_shaped_like_the_posterior(written, writer):
    idata = _read(written[writer])
    for k in MODULE_PARAMETERS:
        assert idata.prior[k].dims == idata.posterior[k].dims == ("chain", "draw", "module")
        assert list(idata.prior["module"].values) == list(idata.posterior["module"].values)
        for mid in ("TEM1", "TEM2"):  # the shared datasheet prior, numbers unchanged
            np.testing.assert_array_equal(idata.prior[k].sel(module=mid).values[0], written["prior"][k])
    axes = az.plot_dist_comparison(idata, var_names=["R0_ohm"])
    assert np.size(axes) > 0
    plt.close("all")


def test_streamed_prior_and_units_equal_the_in_memory_ones(written):
    a, b = _read(written["memory"]), _read(written["streamed"])
    for g in ("prior", "posterior", "constant_data", "population"):
        ga, gb = getattr(a, g), getattr(b, g)
        for v in ga.data_vars:
            assert ga[v].attrs.get("units") == gb[v].attrs.get("units"), f"{g}/{v}"
    for k in MODULE_PARAMETERS:
        np.testing.assert_array_equal(a.prior[k].values, b.prior[k].values)


def test_run_prior_draws_per_module(written):
    run = load_run(written["streamed"].parent)
    d = run.prior_draws(("R0_ohm", "K_W_per_K"))
    assert d.shape == (300, 2)
    np.testing.assert_array_equal(d[:, 0], written["prior"]["R0_ohm"])
    np.testing.assert_array_equal(run.prior_draws(("R0_ohm",), "TEM2")[:, 0], written["prior"]["R0_ohm"])


def test_a_rig_files_own_parameters_carry_its_units(tmp_path):
    """A rig file's parameters that no shipped table knows (``g_sink``, ``lead_share``) get the units
    the rig file gives them, in the module files, both writers' posterior.nc and a module read back."""
    import dataclasses

    from tembayes.physics.rigread import shipped_rig

    rig = shipped_rig("heatsink-al").build(layers=True)
    extra = ("g_sink", "lead_share")
    assert all(results.variable_unit(k) is None for k in extra)  # unknown without the run's rig
    rng = np.random.default_rng(2)
    mods = []
    for mid in ("TEM1", "TEM2"):
        m = make_module(mid, rng)
        shape = m.draws["R0_ohm"].shape
        draws = {**m.draws, **{k: rig.parameter(k).nominal * np.ones(shape) for k in extra}}
        units = {k: rig.parameter(k).unit for k in extra}
        mods.append(dataclasses.replace(m, names=m.names + extra, draws=draws, units=units))
    files = [results.write_netcdf(results.to_inference_data([m]), tmp_path / "m" / f"{m.module_id}.nc") for m in mods]
    memory = results.write_netcdf(results.to_inference_data(mods), tmp_path / "memory.nc")
    streamed = results.write_run_posterior(tmp_path / "streamed.nc", files)
    for path in (*files, memory, streamed):
        post = _read(path).posterior
        assert (post["g_sink"].attrs["units"], post["lead_share"].attrs["units"]) == ("W/K", "1"), path
        assert post["R0_ohm"].attrs["units"] == "ohm"
    assert results.read_module(files[0]).units == {"g_sink": "W/K", "lead_share": "1"}
