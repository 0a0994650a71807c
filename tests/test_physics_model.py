"""The physics of the model: the module element (paper eqs 4-5, 9), the rig network
and the effect catalogue, checked against hand-computable oracles.

Single-draw kernel helpers (``steady_one``, ``rhs_one``, ``jac_one``,
``tem_heat``, ``tem_voltage``) are used wherever the oracle is an algebraic
identity, so that these tests do not depend on the integrator.
"""

from __future__ import annotations

import numpy as np
import pytest
from typical import PAPER, TA, TW  # noqa: E402

from tembayes.bench.hifi import hifi_rig
from tembayes.bench.outside import outside_rig
from tembayes.constants import MODULE_PARAMETERS, T_REF
from tembayes.errors import ModelError
from tembayes.physics import CATALOGUE, REFERENCE, Inputs, RigDescription, RigParameter, rig_from_config, simulate
from tembayes.physics import effects as effects_mod
from tembayes.physics import kernel as K
from tembayes.physics.rigread import SHIPPED
from tembayes.physics.simulate import build, check_params, tem_vectors


def _steady(params, current, rig=REFERENCE, tw=TW, ta=TA):
    """Steady state of one draw at constant inputs; returns (y, kernel arrays)."""
    m = build(params, rig)
    n = len(m["network"].nodes)
    y, ok = K.steady_one(
        np.full(n, tw), float(current), np.array([tw, ta]), m["A"][0], m["Bb"][0], m["Cinv"][0], m["tem"], m["P"][0]
    )
    assert ok, "steady_one did not converge"
    return y, m


def _pvec(params):
    arrs, nd = check_params(params)
    return tem_vectors(arrs, nd)[0]


def _heat(T, current, p):
    T = np.ascontiguousarray(T, dtype=float)
    Q = np.empty_like(T)
    K.tem_heat(T, float(current), p, Q)
    return Q


# ---------------------------------------------------------------- 1. energy balance

ENERGY_CASES = {
    "paper": ({}, 0),
    "thomson": ({"thomson_fraction": 1.0}, 0),
    "legs3": ({}, 3),
    "legs3+thomson": ({"thomson_fraction": 1.0}, 3),
    "joule_split": ({"joule_hot_excess": 0.1}, 0),
    "legs3+joule_split": ({"joule_hot_excess": 0.1}, 3),
    "legs3+joule_split_cold+thomson": ({"joule_hot_excess": -0.1, "thomson_fraction": 1.0}, 3),
    "k_temperature": ({"K1_per_K": 0.004}, 0),
    "quadratic_laws": ({"R2_rel_per_K2": 4e-5, "S2_rel_per_K2": -6e-5}, 0),
    "legs3+quadratic_laws": ({"R2_rel_per_K2": 4e-5, "S2_rel_per_K2": -6e-5}, 3),
}


@pytest.mark.parametrize("current", [0.6, -1.2])
@pytest.mark.parametrize("case", list(ENERGY_CASES))
def test_steady_state_energy_balance(case, current):
    # At steady state the electrical power V*I must leave through the two
    # boundaries (water and ambient); nothing else stores or creates energy.
    extra, legs = ENERGY_CASES[case]
    rig = rig_from_config(None, leg_cells=legs)
    y, m = _steady({**PAPER, **extra}, current, rig)
    p = m["P"][0]
    volt = K.tem_voltage(np.ascontiguousarray(y[m["tem"]]), current, p)
    power = volt * current
    Gb = m["network"].Gb[0]
    out = np.sum(Gb[:, 0] * (y - TW) + Gb[:, 1] * (y - TA))
    assert power > 0.5  # a real load: the check is not 0 == 0
    # Newton stops at |step| < 1e-11 K and the flows are sums of G (<= 12 W/K)
    # times differences of ~300 K numbers (rounding ~6e-14 K): the residual is
    # ~1e-12 W against >= 0.9 W, so 1e-9 relative leaves three decades of margin.
    assert out == pytest.approx(power, rel=1e-9)


@pytest.mark.parametrize("case", [c for c in ENERGY_CASES if "quadratic" not in c])
def test_module_heat_equals_electrical_power_everywhere(case):
    # Pointwise first law of the element (not only at steady state): the heat
    # it releases into its nodes sums to V*I for any temperatures and current.
    extra, legs = ENERGY_CASES[case]
    p = _pvec({**PAPER, **extra})
    rng = np.random.default_rng(3)
    for _ in range(20):
        T = np.sort(rng.uniform(275.0, 355.0, legs + 2))[:: rng.choice([-1, 1])]
        current = rng.uniform(-1.6, 0.9)
        Q = _heat(T, current, p)
        vi = K.tem_voltage(np.ascontiguousarray(T), current, p) * current
        # terms of up to ~30 W cancel down to ~1 W: allow 1e-12 W absolute
        assert Q.sum() == pytest.approx(vi, rel=1e-10, abs=1e-12)


def test_energy_balance_thomson_with_quadratic_seebeck():
    # Same first law as above, with the thomson and quadratic_laws effects
    # together (both in the catalogue, so a bench run may use both).
    params = {**PAPER, "thomson_fraction": 1.0, "S2_rel_per_K2": -6e-5}
    y, m = _steady(params, -1.6)
    volt = K.tem_voltage(np.ascontiguousarray(y[m["tem"]]), -1.6, m["P"][0])
    Gb = m["network"].Gb[0]
    out = np.sum(Gb[:, 0] * (y - TW) + Gb[:, 1] * (y - TA))
    assert out == pytest.approx(volt * -1.6, rel=1e-9)


# ------------------------------------------------------ 2. I = 0: pure conduction


def _leg_steady(n, current, p, th, tc):
    """The leg cells' steady temperatures [K] between junctions held at ``th`` and ``tc`` (Newton on tem_heat)."""
    cells = np.linspace(th, tc, n + 2)[1:-1]
    for _ in range(30):
        T = np.concatenate([[th], cells, [tc]])
        f = _heat(T, current, p)[1:-1]
        J = np.empty((n, n))
        for j in range(n):
            Tz = T.astype(complex)
            Tz[j + 1] += 1e-20j
            Q = np.empty(n + 2, dtype=complex)
            K.tem_heat(Tz, complex(current), p, Q)
            J[:, j] = Q[1:-1].imag / 1e-20
        step = np.linalg.solve(J, -f)
        cells = cells + step
        if np.max(np.abs(step)) < 1e-12:
            return np.concatenate([[th], cells, [tc]])
    raise AssertionError("no steady state")


@pytest.mark.parametrize("n", [1, 2, 3, 4, 8])
def test_leg_cells_resist_at_the_continuous_legs_mean_excess(n):
    # Joule heat q = R0 I^2 alone (no Seebeck, R and K constant) in a leg
    # between junctions at 310 K and 300 K: the continuum's excess over the
    # straight line is q x (1 - x) / (2 K), mean q / (12 K).  The cells of
    # tem_heat run (1 + 2/n^2) times that; the temperatures they resist at
    # carry the continuum's mean exactly.  ~300 K values against a 0.5 K
    # excess: rounding ~1e-13 K, so 1e-10 relative leaves three decades.
    p = _pvec(PAPER)
    p[[K.P_R1, K.P_S0, K.P_S1]] = 0.0
    current = 1.3
    q, k, th, tc = PAPER["R0_ohm"] * current**2, PAPER["K_W_per_K"], 310.0, 300.0
    T = _leg_steady(n, current, p, th, tc)
    line = th + (tc - th) * (np.arange(1, n + 1) - 0.5) / n
    assert np.mean(T[1:-1] - line) == pytest.approx((1.0 + 2.0 / n**2) * q / (12.0 * k), rel=1e-10)
    resist = np.array([K._resistance_t(T, i, p) for i in range(1, n + 1)])
    assert np.mean(resist - line) == pytest.approx(q / (12.0 * k), rel=1e-10)


def test_a_leg_curved_by_k_of_t_alone_resists_at_its_cells():
    # At zero current a temperature-dependent K bends the leg's profile, and
    # the cells are exact there (their conduction is linear in the Kirchhoff
    # variable): the temperatures they resist at are their own.  The 40 K
    # span and K1 = 0.005/K bend it by ~1 K, which a scaling of the plain
    # departure would move by ~0.1 K.
    p = _pvec({**PAPER, "K1_per_K": 0.005})
    T = _leg_steady(4, 0.0, p, 320.0, 280.0)
    line = 320.0 - 40.0 * (np.arange(1, 5) - 0.5) / 4
    assert np.max(np.abs(T[1:-1] - line)) > 0.5
    resist = np.array([K._resistance_t(T, i, p) for i in range(1, 5)])
    assert resist == pytest.approx(T[1:-1], abs=1e-9)


@pytest.mark.parametrize("current, tol", [(1.6, 3e-4), (6.0, 2e-2)])
def test_four_leg_cells_give_the_converged_legs_voltage(current, tol):
    # The reference rig's steady voltage with the legs in 4 cells against 32:
    # read at the cells' own temperatures 0.89 mV apart at 1.6 A and 76 mV
    # at 6 A (a noise sd is 1 mV); read at the continuum's excess 0.15 mV
    # and 9.7 mV (what is left is the Thomson heat's own non-uniformity).
    volts = []
    for legs in (4, 32):
        rig = rig_from_config(None, leg_cells=legs, layers=True, physics={"thomson_fraction": 1.0})
        y, m = _steady(PAPER, current, rig)
        volts.append(K.tem_voltage(np.ascontiguousarray(y[m["tem"]]), current, m["P"][0]))
    assert abs(volts[0] - volts[1]) < tol


@pytest.mark.parametrize("legs", [0, 3])
def test_zero_current_is_linear_conduction(legs):
    rig = rig_from_config(None, leg_cells=legs)
    ta = 340.0  # a hot room, so the conduction problem has a clear gradient
    y, m = _steady(PAPER, 0.0, rig, ta=ta)
    net = m["network"]
    G, Gb = net.G[0], net.Gb[0]
    L = np.diag(G.sum(axis=1) + Gb.sum(axis=1)) - G
    # the module's conduction: a chain of conductances whose series sum is K
    # (end half-cells 2 n K, inner cells n K; a single K when lumped)
    tem = m["tem"]
    n = len(tem) - 1
    w = np.full(n, float(legs)) if legs else np.ones(1)
    if legs:
        w[0] = w[-1] = 2.0 * legs
    assert np.sum(1.0 / (w * PAPER["K_W_per_K"])) == pytest.approx(1.0 / PAPER["K_W_per_K"], rel=1e-14)
    for j in range(n):
        a, b, g = tem[j], tem[j + 1], w[j] * PAPER["K_W_per_K"]
        L[a, a] += g
        L[b, b] += g
        L[a, b] -= g
        L[b, a] -= g
    expected = np.linalg.solve(L, Gb[:, 0] * TW + Gb[:, 1] * ta)
    # a linear problem solved two ways: agreement to rounding (1e-9 K)
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-9)
    # a temperature difference really exists, so the test distinguishes
    # conduction from "everything at one temperature"
    assert np.ptp(y) > 2.0


@pytest.mark.parametrize("extra", [{}, {"thomson_fraction": 1.0, "joule_hot_excess": 0.1}])
def test_tem_heat_at_zero_current_is_fourier_exactly(extra):
    p = _pvec({**PAPER, **extra})
    Th, Tc = 310.37, 287.91
    Q = _heat([Th, Tc], 0.0, p)
    k = PAPER["K_W_per_K"]
    assert Q[0] == k * (Tc - Th)
    assert Q[1] == k * (Th - Tc)


# ------------------------------------------------------ 3. paper eqs 4, 5 and 9


@pytest.mark.parametrize("Th, Tc, current", [(305.3, 281.7, 0.73), (297.2, 342.6, -1.41), (300.0, 300.0, 0.2)])
def test_tem_heat_and_voltage_by_hand(Th, Tc, current):
    p = _pvec(PAPER)
    x = 0.5 * (Th + Tc) - T_REF
    R = PAPER["R0_ohm"] + PAPER["R1_ohm_per_K"] * x
    S = PAPER["S0_V_per_K"] + PAPER["S1_V_per_K2"] * x
    k = PAPER["K_W_per_K"]
    Q = _heat([Th, Tc], current, p)
    # eq 4 (cold) and eq 5 (hot); a few rounding errors on ~20 W terms
    assert Q[1] == pytest.approx(k * (Th - Tc) + 0.5 * R * current**2 - S * Tc * current, rel=1e-12, abs=1e-12)
    assert Q[0] == pytest.approx(k * (Tc - Th) + 0.5 * R * current**2 + S * Th * current, rel=1e-12, abs=1e-12)
    # eq 9
    V = K.tem_voltage(np.array([Th, Tc]), current, p)
    assert V == pytest.approx(R * current + S * (Th - Tc), rel=1e-12, abs=1e-15)


def test_tem_heat_with_joule_split_and_thomson_by_hand():
    # Extensions of eqs 4-5 as the catalogue defines them: a fraction 0.5 + delta
    # of the Joule heat at the hot side; with thomson, each junction's own S and
    # the Thomson heat -T_mean S'(T_mean) I dT shared equally by the two plates.
    Th, Tc, current, delta = 318.4, 284.9, 1.1, 0.1
    p = _pvec({**PAPER, "joule_hot_excess": delta, "thomson_fraction": 1.0})
    Tm = 0.5 * (Th + Tc)
    R = PAPER["R0_ohm"] + PAPER["R1_ohm_per_K"] * (Tm - T_REF)
    S_of = lambda T: PAPER["S0_V_per_K"] + PAPER["S1_V_per_K2"] * (T - T_REF)  # noqa: E731
    k = PAPER["K_W_per_K"]
    thomson = -Tm * PAPER["S1_V_per_K2"] * current * (Th - Tc)
    Q = _heat([Th, Tc], current, p)
    assert Q[0] == pytest.approx(
        k * (Tc - Th) + (0.5 + delta) * R * current**2 + S_of(Th) * Th * current + 0.5 * thomson, rel=1e-12
    )
    assert Q[1] == pytest.approx(
        k * (Th - Tc) + (0.5 - delta) * R * current**2 - S_of(Tc) * Tc * current + 0.5 * thomson, rel=1e-12
    )


def _insulated_cold_rig():
    # water -> hot plate through a huge conductance; the cold plate touches only
    # the module and a small block with no leak anywhere
    return RigDescription(
        name="insulated-cold",
        parameters=(RigParameter("g_sink", 1e4, 1e3, 1e5, "W/K"),),
        nodes=(("hot", 4.5), ("cold", 4.5), ("block", 0.05)),
        links=(("water", "hot", "g_sink"), ("cold", "block", 50.0)),
        hot="hot",
        cold="cold",
        boundaries=REFERENCE.boundaries,
    )


@pytest.mark.parametrize("current", [0.3, 0.8, 2.0])
def test_insulated_cold_side_steady_state(current):
    # With no path for heat into the cold side but the module, Q_c = 0:
    # K (Th - Tc) = S Tc I - 0.5 R I^2, with R, S at the mean plate temperature.
    rig = _insulated_cold_rig()
    y, m = _steady(PAPER, current, rig)
    names = m["network"].nodes
    Th, Tc, Tb = (y[names.index(n)] for n in ("hot", "cold", "block"))
    x = 0.5 * (Th + Tc) - T_REF
    R = PAPER["R0_ohm"] + PAPER["R1_ohm_per_K"] * x
    S = PAPER["S0_V_per_K"] + PAPER["S1_V_per_K2"] * x
    lhs = PAPER["K_W_per_K"] * (Th - Tc)
    rhs = S * Tc * current - 0.5 * R * current**2
    assert Th - Tc > 5.0  # a real temperature difference
    # both sides are ~10 W; the Newton tolerance (1e-11 K) times K, S I is ~1e-11 W
    assert lhs == pytest.approx(rhs, rel=1e-9)
    assert Tb == pytest.approx(Tc, abs=1e-9)  # no flow through the block's link
    # the hot plate sits at the water, up to (heat it rejects) / g_sink
    assert Th - TW == pytest.approx((S * Th * current + 0.5 * R * current**2 - lhs) / 1e4, rel=1e-6)


# ------------------------------------------------------ 4. sign conventions


def test_positive_current_cools_the_bottom_block():
    names = REFERENCE.node_names
    bottom = [names.index(REFERENCE.sensors[c]) for c in ("T3_C", "T4_C")]
    y0, _ = _steady(PAPER, 0.0)
    ycool, _ = _steady(PAPER, 0.6)
    yheat, _ = _steady(PAPER, -1.2)
    # several kelvin either way (the steady swings are ~10-40 K)
    assert np.all(ycool[bottom] < y0[bottom] - 5.0)
    assert np.all(yheat[bottom] > y0[bottom] + 5.0)
    # the cold plate is below the hot plate when cooling, above when heating
    h, c = names.index(REFERENCE.hot), names.index(REFERENCE.cold)
    assert ycool[c] < ycool[h] and yheat[c] > yheat[h]


@pytest.mark.parametrize("current", [0.3, 0.8, -0.5, -1.6])
def test_steady_voltage_has_the_sign_of_the_current(current):
    y, m = _steady(PAPER, current)
    V = K.tem_voltage(np.ascontiguousarray(y[m["tem"]]), current, m["P"][0])
    # R I and the back-EMF S dT add up with the sign of I
    assert np.sign(V) == np.sign(current)
    assert abs(V) > abs(PAPER["R0_ohm"] * current) * 0.9
    # and simulate reports the same at a steady start
    t = np.arange(0.0, 10.0, 1.0)
    sim = simulate(Inputs(t, np.full(10, current), [np.full(10, TW), np.full(10, TA)]), PAPER)
    assert sim.voltage[0, 0] == pytest.approx(V, abs=1e-9)


@pytest.mark.parametrize("step", [0.8, -1.2])
def test_larger_resistance_raises_voltage_at_the_jump(step):
    t = np.arange(0.0, 60.0, 0.2)
    current = np.where(t >= 30.0, step, 0.0)
    inp = Inputs(t, current, [np.full_like(t, TW), np.full_like(t, TA)])
    k = int(np.searchsorted(t, 30.0))
    v_lo = simulate(inp, PAPER).voltage[0, k]
    v_hi = simulate(inp, {**PAPER, "R0_ohm": 2.0}).voltage[0, k]
    # at the first sample at the new level the back-EMF has barely moved in
    # either run, so the difference is dR * I to within a few percent
    assert (v_hi - v_lo) * np.sign(step) > 0
    assert v_hi - v_lo == pytest.approx(0.25 * step, rel=0.05)


# ------------------------------------------------------ 5. Jacobian


@pytest.mark.parametrize("legs", [0, 3])
@pytest.mark.parametrize("current", [0.7, -1.3])
def test_jacobian_matches_finite_differences(legs, current):
    params = {
        **PAPER,
        "thomson_fraction": 1.0,
        "K1_per_K": 0.004,
        "R2_rel_per_K2": 4e-5,
        "S2_rel_per_K2": -6e-5,
        "joule_hot_excess": 0.05,
    }
    m = build(params, rig_from_config(None, leg_cells=legs))
    A, Bb, Cinv, tem, p = m["A"][0], m["Bb"][0], m["Cinv"][0], m["tem"], m["P"][0]
    rng = np.random.default_rng(11)
    y = rng.uniform(280.0, 340.0, A.shape[0])
    J = K.jac_one(y, current, A, Cinv, tem, p)
    # h = 1e-3 K: truncation (h^2 f'''/6) and rounding (~1e-16 |A y| / h) are
    # both below 1e-10 relative (observed 5e-11), so 1e-8 -- stricter than the
    # usual 1e-6 -- keeps a factor 200 of margin and catches a Jacobian off by
    # 1e-6 relative (which a 1e-6 tolerance would not)
    h = 1e-3
    Jfd = np.empty_like(J)
    for j in range(len(y)):
        e = np.zeros_like(y)
        e[j] = h
        Jfd[:, j] = (
            K.rhs_one(y + e, current, np.array([TW, TA]), A, Bb, Cinv, tem, p)
            - K.rhs_one(y - e, current, np.array([TW, TA]), A, Bb, Cinv, tem, p)
        ) / (2 * h)
    scale = np.abs(J).max()
    np.testing.assert_allclose(J, Jfd, rtol=1e-8, atol=1e-8 * scale)
    # the module block is genuinely nonlinear (not just the network's A)
    assert np.abs(J - A).max() > 1e-3 * scale


# ------------------------------------------------------ 6. effects at zero


def _short_inputs():
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 180.0, 0.5)
    current = np.select([t < 60, t < 120], [0.0, 0.8], -1.2) + rng.normal(0, 1e-3, t.size)
    tw = TW + 0.02 * np.sin(2 * np.pi * t / 300.0)
    ta = TA + 0.1 * t / 180.0
    return Inputs(t, current, [tw, ta])


@pytest.fixture(scope="module")
def short_base():
    inp = _short_inputs()
    return inp, simulate(inp, PAPER)


def _same(a, b):
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("sensors", "voltage", "t_hot", "t_cold"))


@pytest.mark.parametrize("name", list(CATALOGUE))
def test_each_effect_at_zero_is_the_paper_model(name, short_base):
    inp, base = short_base
    zeros = {p: 0.0 for p in CATALOGUE[name].parameter_names}
    # exact: a zero coefficient is the same floating-point computation
    assert _same(simulate(inp, {**PAPER, **zeros}), base)
    # and at its bench default the effect does act (the zero test is not vacuous)
    assert not _same(simulate(inp, {**PAPER, **CATALOGUE[name].defaults()}), base)


def test_quadratic_and_k_temperature_laws_by_hand():
    # quadratic_laws: R = R0 (1 + R2 x^2) + R1 x and S = S0 (1 + S2 x^2) + S1 x
    # (R2, S2 relative); k_temperature: K (1 + K1 x); x = T_mean - 25 degC
    r2, s2, k1 = 4e-5, -6e-5, 0.004
    p = _pvec({**PAPER, "R2_rel_per_K2": r2, "S2_rel_per_K2": s2, "K1_per_K": k1})
    Th, Tc, current = 301.4, 349.8, -1.3
    x = 0.5 * (Th + Tc) - T_REF
    R = PAPER["R0_ohm"] * (1 + r2 * x**2) + PAPER["R1_ohm_per_K"] * x
    S = PAPER["S0_V_per_K"] * (1 + s2 * x**2) + PAPER["S1_V_per_K2"] * x
    k = PAPER["K_W_per_K"] * (1 + k1 * x)
    assert K.tem_voltage(np.array([Th, Tc]), current, p) == pytest.approx(R * current + S * (Th - Tc), rel=1e-12)
    Q = _heat([Th, Tc], current, p)
    assert Q[1] == pytest.approx(k * (Th - Tc) + 0.5 * R * current**2 - S * Tc * current, rel=1e-12)
    assert Q[0] == pytest.approx(k * (Tc - Th) + 0.5 * R * current**2 + S * Th * current, rel=1e-12)


def test_network_effects_by_hand():
    base = build(PAPER)["network"]
    net = build({**PAPER, "contact_R_cold_K_per_W": 0.06, "contact_R_hot_K_per_W": 0.02, "extra_leak_W_per_K": 0.15})[
        "network"
    ]
    idx = base.index
    # a contact resistance in series with the plate's link to its block only
    for plate, block, r in (("cold_plate", "bottom_upper", 0.06), ("hot_plate", "top_lower", 0.02)):
        g = base.G[0, idx(plate), idx(block)]
        assert net.G[0, idx(plate), idx(block)] == pytest.approx(1.0 / (1.0 / g + r), rel=1e-14)
        assert net.G[0, idx(block), idx(plate)] == net.G[0, idx(plate), idx(block)]
    # the module's own conduction is not a network link and stays untouched
    assert net.G[0, idx("hot_plate"), idx("cold_plate")] == 0.0
    # the extra ambient leak adds 0.15 W/K in proportion to the existing leaks
    amb0, amb = base.Gb[0, :, 1], net.Gb[0, :, 1]
    assert amb.sum() == pytest.approx(amb0.sum() + 0.15, rel=1e-14)
    np.testing.assert_allclose(amb, amb0 * (1.0 + 0.15 / amb0.sum()), rtol=1e-14)
    np.testing.assert_array_equal(net.Gb[0, :, 0], base.Gb[0, :, 0])  # water side untouched


@pytest.mark.parametrize(
    ("rig", "hot_block", "cold_block"),
    [
        (rig_from_config(None, layers=True), "top_lower", "bottom_upper"),
        (hifi_rig(layers=True), "top_6", "bottom_1"),
        (outside_rig(), "top_18", "bottom_1"),
    ],
    ids=["reference-layers", "bench-hifi-layers", "bench-outside"],
)
def test_a_contact_resistance_lies_between_the_modules_outer_face_and_its_block(rig, hot_block, cold_block):
    """With the plates in layers the module's face is its alumina: the catalogue's "module face to
    block" contact goes on the alumina's link to the block, not between the junctions' copper and
    the alumina inside the module (where it hid part of the plate's heat capacity behind it)."""
    params = {**PAPER, **rig.nominal()}
    base = build(params, rig)["network"]
    net = build({**params, "contact_R_cold_K_per_W": 0.06, "contact_R_hot_K_per_W": 0.02}, rig)["network"]
    changed = {
        tuple(sorted((rig.node_names[i], rig.node_names[j])))
        for i, j in zip(*np.nonzero(~np.isclose(net.G[0], base.G[0], rtol=1e-15, atol=0.0)))
    }
    assert rig.module_faces == ("hot_ceramic", "cold_ceramic")
    expected = {("cold_ceramic", cold_block): 0.06, ("hot_ceramic", hot_block): 0.02}
    assert changed == {tuple(sorted(pair)) for pair in expected}, changed
    for (a, b), r in expected.items():
        g = base.G[0, base.index(a), base.index(b)]
        assert net.G[0, net.index(a), net.index(b)] == pytest.approx(1.0 / (1.0 / g + r), rel=1e-14)


def test_current_offset_inverts_the_measurement():
    # measured = (1 + g) I + o: a model told about g and o, fed the measured
    # current, must reproduce the model fed the true current
    g, o = 0.015, 0.006
    t = np.arange(0.0, 240.0, 0.5)
    true = np.select([t < 60, t < 150], [0.0, 0.8], -1.2)
    tw, ta = np.full_like(t, TW), np.full_like(t, TA)
    a = simulate(Inputs(t, true, [tw, ta]), PAPER)
    b = simulate(Inputs(t, (1 + g) * true + o, [tw, ta]), {**PAPER, "current_gain_error": g, "current_offset_A": o})
    # same true current up to rounding in (I (1+g) + o - o)/(1+g): 1e-12 K
    # after integration; the effect itself moves things by ~20 mK
    np.testing.assert_allclose(b.sensors, a.sensors, rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.voltage, a.voltage, rtol=0, atol=1e-10)
    c = simulate(Inputs(t, true, [tw, ta]), {**PAPER, "current_gain_error": g, "current_offset_A": o})
    assert np.abs(c.sensors - a.sensors).max() > 0.01


def test_sensor_lag_is_a_first_order_lag():
    # tau y' = u - y.  A ramp u = t from y(0) = 0 has y = t - tau (1 - exp(-t/tau))
    # exactly; the hook is exact for inputs linear between samples, so only
    # rounding separates them (1e-12), on an uneven time grid as well.
    tau = 6.0
    rng = np.random.default_rng(2)
    t = np.cumsum(np.r_[0.0, rng.uniform(0.05, 2.0, 300)])
    Y = np.tile(t, (2, 4, 1))  # (draws, channels, samples)
    effects_mod.apply_sensors(t, Y, {"sensor_tau_s": np.array([tau, 0.0])})
    np.testing.assert_allclose(Y[0], np.tile(t - tau * (1.0 - np.exp(-t / tau)), (4, 1)), rtol=0, atol=1e-12)
    assert np.array_equal(Y[1], np.tile(t, (4, 1)))  # tau = 0: untouched
    # a sine at steady state: gain 1/sqrt(1 + (w tau)^2) and a phase lag
    # atan(w tau); the linear interpolation of the sine between 0.1 s samples
    # costs ~(w dt)^2 / 8 ~ 1e-4 relative, hence 1e-3
    w = 2 * np.pi / 60.0
    t = np.arange(0.0, 600.0, 0.1)
    Y = np.sin(w * t)[None, None, :].copy()
    effects_mod.apply_sensors(t, Y, {"sensor_tau_s": tau})
    late = t > 300.0
    expected = np.sin(w * t[late] - np.arctan(w * tau)) / np.sqrt(1.0 + (w * tau) ** 2)
    np.testing.assert_allclose(Y[0, 0, late], expected, rtol=0, atol=1e-3)


def test_a_sensor_with_its_own_response_time_lags_by_it_and_the_others_by_the_common_one():
    # channel 0 its own 2 s, channel 1 the common 6 s, channel 2 its own 0 (no lag)
    t = np.arange(0.0, 120.0, 0.5)
    Y = np.tile(t, (1, 3, 1))
    effects_mod.apply_sensors(t, Y, {"sensor_tau_s": 6.0}, np.array([[2.0, np.nan, 0.0]]))
    for c, tau in ((0, 2.0), (1, 6.0)):
        np.testing.assert_allclose(Y[0, c], t - tau * (1.0 - np.exp(-t / tau)), rtol=0, atol=1e-12)
    assert np.array_equal(Y[0, 2], t)
    assert effects_mod.has_sensor_effect({}, np.array([[np.nan, 0.5]]))
    assert not effects_mod.has_sensor_effect({}, np.array([[np.nan, 0.0]]))


def test_a_rig_files_sensor_lags_reach_the_simulation():
    """reference-faces gives T2 and T3 their own response times: a slower T2 moves T2 alone."""
    from tembayes.physics.rigread import shipped_rig

    rig = shipped_rig("reference-faces").build()
    t = np.arange(0.0, 600.0, 1.0)
    current = np.where(t < 200.0, 1.0, 3.0)
    bounds = np.vstack([np.full_like(t, 293.15), np.full_like(t, 295.15)])
    base = {"R0_ohm": 1.6, "R1_ohm_per_K": 0.007, "S0_V_per_K": 0.049, "S1_V_per_K2": 1e-4, "K_W_per_K": 0.5}
    fast = simulate(Inputs(t, current, bounds), {**base, "tau_T2": 0.5, "tau_T3": 0.5}, rig=rig)
    slow = simulate(Inputs(t, current, bounds), {**base, "tau_T2": 3.0, "tau_T3": 0.5}, rig=rig)
    assert np.array_equal(fast.sensors[0, 1], slow.sensors[0, 1])
    after = (t > 200.0) & (t < 215.0)
    assert np.all(slow.sensors[0, 0, after] < fast.sensors[0, 0, after] - 1e-4)  # T2 rises, later when slower


def test_all_effects_at_zero_is_the_paper_model(short_base):
    inp, base = short_base
    zeros = {p: 0.0 for e in CATALOGUE.values() for p in e.parameter_names}
    assert _same(simulate(inp, {**PAPER, **zeros}), base)


# ------------------------------------------------------ 7. rig descriptions


def test_unknown_preset_names_the_known_ones():
    with pytest.raises(ModelError, match="nope") as err:
        rig_from_config({"preset": "nope"})
    for preset in SHIPPED:
        assert preset in str(err.value)


def test_unknown_override_raises():
    with pytest.raises(ModelError, match="g_coolr"):
        rig_from_config({"preset": "reference", "g_coolr": 11.0})
    with pytest.raises(ModelError, match="must be numbers"):
        rig_from_config({"g_cooler": "11"})
    with pytest.raises(ModelError, match="positive"):
        rig_from_config({"g_cooler": -1.0})


def test_override_changes_the_network():
    base = rig_from_config({}).network()
    rig = rig_from_config({"preset": "reference", "g_cooler": 11.0, "leak_bottom": 0.05})
    assert rig.nominal()["g_cooler"] == 11.0
    net = rig.network()
    i = net.index("top_upper")
    g_sq = REFERENCE.nominal()["g_steel_quarter"]
    assert net.Gb[0, i, 0] == pytest.approx(1.0 / (1.0 / 11.0 + 1.0 / g_sq), rel=1e-14)
    assert net.Gb[0, i, 0] != base.Gb[0, i, 0]
    assert net.Gb[0, :, 1].sum() == pytest.approx(0.02 + 0.05, rel=1e-14)
    # and the simulated block temperatures move with it
    t = np.arange(0.0, 5.0)
    inp = Inputs(t, np.full(5, 0.8), [np.full(5, TW), np.full(5, TA)])
    a = simulate(inp, PAPER).sensors
    b = simulate(inp, PAPER, rig=rig).sensors
    assert np.abs(a - b).max() > 1e-3


def _mini(**kw):
    args = dict(
        name="mini",
        parameters=(
            RigParameter("a", 2.0, 1.0, 3.0, "W/K"),
            RigParameter("b", 6.0, 1.0, 9.0, "W/K"),
            RigParameter("c_plate_hot", 4.0, 3.0, 5.0, "J/K"),
            RigParameter("c_legs", 1.0, 0.5, 2.0, "J/K"),
        ),
        nodes=(("h", "c_plate_hot + 0.5*c_legs"), ("c", 4.0)),
        links=(("water", "h", ["a", "b"]), ("c", "ambient", "0.25*b"), ("h", "c", "a + 2*b")),
        hot="h",
        cold="c",
        boundaries=REFERENCE.boundaries,
    )
    args.update(kw)
    return RigDescription(**args)


def test_rig_expressions():
    net = _mini().network()
    assert net.Gb[0, 0, 0] == pytest.approx(1.0 / (1.0 / 2.0 + 1.0 / 6.0), rel=1e-15)  # series
    assert net.C[0, 0] == pytest.approx(4.0 + 0.5 * 1.0, rel=1e-15)  # sum with a factor
    assert net.Gb[0, 1, 1] == pytest.approx(0.25 * 6.0, rel=1e-15)
    assert net.G[0, 0, 1] == net.G[0, 1, 0] == pytest.approx(2.0 + 12.0, rel=1e-15)
    assert net.C[0, 1] == 4.0
    # values per draw override the nominal ones
    net2 = _mini().network({"a": np.array([1.0, 3.0])})
    assert net2.Gb[:, 0, 0] == pytest.approx([1.0 / (1.0 + 1.0 / 6.0), 1.0 / (1.0 / 3.0 + 1.0 / 6.0)])
    # the reference rig: plates carry half the legs, sensors at node centres
    ref = REFERENCE.network()
    nom = REFERENCE.nominal()
    assert ref.C[0, ref.index("hot_plate")] == pytest.approx(nom["c_plate_hot"] + 0.5 * nom["c_legs"])
    assert REFERENCE.tem_chain == ("hot_plate", "cold_plate")
    assert rig_from_config(None, leg_cells=3).tem_chain == ("hot_plate", "leg_1", "leg_2", "leg_3", "cold_plate")
    legs = rig_from_config(None, leg_cells=3).network()
    assert legs.C[0].sum() == pytest.approx(ref.C[0].sum(), rel=1e-14)  # same total capacitance


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"links": (("water", "h", "a"), ("h", "nowhere", "a"))}, "nowhere"),
        ({"links": (("water", "h", "a_typo"),)}, "a_typo"),
        ({"nodes": (("h", "c_plate_hot + 0.5*c_leggs"), ("c", 4.0))}, "c_leggs"),
        ({"links": (("water", "h", "x*a"),)}, "unknown parameter 'x'"),
        ({"links": (("water", "h", "1.5.2*a"),)}, "bad factor"),
        ({"links": (("water", "ambient", "a"),)}, "two boundaries"),
        ({"links": (("water", "h", []),)}, "empty series"),
        ({"links": (("water", "h", -1.0),)}, "non-positive"),
        ({"hot": "hh"}, "hh"),
        ({"legs": ("h",)}, "leg node"),
        ({"sensors": {"T1_C": "zz"}}, "zz"),
        ({"parameters": (RigParameter("a", 1.0, 0.5, 2.0, "W/K"),) * 2}, "duplicate"),
    ],
)
def test_bad_rig_description_raises(kw, match):
    with pytest.raises(ModelError, match=match):
        _mini(**kw)


def test_rig_with_only_numeric_expressions_builds():
    rig = RigDescription(
        name="numbers",
        parameters=(),
        nodes=(("h", 4.0), ("c", 4.0)),
        links=(("water", "h", 100.0), ("c", "ambient", 0.1)),
        hot="h",
        cold="c",
        boundaries=REFERENCE.boundaries,
    )
    net = rig.network()
    assert net.C.shape == (1, 2)


def test_simulate_rejects_unknown_and_missing_parameters():
    inp = Inputs(np.arange(3.0), np.zeros(3), [np.full(3, TW), np.full(3, TA)])
    with pytest.raises(ModelError, match="S0_V_per_KK"):
        simulate(inp, {**PAPER, "S0_V_per_KK": 0.05})
    with pytest.raises(ModelError, match="sensor_tau"):  # effect name instead of its parameter
        simulate(inp, {**PAPER, "sensor_tau": 5.0})
    for missing in MODULE_PARAMETERS:
        params = {k: v for k, v in PAPER.items() if k != missing}
        with pytest.raises(ModelError, match=missing):
            simulate(inp, params)
    with pytest.raises(ModelError, match="K_W_per_K"):
        simulate(inp, {**PAPER, "K_W_per_K": -0.5})
    with pytest.raises(ModelError, match="shape"):
        simulate(inp, {**PAPER, "R0_ohm": [1.7, 1.8], "S0_V_per_K": [0.04, 0.05, 0.06]})
    # a rig parameter of another rig is unknown to this one
    with pytest.raises(ModelError, match="g_cell"):
        simulate(inp, {**PAPER, "g_cell": 300.0})


def test_a_sensor_off_its_cells_centre_reads_the_steel_at_its_own_depth():
    """Depth from the face the sensor is named against; at the nominal depth the node itself."""
    from tembayes.bench.hifi import SENSOR_DEPTH
    from tembayes.physics.simulate import Inputs, simulate

    rig = rig_from_config(None, leg_cells=2, block_split=3)
    dx = 0.010 / 6
    t = np.linspace(0.0, 600.0, 61)
    inputs = Inputs(time=t, current=np.full_like(t, 3.0), boundaries=[np.full_like(t, 298.15), np.full_like(t, 296.15)])
    laws = {"R0_ohm": 2.0, "R1_ohm_per_K": 0.01, "S0_V_per_K": 0.05, "S1_V_per_K2": 1e-4, "K_W_per_K": 0.5}
    # T2 one cell deeper (towards the cooler) reads the next cell's centre, the T1 side unchanged
    nominal, deeper = (
        simulate(inputs, {**laws, "depth_T2": d}, rig=rig).sensors[0] for d in (SENSOR_DEPTH, SENSOR_DEPTH + dx)
    )
    assert np.array_equal(nominal[[0, 2, 3]], deeper[[0, 2, 3]])
    profile = simulate(inputs, laws, rig=rig_from_config(None, leg_cells=2, block_split=3)).sensors[0]
    assert np.array_equal(profile, nominal)
    # in steady state, heat flows from the module up through the top block: the deeper cell is cooler,
    # and by the flux times the steel's resistance over one cell
    assert np.all(deeper[1, -5:] < nominal[1, -5:] - 0.05)
    half = SENSOR_DEPTH + 0.5 * dx
    mid = simulate(inputs, {**laws, "depth_T2": half}, rig=rig).sensors[0]
    np.testing.assert_allclose(mid[1], 0.5 * (nominal[1] + deeper[1]), rtol=0, atol=1e-9)
