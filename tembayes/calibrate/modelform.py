"""Which physics the calibration model has: ``full`` (the default) or the paper's.

``full`` holds what every real module and rig has, beyond the paper's form:

- Peltier heat at each junction's own Seebeck coefficient and Thomson heat
  in the legs (``thomson_fraction = 1``): thermodynamics whenever S depends
  on T, the first law exact for a linear law;
- the module's plates in two layers, alumina and the junctions' copper,
  joined by the ceramic's conductance ``g_ceramic`` (held at its nominal
  value, :data:`tembayes.physics.rig.CERAMIC`): the junctions see only a
  fifth of the plate's heat capacity, so their temperature difference moves
  faster after a step than the paper's plate node lets it;
- the sensors' own response time ``sensor_tau_s`` (a thermistor in its
  hole: a fraction of a second to a few seconds), sampled under a uniform
  prior on [0, 3] s;
- a temperature slope of the module's thermal conductance ``K1_per_K``
  (``K(T) = K (1 + K1 (T - T_ref))``), sampled under N(0, 0.001/K): left
  out, a slope of 0.0002/K moves S1 by ~10 % (measured on the
  out-of-model bench).
- the steel's heat capacity and conductivity sampled under their documented
  ranges (+-3 %, +-5 %) rather than held at the handbook value: held, their
  uncertainty alone is ~2 % of R0, S0 and K (carried over by ``--discrepancy
  robust``); sampled, the run pins them and the laws' 90 % widths fall to
  ~0.6-0.9 % (two out-of-model modules, both still inside their intervals).

The laws keep their meaning: R_m and S_m are the linear laws in the mean
junction temperature, and K is the conductance at T_ref.  ``paper`` is the
form of Evers et al. (S at the mean temperature at both junctions, one node
per plate, no sensor lag, constant K).

``paper`` is selected with ``tembayes calibrate --model paper``, for
comparison with the source study.
"""

from __future__ import annotations

from dataclasses import dataclass

from tembayes.calibrate.priors import ParameterPrior
from tembayes.errors import ModelError

__all__ = ["ModelForm", "FORMS", "DEFAULT_FORM", "get_form"]


@dataclass(frozen=True)
class ModelForm:
    """A calibration model's physics.

    Attributes
    ----------
    name : str
    layers : bool
        The module's plates in two layers (:meth:`tembayes.physics.rigfile.RigFile.build` with ``layers``).
    physics : dict
        Effect parameters held at a value (the rig description carries them).
    priors : tuple of ParameterPrior
        Effect parameters sampled with every calibration.
    includes : tuple of str
        Catalogue effects the form already contains (``gap`` does not test them;
        ``calibrate --effect`` with one of them is refused).
    min_range : float
        Rig parameters whose documented range (high/low) is narrower than
        this are held at their nominal value; the others are sampled.
    """

    name: str
    layers: bool
    physics: dict
    priors: tuple
    includes: tuple
    min_range: float


FORMS = {
    f.name: f
    for f in (
        ModelForm(
            "full",
            True,
            {"thomson_fraction": 1.0},
            (ParameterPrior("sensor_tau_s", "uniform", 1.5, 1.5), ParameterPrior("K1_per_K", "normal", 0.0, 1e-3)),
            ("thomson", "sensor_lag", "k_temperature"),
            1.05,
        ),
        # the paper's steel is known: its material and size
        ModelForm("paper", False, {}, (), (), 1.2),
    )
}

#: The form a calibration uses unless told otherwise.
DEFAULT_FORM = "full"


def get_form(name: str) -> ModelForm:
    """The form called ``name`` (``"full"`` or ``"paper"``)."""
    try:
        return FORMS[name]
    except KeyError:
        raise ModelError(f"unknown model form {name!r}; known: {', '.join(FORMS)}") from None
