"""The rig model linearised at an operating point, for observer design.

The rig is the thermal network of :mod:`tembayes.physics` (node temperatures
``x`` [K]) driven by the module current and the water and ambient
temperatures, ``u = (I [A], T_water [K], T_amb [K])``, and read by the four
sensors and the module voltage, ``y = (T1..T4 [K], V [V])``.  Inputs and
outputs are named by their CSV columns (``current_A``, ``T_water_C``, ...,
``T1_C``, ..., ``voltage_V``), the channel names of every output of tembayes;
their values are SI (:data:`INPUT_UNITS`, :data:`OUTPUT_UNITS`):

    dx/dt = f(x, u; theta),   y = h(x, u; theta).

At an operating point -- the module's mean junction temperature ``T̄`` and
its current ``I``, the water temperature solved so that the steady state has
that ``T̄`` (ambient fixed) -- the deviations obey

    d(dx)/dt = A dx + B du,   dy = C dx + D du

with ``A = df/dx`` (exact: the network is linear, the module's heat
Jacobian is a complex step in the kernel), ``B``'s water and ambient columns
exact, its current column and the voltage row of ``C`` and ``D`` by central
differences.  The sensors read nodes, so their rows of ``C`` are unit
vectors.  Sensitivities ``dA/dtheta`` etc. are central differences in each
parameter with the operating point (``T̄``, ``I``) held, i.e. the water
temperature solved again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from tembayes.constants import KELVIN, SENSOR_CHANNELS
from tembayes.errors import ModelError
from tembayes.physics import kernel as K
from tembayes.physics.simulate import build
from tembayes.predict.runmodel import CHANNELS

#: Inputs of the linear model, named by their CSV columns.
INPUTS = ("current_A", "T_water_C", "T_amb_C")
#: Units of the inputs' values (SI: kelvin, though the names are the degC columns').
INPUT_UNITS = ("A", "K", "K")
#: Outputs of the linear model: the predicted channels (sensors, then the voltage).
OUTPUTS = CHANNELS
#: Units of the outputs' values (a deviation in K is one in degC).
OUTPUT_UNITS = ("K",) * len(SENSOR_CHANNELS) + ("V",)
#: Relative step of the parameter sensitivities.
REL_STEP = 1e-4


@dataclass(frozen=True)
class LinearModel:
    """The rig linearised at one operating point (SI, deviation variables).

    Attributes
    ----------
    tavg_C, current_A : float
        The operating point asked for: mean junction temperature [degC], current [A].
    x0 : ndarray, shape (n,)
        Steady node temperatures [K].
    u0 : ndarray, shape (3,)
        Inputs at the point: current [A], water and ambient temperature [K].
    y0 : ndarray, shape (5,)
        Outputs at the point: T1..T4 [K], voltage [V].
    A, B, C, D : ndarray
        ``(n, n)`` [1/s], ``(n, 3)``, ``(5, n)``, ``(5, 3)``.
    states, inputs, outputs : tuple of str
    sensitivity : dict
        Parameter -> ``{"A", "B", "C", "D", "x0", "u0", "y0"}``, the
        derivatives of the matrices and of the operating point (T̄ and I
        held, the water temperature solved again) per unit of the parameter (SI).
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
        a, b, f = rig.readout(SENSOR_CHANNELS, {k: float(v) for k, v in params.items()})
        # each sensor reads a blend of two nodes (its depth, RigDescription.readout)
        self.read = np.zeros((len(a), len(self.nodes)))
        self.read[np.arange(len(a)), a] += 1.0 - f[0]
        self.read[np.arange(len(a)), b] += f[0]
        self.hot, self.cold = self.nodes.index(rig.hot), self.nodes.index(rig.cold)

    def steady(self, current, tw, ta, guess=None):
        y0 = np.full(len(self.nodes), tw) if guess is None else guess
        y, ok = K.steady_one(y0, K.true_current(current, self.p), tw, ta, self.A, self.Bb, self.Cinv, self.tem, self.p)
        if not ok or not np.all(np.isfinite(y)):
            raise ModelError(f"no steady state at I = {current} A, water {tw - KELVIN:.2f} C")
        return y

    def rhs(self, x, current, tw, ta):
        return K.rhs_one(x, K.true_current(current, self.p), tw, ta, self.A, self.Bb, self.Cinv, self.tem, self.p)

    def outputs(self, x, current):
        v = K.tem_voltage(x[self.tem], K.true_current(current, self.p), self.p)
        return np.concatenate([self.read @ x, [v]])

    def point(self, tavg_K, current, ta):
        """Steady state whose mean junction temperature is ``tavg_K``: the water temperature solved."""

        def miss(tw):
            y = self.steady(current, tw, ta)
            return 0.5 * (y[self.hot] + y[self.cold]) - tavg_K

        lo, hi = tavg_K - 80.0, tavg_K + 80.0
        try:
            tw = brentq(miss, lo, hi, xtol=1e-9)
        except ValueError as err:
            raise ModelError(
                f"no water temperature in {lo - KELVIN:.0f}..{hi - KELVIN:.0f} C gives "
                f"T_avg {tavg_K - KELVIN:.2f} C at {current} A"
            ) from err
        return self.steady(current, tw, ta), tw

    def matrices(self, x0, u0):
        current, tw, ta = u0
        n = len(x0)
        A = K.jac_one(x0, K.true_current(current, self.p), self.A, self.Cinv, self.tem, self.p)
        h = 1e-4 * max(1.0, abs(current))
        B = np.empty((n, 3))
        B[:, 0] = (self.rhs(x0, current + h, tw, ta) - self.rhs(x0, current - h, tw, ta)) / (2 * h)
        B[:, 1:] = self.Bb  # the network is linear in the boundary temperatures
        C = np.zeros((len(OUTPUTS), n))
        C[: len(self.read)] = self.read
        hx = 1e-3  # K: the voltage is smooth (quadratic) in the temperatures
        for i in self.tem:
            e = np.zeros(n)
            e[i] = hx
            C[-1, i] = (self.outputs(x0 + e, current)[-1] - self.outputs(x0 - e, current)[-1]) / (2 * hx)
        D = np.zeros((len(OUTPUTS), 3))
        D[-1, 0] = (self.outputs(x0, current + h)[-1] - self.outputs(x0, current - h)[-1]) / (2 * h)
        return A, B, C, D


def linearise(params, rig, tavg_C, current_A, *, t_amb_C=25.0, sensitivity=()):
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
    t_amb_C : float
        Ambient temperature [degC]; the water temperature is solved.
    sensitivity : sequence of str
        Parameters to differentiate the matrices by (names of ``params``).

    Returns
    -------
    LinearModel

    Raises
    ------
    tembayes.errors.ModelError
        No steady state reaches the point (e.g. a ``T̄`` the water cannot reach at that current).
    """
    ta = float(t_amb_C) + KELVIN
    tavg = float(tavg_C) + KELVIN

    def at(p):
        r = _Rig(p, rig)
        x0, tw = r.point(tavg, float(current_A), ta)
        u0 = np.array([float(current_A), tw, ta])
        return r, x0, u0, r.matrices(x0, u0), r.outputs(x0, float(current_A))

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
    return LinearModel(float(tavg_C), float(current_A), x0, u0, y0, A, B, C, D, r.nodes, INPUTS, OUTPUTS, sens)
