"""Acceptance tolerances of a batch report: the pass/fail line per module.

A tolerance is one text, as on the command line (``--tolerance``):

- ``R0=5%`` -- within +-5 % of the **datasheet-derived value** (``R0``,
  ``S0`` and ``K`` only: the standard conversions (docs/data-format.md,
  '[module_type]') of Vmax, Imax, dTmax at
  the datasheet's hot-side temperature ``th_C``; the law is evaluated at
  ``th_C``, so a datasheet quoted at 27 degC is compared with R(27 degC));
- ``R1=0.008:0.012`` -- inside an absolute range, SI units
  (ohm, ohm/K, V/K, V/K^2, W/K);
- ``outlier_prob=0.5`` -- the module's outlier probability at most this;
- ``converged=yes`` -- the calibration converged (``no`` drops the check).

A parameter check **passes** when the posterior probability of the range is
at least ``confidence`` (default 0.95): a module whose value is probably,
but not surely, inside fails with that probability shown, rather than
passing on its mean.  Parameters may be named short (``R0``) or as in
docs/outputs.md, 'Module parameters' (``R0_ohm``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from tembayes.constants import KELVIN, MODULE_PARAMETERS

if TYPE_CHECKING:
    from collections.abc import Sequence

    from tembayes.calibrate.run import CalibrationRun
    from tembayes.data import Datasheet

#: Checks applied when the user sets none.
DEFAULT_TOLERANCES = ("R0=5%", "S0=5%", "K=10%", "outlier_prob=0.5", "converged=yes")
#: Posterior probability of the range that passes a parameter check.
DEFAULT_CONFIDENCE = 0.95

_SHORT = {p.split("_")[0]: p for p in MODULE_PARAMETERS}
_DATASHEET = {"R0_ohm": "resistance", "S0_V_per_K": "seebeck", "K_W_per_K": "conductance"}


@dataclass(frozen=True)
class Tolerance:
    """One acceptance check.

    Attributes
    ----------
    text : str
        As given (``"R0=5%"``).
    name : str
        Contract parameter name, ``"outlier_prob"`` or ``"converged"``.
    kind : str
        ``"relative"`` (to the datasheet), ``"range"``, ``"max"`` or ``"flag"``.
    value : tuple
        ``(fraction,)``, ``(low, high)`` SI, ``(max,)`` or ``(required,)``.
    """

    text: str
    name: str
    kind: str
    value: tuple


def parse_tolerance(text: str) -> Tolerance:
    """One :class:`Tolerance` from its text; ``ValueError`` naming what is wrong."""
    if "=" not in text:
        raise ValueError(f"tolerance {text!r}: expected NAME=VALUE, e.g. R0=5% or R1=0.008:0.012")
    key, val = (s.strip() for s in text.split("=", 1))
    if key == "converged":
        if val.lower() not in ("yes", "no", "true", "false"):
            raise ValueError(f"tolerance {text!r}: converged=yes or converged=no")
        return Tolerance(text, key, "flag", (val.lower() in ("yes", "true"),))
    if key == "outlier_prob":
        p = _number(text, val)
        if not 0.0 <= p <= 1.0:
            raise ValueError(f"tolerance {text!r}: an outlier probability between 0 and 1")
        return Tolerance(text, key, "max", (p,))
    name = _SHORT.get(key, key)
    if name not in MODULE_PARAMETERS:
        raise ValueError(
            f"tolerance {text!r}: unknown name {key!r}; use one of {sorted(_SHORT) + ['outlier_prob', 'converged']}"
        )
    if val.endswith("%"):
        if name not in _DATASHEET:
            raise ValueError(
                f"tolerance {text!r}: the datasheet gives no value of {name}; give an absolute "
                f"range, e.g. {key}=LOW:HIGH in SI units"
            )
        f = _number(text, val[:-1]) / 100.0
        if not f > 0:
            raise ValueError(f"tolerance {text!r}: a positive percentage")
        return Tolerance(text, name, "relative", (f,))
    if ":" in val:
        lo, hi = (_number(text, v) for v in val.split(":", 1))
        if not hi > lo:
            raise ValueError(f"tolerance {text!r}: LOW:HIGH with LOW < HIGH")
        return Tolerance(text, name, "range", (lo, hi))
    raise ValueError(f"tolerance {text!r}: give PERCENT% (of the datasheet value) or LOW:HIGH (SI)")


def _number(text, s):
    try:
        return float(s)
    except ValueError:
        raise ValueError(f"tolerance {text!r}: {s!r} is not a number") from None


def check_module(
    tolerances: Sequence[Tolerance],
    run: CalibrationRun,
    module_id: str,
    datasheet: Datasheet,
    *,
    confidence: float = DEFAULT_CONFIDENCE,
) -> dict:
    """Every check of one module.

    Parameters
    ----------
    tolerances : sequence of Tolerance
    run : tembayes.calibrate.run.CalibrationRun
    module_id : str
    datasheet : tembayes.data.Datasheet
    confidence : float
        Posterior probability of the range needed to pass.

    Returns
    -------
    dict
        ``{"passed": bool, "checks": [{"check", "passed", "detail", ...}]}``.
    """
    checks = []
    draws = run.draws(module_id, MODULE_PARAMETERS)
    for tol in tolerances:
        if tol.kind == "flag":
            conv = run.converged(module_id)
            ok = bool(conv) or not tol.value[0]
            checks.append({"check": tol.text, "passed": ok, "detail": run.status(module_id)})
        elif tol.kind == "max":
            p = run.outlier_prob(module_id)
            ok = p is None or p <= tol.value[0]
            detail = "no population fit" if p is None else f"outlier probability {p:.2f}"
            checks.append({"check": tol.text, "passed": ok, "detail": detail})
        else:
            x = draws[:, MODULE_PARAMETERS.index(tol.name)]
            if tol.kind == "relative":
                x, lo, hi, ref = _vs_datasheet(tol, draws, datasheet, run.tref_C)
                where = f"datasheet {ref:.4g} at {datasheet.th - KELVIN:g} °C +-{100 * tol.value[0]:g} %"
            else:
                lo, hi = tol.value
                where = f"range {lo:.4g}..{hi:.4g}"
            p_in = float(np.mean((x >= lo) & (x <= hi))) if len(x) else float("nan")
            checks.append(
                {
                    "check": tol.text,
                    "passed": bool(p_in >= confidence),
                    "p_inside": p_in,
                    "low": lo,
                    "high": hi,
                    "mean": float(np.mean(x)),
                    "detail": f"mean {np.mean(x):.4g}, P(inside {where}) = {p_in:.3f}",
                }
            )
    return {"passed": all(c["passed"] for c in checks), "checks": checks}


def _vs_datasheet(tol, draws, datasheet, tref_C):
    """Draws of the parameter at the datasheet's temperature, and its tolerance band."""
    ref = float(getattr(datasheet, _DATASHEET[tol.name])())
    col = MODULE_PARAMETERS.index(tol.name)
    x = draws[:, col]
    dT = (datasheet.th - KELVIN) - tref_C
    if tol.name in ("R0_ohm", "S0_V_per_K") and dT != 0.0:
        x = x + dT * draws[:, col + 1]  # the law at th_C: R0 + R1 (th - tref)
    f = tol.value[0]
    return x, ref * (1.0 - f), ref * (1.0 + f), ref
