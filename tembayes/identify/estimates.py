"""Per-step estimates of R (the voltage jump) and S (the steady state).

The paper's Algorithm 1 (after Mitrani et al. 2004), done carefully:

- **R from the jump.**  Right after a current step only ``R dI`` moves the
  voltage, but the Seebeck back-EMF starts moving at once (the plates respond
  in a fraction of a second).  So the post-step voltage is fitted over a few
  seconds with ``c0 + c1 sqrt(tau)`` (tau: time since the step; a block's
  surface answers a step in heat flux as sqrt(tau)) and extrapolated back to
  the step instant (midway between the two samples that bracket it), and the
  pre-step voltage (a steady hold) with a line.  Where exactly between the
  samples the step fell is not in the data; that uncertainty is common to all
  steps of a run (a programme timer and a DAQ clock keep a nearly fixed
  phase) and is carried as a correlated error into the R(T) fit.
  On bench data this basis is unbiased to ~0.1 %, where a quadratic in tau
  over the same window is +1-2 % and the first sample +2-4 %
  (``analyses/jump_extrapolation.py``).  ``R = dV(t_step) / dI`` (the paper prints it upside
  down).  The uncertainty combines both fits' standard errors with the
  step-time uncertainty (the step happened somewhere between two samples).
  The paper's literal version takes the first sample after the step.

- **S from the steady state.**  At the end of each hold,
  ``S(T_mean) = (V - R(T_mean) I) / dT``.  The paper takes the face sensors
  (the sensor nearest each module face; T2 and T3 on the reference rig):
  ``dT = T2 - T3``, ``T_mean = (T2 + T3) / 2``.  But tens of watts flow
  through paste and steel between a junction and its sensor, so the junction
  temperatures differ from the sensors by up to kelvins.  The corrected
  version reconstructs them from the rig network (:func:`junction_temperatures`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from tembayes.errors import ModelError

if TYPE_CHECKING:
    from collections.abc import Mapping

    from tembayes.data.experiment import Experiment
    from tembayes.data.steps import Step
    from tembayes.physics.rig import RigDescription


@dataclass(frozen=True)
class Jump:
    """Voltage jump at a current step.

    Attributes
    ----------
    R : float
        Extrapolated jump resistance ``dV(t_step)/dI`` [ohm].
    R_sd : float
        Its standard uncertainty [ohm]: ``hypot(R_sd_fit, R_sd_time)``.
    R_sd_fit : float
        From the two fits' standard errors (independent between steps) [ohm].
    R_sd_time : float
        From not knowing where between two samples the step happened
        (common to the steps of a run) [ohm].
    R_first : float
        The paper's literal estimate: first sample after minus last before,
        over dI [ohm].
    window : float
        Length of the post-step fit window [s].
    """

    R: float
    R_sd: float
    R_sd_fit: float
    R_sd_time: float
    R_first: float
    window: float


def _basis(u, basis):
    if basis == "line":
        return np.c_[np.ones_like(u), u]
    if basis == "sqrt":
        return np.c_[np.ones_like(u), np.sqrt(np.maximum(u, 0.0))]
    raise ValueError(f"basis must be 'line' or 'sqrt', got {basis!r}")


def _fit_at(x, y, x0, basis):
    """Least-squares fit in ``x - x0``; value at ``x0``, its standard error, coefficients."""
    X = _basis(x - x0, basis)
    coef = np.linalg.lstsq(X, y, rcond=None)[0]
    dof = max(len(y) - X.shape[1], 1)
    resid = y - X @ coef
    cov = float(resid @ resid) / dof * np.linalg.pinv(X.T @ X)
    return float(coef[0]), float(np.sqrt(cov[0, 0])), coef


def jump_resistance(
    time: np.ndarray,
    voltage: np.ndarray,
    current: np.ndarray,
    step: Step,
    *,
    pre_window: float = 30.0,
    post_window: float | None = None,
) -> Jump:
    """Estimate R from the voltage jump at one step.

    Parameters
    ----------
    time, voltage, current : ndarray, shape (n,)
        [s], [V], [A].
    step : tembayes.data.steps.Step
    pre_window : float
        Length of the pre-step line fit [s] (inside the previous hold).
    post_window : float, optional
        Length of the post-step fit [s]; default ``max(3 s, 8 sampling
        intervals)``.

    Returns
    -------
    Jump
    """
    t, v, i = time, voltage, current
    k = step.index
    dt = float(np.median(np.diff(t[max(k - 20, 1) : k + 20])))
    w = post_window if post_window is not None else max(3.0, 8.0 * dt)
    pre = slice(max(step.prev_start, int(np.searchsorted(t, step.t - pre_window))), k)
    post = slice(k, min(step.hold_end, int(np.searchsorted(t, step.t + w, side="right"))))
    if pre.stop - pre.start < 3 or post.stop - post.start < 4:
        raise ModelError(f"step at t = {step.t:.1f} s: too few samples around it for the jump fit")
    dI = float(np.median(i[post]) - np.median(i[pre]))
    v_pre, sd_pre, _ = _fit_at(t[pre], v[pre], step.t, "line")
    v_post, sd_post, _ = _fit_at(t[post], v[post], step.t, "sqrt")
    R = (v_post - v_pre) / dI
    # The step happened somewhere within +- t_window of the midpoint.  The
    # data cannot tell where (the back-EMF's shape near tau = 0 is not known
    # well enough), and a programme timer and a DAQ clock keep a nearly fixed
    # phase, so this error is common to all steps of a run: reported apart.
    lo = _fit_at(t[post], v[post], step.t - step.t_window, "sqrt")[0]
    hi = _fit_at(t[post], v[post], step.t + 0.999 * step.t_window, "sqrt")[0]
    lo_pre = _fit_at(t[pre], v[pre], step.t - step.t_window, "line")[0]
    hi_pre = _fit_at(t[pre], v[pre], step.t + 0.999 * step.t_window, "line")[0]
    R_sd_time = abs((hi - hi_pre) - (lo - lo_pre)) / abs(dI) / 2.0 / np.sqrt(3.0)
    R_sd_fit = float(np.hypot(sd_pre, sd_post) / abs(dI))
    R_first = float((v[k] - v[k - 1]) / dI)
    return Jump(
        R=float(R),
        R_sd=float(np.hypot(R_sd_fit, R_sd_time)),
        R_sd_fit=R_sd_fit,
        R_sd_time=float(R_sd_time),
        R_first=R_first,
        window=float(w),
    )


@dataclass(frozen=True)
class Steady:
    """The end of a hold: averages over its last ``window`` seconds.

    Temperatures in kelvin, ``sensors`` in the experiment's (the rig's)
    order, ``boundaries`` in the rig's boundary order, ``face_T`` the hot- and
    cold-face sensors' temperatures (:attr:`~tembayes.physics.layout.Layout.face`).
    """

    t_end: float
    window: float
    current: float
    voltage: float
    voltage_sd: float
    sensors: np.ndarray
    sensors_sd: np.ndarray
    boundaries: np.ndarray
    face_T: tuple
    drift: float  # slope of the cold-face sensor over the window [K/s]: how far from steady


def hold_end(exp: Experiment, start: int, stop: int, *, face: tuple[str, str], window: float = 60.0) -> Steady:
    """Average the last ``window`` seconds of a hold ``[start, stop)`` of an experiment.

    ``face`` names the sensors next to the module's hot and cold faces.
    """
    t = exp.time
    a = max(start, int(np.searchsorted(t, t[stop - 1] - window)))
    sl = slice(a, stop)
    n = stop - a
    if n < 5:
        raise ModelError(f"hold ending at t = {t[stop - 1]:.1f} s is too short for a steady-state average")

    def mean_sd(x):
        return float(np.mean(x)), float(np.std(x, ddof=1) / np.sqrt(n))

    v, vsd = mean_sd(exp.voltage[sl])
    sens = np.array([mean_sd(x[sl]) for x in exp.sensors])
    drift = float(np.polyfit(t[sl] - t[sl].mean(), exp.channel(face[1])[sl], 1)[0])
    at_face = tuple(float(sens[exp.sensor_names.index(c), 0]) for c in face)
    return Steady(
        t_end=float(t[stop - 1]),
        window=float(t[stop - 1] - t[a]),
        current=float(np.mean(exp.current[sl])),
        voltage=v,
        voltage_sd=vsd,
        sensors=sens[:, 0],
        sensors_sd=sens[:, 1],
        boundaries=np.mean(exp.boundaries[:, sl], axis=1),
        face_T=at_face,
        drift=drift,
    )


def junction_temperatures(
    steady: Steady,
    rig: RigDescription,
    values: Mapping[str, float] | None = None,
    *,
    sds: Mapping[str, float] | None = None,
    n_draws: int = 400,
    rng: np.random.Generator | None = None,
) -> tuple[tuple[float, float], tuple[float, float], tuple[np.ndarray, np.ndarray]]:
    """Module plate (junction) temperatures at steady state, from the sensors.

    A plate read by a sensor is that sensor.  Otherwise the rig's node next
    to the plate must be read by a sensor.  Then the heat the plate sends
    into the block equals what that node passes on (steady state), and the
    plate temperature is the node's plus that flux over the plate-node
    link's conductance.  The node's other neighbours are read by sensors (the
    reference rig) or, where none is, sit at the steady state of the rig's
    unread nodes between the read ones and the boundaries
    (:func:`node_temperatures`; ``reference-faces``, whose blocks are read
    next to the module only).

    Parameters
    ----------
    steady : Steady
    rig : RigDescription
    values : mapping, optional
        Rig parameter values (e.g. from the rig fit); nominal if absent.
    sds : mapping, optional
        Standard errors of ``values`` (e.g. from the rig fit).
    n_draws : int
        Monte-Carlo draws for the uncertainty: rig parameters normal about
        ``values`` with ``sds`` where given, otherwise uniform over their
        documented range; sensor means within their standard errors.
    rng : numpy.random.Generator, optional

    Returns
    -------
    (t_hot, t_cold) : tuple of float
        [K]
    (sd_hot, sd_cold) : tuple of float
        [K]
    (draws_hot, draws_cold) : tuple of ndarray, shape (n_draws,)
        The Monte-Carlo draws [K].  With the same ``rng`` seed for every hold
        of a run, the rig-value draws are shared between holds, so the draws
        carry the correlation between holds.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    values = dict(values or {})
    sds = dict(sds or {})
    draws = {}
    for p in rig.parameters:
        if p.name in values:
            v, sd = float(values[p.name]), float(sds.get(p.name, 0.0) or 0.0)
            draws[p.name] = np.abs(v + sd * rng.standard_normal(n_draws))
        else:
            draws[p.name] = rng.uniform(p.low, p.high, n_draws)
    draws = {k: np.concatenate([[values.get(k, rig.parameter(k).nominal)], v]) for k, v in draws.items()}
    net = rig.network(draws)
    names = net.nodes
    read = {node: c for c, node in enumerate(rig.sensors.values())}
    ns = len(steady.sensors)
    sens = steady.sensors[None, :] + np.concatenate(
        [np.zeros((1, ns)), rng.normal(0, 1, (n_draws, ns)) * steady.sensors_sd[None, :]]
    )
    node_T = node_temperatures(rig, net, sens, steady.boundaries)
    out = []
    for plate in (rig.hot, rig.cold):
        if plate in read:
            out.append(sens[:, read[plate]])
            continue
        p = names.index(plate)
        nbrs = [j for j in np.flatnonzero(net.G[0, p]) if names[j] not in rig.tem_chain]
        if len(nbrs) != 1 or names[nbrs[0]] not in read:
            raise ModelError(f"rig '{rig.name}': plate '{plate}' needs exactly one neighbour read by a sensor")
        b = nbrs[0]
        Tb = node_T[names[b]]
        flux = np.zeros(n_draws + 1)  # heat leaving node b other than to the plate [W]
        for j in np.flatnonzero(net.G[0, b]):
            if j != p:
                flux += net.G[:, b, j] * (Tb - node_T[names[j]])
        for kb in range(len(rig.boundaries)):
            flux += net.Gb[:, b, kb] * (Tb - steady.boundaries[kb])
        out.append(Tb + flux / net.G[:, p, b])
    th, tc = out
    return (float(th[0]), float(tc[0])), (float(np.std(th[1:])), float(np.std(tc[1:]))), (th[1:], tc[1:])


def node_temperatures(rig: RigDescription, net, sens: np.ndarray, boundaries: np.ndarray) -> dict[str, np.ndarray]:
    """Steady temperatures of the rig's nodes outside the module.

    A node a sensor reads is that sensor.  Every other one passes on all
    the heat it takes (no source at steady state), so with the read nodes
    and the boundaries given their temperatures solve one linear system per
    draw.

    Parameters
    ----------
    rig : RigDescription
    net : the rig's network at the draws (``G`` (nd, N, N), ``Gb`` (nd, N, nb)) [W/K]
    sens : ndarray, shape (nd, n_sensors)
        Sensor readings per draw [K], in the order of ``rig.sensors``.
    boundaries : ndarray, shape (nb,)
        [K]

    Returns
    -------
    dict
        Node name -> (nd,) temperatures [K].

    Raises
    ------
    ModelError
        An unread node next to the module (its heat is not passed on).
    """
    names = list(net.nodes)
    read = {names.index(node): c for c, node in enumerate(rig.sensors.values())}
    known = {names[i]: sens[:, c] for i, c in read.items()}
    module = {names.index(n) for n in (rig.hot, rig.cold, *rig.tem_chain)}
    free = [i for i in range(len(names)) if i not in read and i not in module]
    if not free:
        return known
    blind = sorted(module - set(read))
    touching = np.argwhere(net.G[0][np.ix_(free, blind)] > 0)
    if len(touching):
        u, j = touching[0]
        raise ModelError(
            f"rig '{rig.name}': node '{names[free[u]]}' next to the module's '{names[blind[j]]}' has no sensor"
        )
    # the free nodes' rows of the network's Laplacian, the read nodes and the boundaries moved to the right
    G = net.G[:, free, :]
    A = -G[:, :, free]
    A[:, np.arange(len(free)), np.arange(len(free))] += G.sum(axis=2) + net.Gb[:, free, :].sum(axis=2)
    at, cols = list(read), list(read.values())
    rhs = net.Gb[:, free, :] @ np.asarray(boundaries, float) + np.einsum("dkr,dr->dk", G[:, :, at], sens[:, cols])
    T = np.linalg.solve(A, rhs[..., None])[..., 0]
    return {**known, **{names[u]: T[:, k] for k, u in enumerate(free)}}
