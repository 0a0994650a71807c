"""The rig model linearised at an operating point, for observer design.

The rig is the thermal network of :mod:`tembayes.physics` (node temperatures
``x`` [K]) driven by the module current and the rig's measured boundary
temperatures, ``u = (I [A], boundaries [K])``, and read by the rig's sensors
and the module voltage, ``y = (sensors [K], V [V])``.  Inputs and outputs
are named by their CSV columns (``current_A``, the boundary columns, the
sensor columns, ``voltage_V``), the channel names of every output of
tembayes; their values are SI (:func:`io_names`):

    dx/dt = f(x, u; theta),   y = h(x, u; theta).

At an operating point -- the module's mean junction temperature ``T̄`` and
its current ``I`` -- the rig's controlled boundaries (every boundary but the
room it leaks to, :attr:`~tembayes.physics.layout.Layout.leak_boundary`; the
room itself on a rig with no other) are solved, all at one temperature, so
that the steady state has that ``T̄``; the room stays at its given
temperature.  The deviations obey

    d(dx)/dt = A dx + B du,   dy = C dx + D du

with ``A = df/dx`` (exact: the network is linear, the module's heat
Jacobian is a complex step in the kernel), ``B``'s boundary columns exact,
its current column and the voltage row of ``C`` and ``D`` by central
differences.  A sensor reads a node (or a blend of two at its depth), so its
row of ``C`` is fixed by the rig.  Sensitivities ``dA/dtheta`` etc. are
central differences in each parameter with the operating point (``T̄``,
``I``) held, i.e. the controlled boundaries solved again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from tembayes.constants import KELVIN
from tembayes.errors import ModelError
from tembayes.physics import kernel as K
from tembayes.physics.simulate import build
from tembayes.predict.runmodel import VOLTAGE

#: Relative step of the parameter sensitivities.
REL_STEP = 1e-4


def io_names(rig):
    """``(inputs, input_units, outputs, output_units)`` of the rig's linear model, named by CSV columns.

    Units are SI: kelvin for temperatures, though the names are the degC
    columns' (a deviation in K is one in degC).
    """
    layout = rig.layout
    inputs = ("current_A", *layout.boundaries)
    outputs = (*layout.sensors, VOLTAGE)
    return inputs, ("A",) + ("K",) * len(layout.boundaries), outputs, ("K",) * len(layout.sensors) + ("V",)


@dataclass(frozen=True)
class LinearModel:
    """The rig linearised at one operating point (SI, deviation variables).

    Attributes
    ----------
    tavg_C, current_A : float
        The operating point asked for: mean junction temperature [degC], current [A].
    x0 : ndarray, shape (n,)
        Steady node temperatures [K].
    u0 : ndarray, shape (1 + nb,)
        Inputs at the point: current [A], boundary temperatures [K].
    y0 : ndarray, shape (ns + 1,)
        Outputs at the point: the sensors [K], voltage [V].
    A, B, C, D : ndarray
        ``(n, n)`` [1/s], ``(n, 1 + nb)``, ``(ns + 1, n)``, ``(ns + 1, 1 + nb)``.
    states, inputs, outputs : tuple of str
    sensitivity : dict
        Parameter -> ``{"A", "B", "C", "D", "x0", "u0", "y0"}``, the
        derivatives of the matrices and of the operating point (T̄ and I
        held, the controlled boundaries solved again) per unit of the parameter (SI).
    """

    tavg_C: float
    current_A: float
    x0: np.ndarray
    u0: np.ndarray
    y0: np.ndarray
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    states: tuple
    inputs: tuple
    outputs: tuple
    sensitivity: dict


class _Rig:
    """The kernel arrays of one parameter set, and its steady states."""

    def __init__(self, params, rig):
        m = build({k: float(v) for k, v in params.items()}, rig)
        self.A, self.Bb, self.Cinv = m["A"][0], m["Bb"][0], m["Cinv"][0]
        self.p, self.tem = m["P"][0], m["tem"]
        self.nodes = tuple(m["network"].nodes)
        values = {k: float(v) for k, v in params.items()}
        a, b, f = rig.readout(rig.layout.sensors, values)
        # each sensor reads a blend of two nodes (its depth, RigDescription.readout), and a
        # share of the room through its leads (RigDescription.lead_shares)
        self.lead = rig.lead_shares(rig.layout.sensors, values)[0]
        self.room = rig.layout.room_index
        self.read = np.zeros((len(a), len(self.nodes)))
        self.read[np.arange(len(a)), a] += 1.0 - f[0]
        self.read[np.arange(len(a)), b] += f[0]
        self.read *= (1.0 - self.lead)[:, None]
        self.hot, self.cold = self.nodes.index(rig.hot), self.nodes.index(rig.cold)
        layout = rig.layout
        self.controlled = np.array([c in layout.controlled for c in layout.boundaries])

    def steady(self, current, ub, guess=None):
        y0 = np.full(len(self.nodes), ub[0]) if guess is None else guess
        y, ok = K.steady_one(y0, K.true_current(current, self.p), ub, self.A, self.Bb, self.Cinv, self.tem, self.p)
        if not ok or not np.all(np.isfinite(y)):
            raise ModelError(f"no steady state at I = {current} A, boundaries {np.round(ub - KELVIN, 2)} C")
        return y

    def rhs(self, x, current, ub):
        return K.rhs_one(x, K.true_current(current, self.p), ub, self.A, self.Bb, self.Cinv, self.tem, self.p)

    def outputs(self, x, current, ub):
        v = K.tem_voltage(x[self.tem], K.true_current(current, self.p), self.p)
        return np.concatenate([self.read @ x + self.lead * ub[self.room], [v]])

    def boundaries(self, level, room):
        """The boundary temperatures with the controlled ones at ``level`` and the room at ``room`` [K]."""
        ub = np.full(len(self.controlled), float(room))
        ub[self.controlled] = level
        return ub

    def point(self, tavg_K, current, room):
        """Steady state whose mean junction temperature is ``tavg_K``: the controlled boundaries solved."""

        def miss(level):
            y = self.steady(current, self.boundaries(level, room))
            return 0.5 * (y[self.hot] + y[self.cold]) - tavg_K

        lo, hi = tavg_K - 80.0, tavg_K + 80.0
        try:
            level = brentq(miss, lo, hi, xtol=1e-9)
        except ValueError as err:
            raise ModelError(
                f"no boundary temperature in {lo - KELVIN:.0f}..{hi - KELVIN:.0f} C gives "
                f"T_avg {tavg_K - KELVIN:.2f} C at {current} A"
            ) from err
        ub = self.boundaries(level, room)
        return self.steady(current, ub), ub

    def matrices(self, x0, u0):
        current, ub = u0[0], u0[1:]
        n, nb = len(x0), len(ub)
        ny = len(self.read) + 1
        A = K.jac_one(x0, K.true_current(current, self.p), self.A, self.Cinv, self.tem, self.p)
        h = 1e-4 * max(1.0, abs(current))
        B = np.empty((n, 1 + nb))
        B[:, 0] = (self.rhs(x0, current + h, ub) - self.rhs(x0, current - h, ub)) / (2 * h)
        B[:, 1:] = self.Bb  # the network is linear in the boundary temperatures
        C = np.zeros((ny, n))
        C[: len(self.read)] = self.read
        hx = 1e-3  # K: the voltage is smooth (quadratic) in the temperatures
        for i in self.tem:
            e = np.zeros(n)
            e[i] = hx
            C[-1, i] = (self.outputs(x0 + e, current, ub)[-1] - self.outputs(x0 - e, current, ub)[-1]) / (2 * hx)
        D = np.zeros((ny, 1 + nb))
        D[-1, 0] = (self.outputs(x0, current + h, ub)[-1] - self.outputs(x0, current - h, ub)[-1]) / (2 * h)
        D[: len(self.read), 1 + self.room] = self.lead
        return A, B, C, D


def linearise(params, rig, tavg_C, current_A, *, room_C=25.0, sensitivity=()):
    """The rig linearised at a steady operating point.

    Parameters
    ----------
    params : mapping of str to float
        Module laws and conductance (SI) and any rig parameters (nominal if absent).
    rig : RigDescription
    tavg_C : float
        Mean junction temperature of the point [degC].
    current_A : float
        Module current [A] (positive cools the cold plate).
    room_C : float
        Temperature of the room the rig leaks to [degC]; the controlled
        boundaries are solved (on a rig whose only boundary is the room,
        the room is, and this is ignored).
    sensitivity : sequence of str
        Parameters to differentiate the matrices by (names of ``params``).

    Returns
    -------
    LinearModel

    Raises
    ------
    tembayes.errors.ModelError
        No steady state reaches the point (e.g. a ``T̄`` the boundaries cannot reach at that current).
    """
    room = float(room_C) + KELVIN
    tavg = float(tavg_C) + KELVIN
    inputs, _, outputs, _ = io_names(rig)

    def at(p):
        r = _Rig(p, rig)
        x0, ub = r.point(tavg, float(current_A), room)
        u0 = np.concatenate([[float(current_A)], ub])
        return r, x0, u0, r.matrices(x0, u0), r.outputs(x0, float(current_A), ub)

    r, x0, u0, (A, B, C, D), y0 = at(params)
    sens = {}
    for name in sensitivity:
        if name not in params:
            raise ModelError(f"sensitivity to {name!r}: not a parameter of the model ({sorted(params)})")
        v = float(params[name])
        h = REL_STEP * (abs(v) if v != 0 else 1.0)
        _, xh, uh, mh, yh = at({**params, name: v + h})
        _, xl, ul, ml, yl = at({**params, name: v - h})
        sens[name] = {k: (a - b) / (2 * h) for k, a, b in zip("ABCD", mh, ml)}
        sens[name].update({"x0": (xh - xl) / (2 * h), "u0": (uh - ul) / (2 * h), "y0": (yh - yl) / (2 * h)})
    return LinearModel(float(tavg_C), float(current_A), x0, u0, y0, A, B, C, D, r.nodes, inputs, outputs, sens)
