"""A scipy ``solve_ivp`` reference of exactly the simulator's equations.

Slow and simple on purpose: it checks :func:`tembayes.physics.simulate` (the
tests and ``analyses/bench_simulator.py``) and is the baseline the simulator's
speed is measured against.  Same network, same module element, same inputs
(linear between samples); only the integrator differs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.integrate import solve_ivp

from tembayes.errors import ModelError
from tembayes.physics import effects
from tembayes.physics import kernel as K
from tembayes.physics.rigread import REFERENCE
from tembayes.physics.simulate import Simulation, build

if TYPE_CHECKING:
    from collections.abc import Mapping

    from tembayes.physics.rig import RigDescription
    from tembayes.physics.simulate import Inputs


def simulate_reference(
    inputs: Inputs,
    params: Mapping[str, float | np.ndarray],
    *,
    rig: RigDescription = REFERENCE,
    method: str = "BDF",
    rtol: float = 1e-9,
    atol: float = 1e-9,
    jac: bool = True,
) -> Simulation:
    """Simulate each parameter set with ``scipy.integrate.solve_ivp``, one after the other.

    Parameters
    ----------
    inputs : tembayes.physics.Inputs
    params : mapping
        As for :func:`tembayes.physics.simulate`.
    rig : RigDescription, optional
    method : str, optional
        ``solve_ivp`` method, default ``"BDF"``.
    rtol, atol : float, optional
        ``solve_ivp`` tolerances (``atol`` in kelvin).
    jac : bool, optional
        Pass the analytic Jacobian (the fair baseline for a stiff solver).

    Returns
    -------
    Simulation
    """
    m = build(params, rig)
    nd = m["nd"]
    t = inputs.time
    names = m["network"].nodes
    channels = tuple(rig.sensors)
    a, b, f = rig.readout(channels, m["params"])
    f = np.broadcast_to(f, (nd, len(channels)))
    tem = m["tem"]
    sensors = np.empty((nd, len(channels), len(t)))
    volt = np.empty((nd, len(t)))
    t_hot = np.empty((nd, len(t)))
    t_cold = np.empty((nd, len(t)))
    steps = np.empty(nd, dtype=np.int64)
    for d in range(nd):
        A, Bb, Cinv, p = m["A"][d], m["Bb"][d], m["Cinv"][d], m["P"][d]

        def u(tt, p=p):
            i_true = K.true_current(np.interp(tt, t, inputs.current), p)
            return i_true, np.array([np.interp(tt, t, ub) for ub in inputs.boundaries])

        def fun(tt, y, A=A, Bb=Bb, Cinv=Cinv, p=p):
            i_true, ub = u(tt)
            return K.rhs_one(y, i_true, ub, A, Bb, Cinv, tem, p)

        def jacf(tt, y, A=A, Cinv=Cinv, p=p):
            return K.jac_one(y, u(tt)[0], A, Cinv, tem, p)

        i0, ub0 = u(t[0])
        y0, ok = K.steady_one(np.full(len(names), ub0[0]), i0, ub0, A, Bb, Cinv, tem, p)
        if not ok:
            raise ModelError("reference: steady-state start did not converge")
        sol = solve_ivp(
            fun, (t[0], t[-1]), y0, method=method, t_eval=t, rtol=rtol, atol=atol, jac=jacf if jac else None
        )
        if not sol.success:
            raise ModelError(f"reference solve_ivp failed: {sol.message}")
        Y = sol.y
        sensors[d] = Y[a] + f[d][:, None] * (Y[b] - Y[a])
        t_hot[d] = Y[tem[0]]
        t_cold[d] = Y[tem[-1]]
        i_true = K.true_current(inputs.current, p)
        chain = Y[tem]
        volt[d] = [K.tem_voltage(np.ascontiguousarray(chain[:, n]), i_true[n], p) for n in range(len(t))]
        steps[d] = sol.t.size if sol.nfev is None else sol.nfev
    rig.read_leads(sensors, channels, m["params"], inputs.boundaries)
    effects.apply_sensors(t, sensors, m["params"], rig.sensor_lags(channels, m["params"]))
    return Simulation(t, channels, sensors, volt, t_hot, t_cold, steps)
