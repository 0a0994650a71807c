"""The batched Rosenbrock simulator against scipy, sampling, batching and steady starts."""

from __future__ import annotations

import numpy as np
import pytest
from typical import PAPER, TA, TW  # noqa: E402

from tembayes.errors import ModelError
from tembayes.physics import Inputs, simulate
from tembayes.physics import kernel as K
from tembayes.physics.reference import simulate_reference
from tembayes.physics.rigread import rig_from_config

# Three draws around the typical module (a few % to ~20 % apart), with rig values.
DRAWS = {
    "R0_ohm": np.array([1.75, 1.60, 1.92]),
    "R1_ohm_per_K": np.array([0.0087, 0.0080, 0.0095]),
    "S0_V_per_K": np.array([0.048, 0.046, 0.050]),
    "S1_V_per_K2": np.array([1.0e-4, 0.8e-4, 1.2e-4]),
    "K_W_per_K": np.array([0.54, 0.50, 0.59]),
    "g_paste_cold": np.array([35.0, 25.0, 45.0]),
    "leak_bottom": np.array([0.04, 0.03, 0.055]),
}

EFFECTS_ON = {"thomson_fraction": 1.0, "K1_per_K": 0.004, "sensor_tau_s": 6.0}

# Targets: the fast simulator within 0.01 K and 1 mV of an
# accurate reference (observed ~1e-4 K and ~4e-5 V at the default atol 2e-4 K).
TOL_K = 0.01
TOL_V = 1e-3


def _experiment(hold, rate, seed=1):
    """0 A, +0.8 A, -1.2 A, +0.4 A holds; 1 mA current noise; water wobble, ambient drift."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, 4 * hold, 1.0 / rate)
    levels = np.select([t < hold, t < 2 * hold, t < 3 * hold], [0.0, 0.8, -1.2], 0.4)
    current = levels + rng.normal(0.0, 1e-3, t.size)
    tw = TW + 0.02 * np.sin(2 * np.pi * t / 300.0) + 0.01 * t / t[-1]
    ta = TA + 0.3 * t / t[-1]
    return Inputs(t, current, [tw, ta])


def _assert_close_to_reference(inp, params, rig=None):
    kw = {} if rig is None else {"rig": rig}
    fast = simulate(inp, params, **kw)
    ref = simulate_reference(inp, params, rtol=1e-10, atol=1e-10, **kw)
    dT = np.abs(fast.sensors - ref.sensors).max()
    dV = np.abs(fast.voltage - ref.voltage).max()
    assert dT <= TOL_K, f"max sensor difference {dT:.2e} K"
    assert dV <= TOL_V, f"max voltage difference {dV:.2e} V"
    # the experiment really moves the temperatures (tens of kelvin)
    assert np.ptp(fast.sensors[:, 2]) > 10.0


# ---------------------------------------------------------------- 8. vs scipy


def test_simulator_matches_scipy_reference_short():
    # 4 x 120 s at 2 Hz, one draw: ~2 s of solve_ivp
    _assert_close_to_reference(_experiment(120.0, 2.0), PAPER)


def test_simulator_matches_scipy_reference_legs_and_effects_short():
    _assert_close_to_reference(_experiment(120.0, 2.0), {**PAPER, **EFFECTS_ON}, rig=rig_from_config(None, leg_cells=2))


@pytest.mark.slow
def test_simulator_matches_scipy_reference_20_min():
    # 20 min at 5 Hz, three draws (~30 s of solve_ivp); the whole 4.2-hour identification
    # run is checked in analyses/bench_simulator.py (max 3.5e-5 K, 1.8e-5 V)
    _assert_close_to_reference(_experiment(300.0, 5.0), DRAWS)


@pytest.mark.slow
def test_simulator_matches_scipy_reference_20_min_legs_and_effects():
    # leg cells and every effect on: 20 min at 5 Hz, one draw
    params = {k: v[0] for k, v in DRAWS.items()}
    _assert_close_to_reference(
        _experiment(300.0, 5.0), {**params, **EFFECTS_ON}, rig=rig_from_config(None, leg_cells=2)
    )


# ---------------------------------------------------------------- 9. sampling


def test_extra_samples_do_not_change_the_solution():
    inp = _experiment(150.0, 1.0)
    rng = np.random.default_rng(4)
    # insert 1-3 extra samples at random points in a third of the intervals,
    # with the inputs interpolated linearly (the simulator's own input model),
    # so the ODE is the same and only the step sequence differs
    extra = []
    for k in rng.choice(len(inp.time) - 1, size=len(inp.time) // 3, replace=False):
        extra.extend(inp.time[k] + np.sort(rng.uniform(0.05, 0.95, rng.integers(1, 4))))
    t2 = np.union1d(inp.time, extra)
    fine = Inputs(t2, np.interp(t2, inp.time, inp.current), [np.interp(t2, inp.time, b) for b in inp.boundaries])
    a = simulate(inp, PAPER)
    b = simulate(fine, PAPER)
    shared = np.searchsorted(t2, inp.time)
    assert np.array_equal(t2[shared], inp.time)
    # two runs of a 2e-4 K local-error integrator: a few 1e-4 K globally
    assert np.abs(a.sensors - b.sensors[:, :, shared]).max() <= 0.005
    assert np.abs(a.voltage - b.voltage[:, shared]).max() <= 0.5e-3


def test_uneven_sampling_matches_regular_sampling():
    # a jittered DAQ clock (+-0.2 s at 1 Hz) and a regular one see the same
    # piecewise-constant current; compare at the regular times by interpolation
    hold = 150.0
    t_reg = np.arange(0.0, 4 * hold, 0.25)
    rng = np.random.default_rng(9)
    t_jit = np.arange(0.0, 4 * hold, 1.0)
    t_jit[1:-1] += rng.uniform(-0.2, 0.2, t_jit.size - 2)
    steps = np.array([hold, 2 * hold, 3 * hold])

    def inputs(t):
        # current steps resolved by a 1 ms ramp, as the bench does
        t = np.union1d(t, np.concatenate([steps - 1e-3, steps]))
        level = np.array([0.0, 0.8, -1.2, 0.4])[np.searchsorted(steps, t, side="right")]
        return Inputs(t, level, [np.full_like(t, TW), np.full_like(t, TA)])

    a, b = simulate(inputs(t_reg), PAPER), simulate(inputs(t_jit), PAPER)
    # compare in the last 80 % of each hold, where the signals are smooth on
    # the 1 s scale so that linear interpolation of the jittered run is exact
    # to ~1 mK; the tolerance is the target's 0.01 K
    sel = np.zeros(a.time.size, bool)
    for k in range(4):
        sel |= (a.time > k * hold + 0.2 * hold) & (a.time < (k + 1) * hold - 1.0)
    for ch in range(4):
        interp = np.interp(a.time[sel], b.time, b.sensors[0, ch])
        assert np.abs(interp - a.sensors[0, ch, sel]).max() <= 0.01


def test_inputs_validation():
    t = np.arange(5.0)
    with pytest.raises(ModelError, match="strictly increasing"):
        Inputs(np.array([0.0, 1.0, 1.0, 2.0, 3.0]), np.zeros(5), [np.full(5, TW), np.full(5, TA)])
    with pytest.raises(ModelError, match="current"):
        Inputs(t, np.zeros(4), [np.full(5, TW), np.full(5, TA)])
    with pytest.raises(TypeError, match="Inputs"):
        simulate((t, np.zeros(5), np.full(5, TW), np.full(5, TA)), PAPER)


# ---------------------------------------------------------------- 10. batches


def test_batch_equals_single_draws():
    inp = _experiment(90.0, 2.0)
    rng = np.random.default_rng(5)
    nd = 5
    params = {k: v * rng.uniform(0.9, 1.1, nd) for k, v in PAPER.items()}
    params["g_cooler"] = rng.uniform(10.0, 15.0, nd)
    params["c_plate_cold"] = rng.uniform(4.0, 5.0, nd)
    params["K1_per_K"] = rng.uniform(0.0, 0.005, nd)
    params["sensor_tau_s"] = np.array([0.0, 3.0, 0.0, 6.0, 1.0])
    together = simulate(inp, params)
    assert together.sensors.shape == (nd, 4, inp.time.size)
    for d in range(nd):
        alone = simulate(inp, {k: v[d] for k, v in params.items()})
        # draws are integrated independently with the same step control
        for f in ("sensors", "voltage", "t_hot", "t_cold"):
            np.testing.assert_allclose(getattr(together, f)[d], getattr(alone, f)[0], rtol=0, atol=1e-12)
    # the draws really differ from each other
    assert np.ptp(together.sensors[:, 2, -1]) > 0.1


# ---------------------------------------------------------------- 11. steady start


@pytest.mark.parametrize("current", [0.0, 0.5, -1.0])
def test_steady_start_stays_put(current):
    t = np.arange(0.0, 1200.0, 2.0)
    inp = Inputs(t, np.full(t.size, current), [np.full(t.size, TW), np.full(t.size, TA)])
    sim = simulate(inp, {**PAPER, "sensor_tau_s": 5.0})
    # Newton converges to 1e-11 K; the integrator then only sees a zero
    # derivative up to rounding, so no drift beyond 1e-9 K over 20 minutes
    drift = np.abs(sim.sensors - sim.sensors[:, :, :1]).max()
    assert drift <= 1e-9
    assert np.abs(sim.voltage - sim.voltage[:, :1]).max() <= 1e-9
    # ... and it did not start at the water temperature (y0) for I != 0
    if current:
        assert np.abs(sim.sensors[0, 2, 0] - TW) > 1.0


def test_without_steady_start_the_rig_relaxes():
    t = np.arange(0.0, 1200.0, 2.0)
    inp = Inputs(t, np.zeros(t.size), [np.full(t.size, TW), np.full(t.size, TA)])
    sim = simulate(inp, PAPER, steady_start=False, y0=np.full(6, 300.0))
    T3 = sim.sensors[0, 2]
    assert T3[0] == 300.0
    # cools towards the ~293.3 K steady state, monotonically (a 6-node passive network)
    assert np.all(np.diff(T3) < 0) and T3[-1] < 296.0


def test_kernel_gets_one_array_type_even_from_read_only_inputs():
    """Experiment columns are read-only, and a read-only array is another numba type: a
    second compiled version of the parallel integrator, loaded back from the on-disk cache,
    crashed the process (segfault).  The entry points copy such arrays, so every compiled
    version of the integrators takes writable C arrays only."""
    from numba.core import types

    inp = _experiment(60.0, 1.0)
    for a in (inp.time, inp.current, inp.boundaries):
        a.flags.writeable = False
    simulate(inp, PAPER)
    simulate(Inputs(inp.time[::2], inp.current[::2], inp.boundaries[:, ::2]), PAPER)  # strided views
    for fn in (K._integrate, K._integrate_grids):
        for sig in fn.signatures:
            arrays = [a for a in sig if isinstance(a, types.Array)]
            if fn is K._integrate_grids and any(a.layout != "C" for a in arrays):
                continue  # _integrate's own call with broadcast views: one fixed internal type
            assert all(a.mutable and a.layout == "C" for a in arrays), sig
