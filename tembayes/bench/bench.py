"""The virtual bench: synthetic batches with known truth.

:func:`simulate_batch` draws a batch of modules of one type (unit-to-unit
spread of a few percent around a type whose true values differ from the
datasheet conversions), optionally makes one of them an outlier, runs the
identification staircase and validation cycles on the higher-fidelity rig
(:mod:`tembayes.bench.hifi`) with slow water and ambient drifts, adds sensor
noise, and writes a contract batch folder plus ``truth.json``.

Two fidelity levels: ``standard`` (:mod:`tembayes.bench.hifi`), the
calibration model's structure at its default resolution, with the current
steps resolved more finely -- it proves the code; and ``high``
(:mod:`tembayes.bench.outside`), a rig and module the calibration model does
not contain (finer steel, the module's layers, sensor bodies at uncertain
depths, Thomson heat, K(T), re-mounting spread, slow sensor noise) -- it
measures the method.  Every statistical study reports both.

Those two are the reference rig's.  Any other rig (a shipped preset or a rig
file, ``BenchConfig.rig``) is simulated by :mod:`tembayes.bench.anyrig`: at
``standard``, the rig file at a finer resolution than the calibration's,
with the standard bench's physics; at ``high``, that network with sensor
bodies and leads, module edge leaks, re-mounting spread and slow sensor
noise added (:func:`~tembayes.bench.anyrig.outside_bench_rig`).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

import tembayes
from tembayes.bench import anyrig, hifi, outside
from tembayes.bench.hifi import DEPTHS
from tembayes.bench.protocols import (
    boundary_drifts,
    identification_staircase,
    plate_staircase,
    sample_times,
    validation_cycle,
)
from tembayes.constants import KELVIN, T_REF
from tembayes.data import (
    Datasheet,
    atomic_directory,
    experiment_from_arrays,
    write_batch_toml,
    write_experiment_csv,
    write_json,
)
from tembayes.errors import ModelError
from tembayes.physics.effects import STEP_FRACTIONS
from tembayes.physics.rigfile import CERAMIC
from tembayes.physics.rigread import rig_file_of
from tembayes.physics.simulate import Inputs, simulate

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping

    from tembayes.bench.protocols import Protocol
    from tembayes.data import Experiment
    from tembayes.physics.rig import RigDescription

#: The reference module type (``docs/data-format.md``, 'The reference rig').
TEC1_12706 = Datasheet(name="TEC1-12706", th=25.0 + KELVIN, imax=6.4, vmax=14.4, dtmax=66.0, qmax=50.0)

#: Measurement noise (rms) of the reference rig.
NOISE = {"temperature_K": 0.004, "voltage_V": 0.001, "current_A": 0.001}

#: Relative unit-to-unit spread (sd) of each parameter within a batch.
UNIT_SPREAD = {"R0_ohm": 0.02, "R1_ohm_per_K": 0.05, "S0_V_per_K": 0.01, "S1_V_per_K2": 0.06, "K_W_per_K": 0.03}

#: Bench fidelity levels (``tembayes simulate --fidelity``).
FIDELITIES = ("standard", "high")
#: The high-fidelity bench's slow sensor noise: an Ornstein-Uhlenbeck part [K], [s].
SLOW_NOISE = (0.0015, 20.0)
#: Module type's relative temperature slope of K (sd) [1/K].
K1_SD = 3e-4
#: Range of the thermistors' response time on the standard bench [s] (the high-fidelity bench has sensor bodies).
SENSOR_TAU_RANGE = (0.2, 1.5)
#: Physics of the standard bench: that of the calibration model's forms (:mod:`tembayes.calibrate.modelform`).
PHYSICS = ("full", "paper")
#: Relative change of the batch's cooler clamp and enclosure leaks from one mounting to the next (sd).
REMOUNT_SD = {"g_cooler": 0.03, "leak_top": 0.1, "leak_bottom": 0.1, "leak_module": 0.2}


@dataclass(frozen=True)
class BenchConfig:
    """What :func:`simulate_batch` makes.

    Attributes
    ----------
    n_modules : int
    effects : dict
        Effect name -> {parameter: value} (see :func:`tembayes.physics.parse_effects`).
    seed : int
    outlier : str or None
        Module id (``"TEM1"``...) whose S0 is shifted by ``outlier_shift``.
    outlier_shift : float
        Relative S0 shift of the outlier; its sign is drawn.
    datasheet : Datasheet
    rate : float
        Sampling rate of the identification runs [Hz].
    validation_rate : float or None
        Sampling rate of the validation runs [Hz]; ``None`` = ``rate``.
    hold : float
        Identification hold duration [s].
    n_validations : int
        Validation runs per module.
    validation_duration : float
        [s]
    fidelity : str
        ``"standard"`` or ``"high"`` (the out-of-model bench, see the module doc).
    validation_start : str
        ``"steady"``: a validation run starts with 300 s at rest (0 A, the rig
        settled); ``"rest"``: the rig at rest and the current switched
        straight to the first level at the first sample.
    physics : str
        The standard bench's physics, that of a calibration model form:
        ``"full"`` (the default model's: Thomson heat, layered plates, a
        sensor response time drawn in :data:`SENSOR_TAU_RANGE`, sensor depths
        drawn in their range, a temperature slope of K) or ``"paper"``
        (Evers et al.'s form).  The high-fidelity bench has its own.
    protocol : Protocol or None
        The identification run's current program (``simulate --protocol``,
        :mod:`tembayes.design.protocol`), levels in A as given; None: the
        rig's identification staircase with ``hold``.
    rig : dict or None
        A ``[rig]`` table (``{"preset": NAME}`` or ``{"file": PATH}``,
        :func:`tembayes.physics.rigread.rig_source`) for a rig other than the
        reference one, simulated by :mod:`tembayes.bench.anyrig`; None (or
        the reference preset): the reference rig's benches.
    """

    n_modules: int = 3
    effects: dict = field(default_factory=dict)
    seed: int = 0
    outlier: str | None = None
    outlier_shift: float = 0.04
    datasheet: Datasheet = TEC1_12706
    rate: float = 5.0
    validation_rate: float | None = None
    hold: float = 600.0
    n_validations: int = 1
    validation_duration: float = 4 * 3600.0
    fidelity: str = "standard"
    validation_start: str = "steady"
    physics: str = "full"
    rig: dict | None = None
    protocol: Protocol | None = None

    def __post_init__(self):
        if self.rig == {"preset": "reference"}:
            object.__setattr__(self, "rig", None)
        if self.rig is not None:
            rig_file_of(self.rig)  # an unreadable rig is refused here, before any work
        if self.fidelity not in FIDELITIES:
            raise ModelError(f"fidelity must be one of {FIDELITIES}, got {self.fidelity!r}")
        if self.physics not in PHYSICS:
            raise ModelError(f"physics must be one of {PHYSICS}, got {self.physics!r}")
        if self.validation_start not in ("steady", "rest"):
            raise ModelError(f"validation_start must be 'steady' or 'rest', got {self.validation_start!r}")
        if self.n_modules < 1:
            raise ModelError("n_modules must be at least 1")
        if self.outlier is not None and self.outlier not in self.module_ids:
            raise ModelError(f"outlier '{self.outlier}' is not one of the modules {self.module_ids}")
        for name in ("rate", "validation_rate"):
            r = getattr(self, name)
            if r is not None and not 0.05 <= r <= 100:
                raise ModelError(f"{name} must be between 0.05 and 100 Hz, got {r}")
        if self.hold < 30:
            raise ModelError(f"hold must be at least 30 s, got {self.hold}")
        if self.n_validations < 0:
            raise ModelError("n_validations must be >= 0")

    @property
    def module_ids(self) -> tuple[str, ...]:
        """Ids of the batch's modules, ``("TEM1", "TEM2", ...)``."""
        return tuple(f"TEM{i + 1}" for i in range(self.n_modules))


def draw_truth(config: BenchConfig, rng: np.random.Generator) -> dict:
    """True parameters of the batch's type and of each module.

    Returns
    -------
    dict
        ``population`` (type means), ``modules`` (id -> law parameters,
        bench rig values and their lumped equivalent, outlier flag).
    """
    population = draw_type(config.datasheet, rng)
    if config.rig is not None:
        return _draw_truth_any_rig(config, rng, population)
    high = config.fidelity == "high"
    full = high or config.physics == "full"
    params = outside.OUTSIDE_PARAMETERS if high else hifi.HIFI_PARAMETERS + (CERAMIC,)
    # one enclosure and one cooler for the whole batch; paste and plates per mounting
    shared = {k: _draw_rig(rng, k, params) for k in ("g_cooler", "leak_top", "leak_bottom")}
    layout = {"physics": {}}
    if high:
        shared.update({k: _draw_rig(rng, k, params) for k in ("leak_module", "c_sensor", "g_sensor")})
        sides, shares = outside.draw_sensor_depths(rng)
        shared.update(shares)
        layout = {"depth_sides": sides, "physics": {"thomson_fraction": 1.0, "K1_per_K": float(rng.normal(0, K1_SD))}}
    elif full:  # the calibration model's own physics, with values a real rig and module would have
        layout = {
            "physics": {
                "thomson_fraction": 1.0,
                "K1_per_K": float(rng.normal(0, K1_SD)),
                "sensor_tau_s": float(rng.uniform(*SENSOR_TAU_RANGE)),
            }
        }
    if full:  # the steel is known to its documented range, not exactly: one rig, one draw
        shared.update({k: _draw_rig(rng, k, params) for k in ("c_cell", "g_cell")})
        if not high:
            shared["g_half_cell"] = 2.0 * shared["g_cell"]
            # the holes' depths, as the out-of-model bench draws its sensors' (outside.draw_sensor_depths)
            shared.update({p.name: float(rng.uniform(p.low, p.high)) for p in DEPTHS})
    modules = {}
    for mid in config.module_ids:
        laws, is_out = _draw_unit(config, rng, population, mid)
        rig = dict(shared)
        for k in ("g_paste_hot", "g_paste_cold", "c_plate_hot", "c_plate_cold", "c_legs") + (
            ("g_ceramic",) if full else ()
        ):
            rig[k] = _draw_rig(rng, k, params)
        if high:  # the cooler clamped and the enclosure closed again for every module
            for k, sd in REMOUNT_SD.items():
                rig[k] *= float(np.exp(sd * rng.standard_normal()))
        equivalent = outside.reference_equivalent(rig) if high else hifi.reference_equivalent(rig)
        modules[mid] = {
            **{k: float(v) for k, v in laws.items()},
            "outlier": bool(is_out),
            "rig_bench": {k: float(v) for k, v in rig.items()},
            "rig": {k: float(v) for k, v in equivalent.items()},
        }
    return {"population": {k: float(v) for k, v in population.items()}, "modules": modules, "bench_layout": layout}


def draw_type(ds, rng):
    """The type's true laws and K: the datasheet conversions off by a few %."""
    R0 = ds.resistance() * rng.normal(1.0, 0.04)
    S0 = ds.seebeck() * rng.normal(1.0, 0.03)
    K0 = ds.conductance() * rng.normal(1.0, 0.05)
    R1 = R0 * 0.005 * rng.normal(1.0, 0.1)  # R rises ~0.5 %/K
    S1 = S0 * 0.002 * rng.normal(1.0, 0.15)  # S rises ~0.2 %/K
    return {"R0_ohm": R0, "R1_ohm_per_K": R1, "S0_V_per_K": S0, "S1_V_per_K2": S1, "K_W_per_K": K0}


def _draw_unit(config, rng, population, mid):
    """One module's laws and K about the type's, and whether it is the outlier."""
    laws = {k: v * (1.0 + UNIT_SPREAD[k] * rng.standard_normal()) for k, v in population.items()}
    is_out = mid == config.outlier
    if is_out:
        laws["S0_V_per_K"] *= 1.0 + config.outlier_shift * rng.choice([-1.0, 1.0])
    return laws, is_out


def _draw_truth_any_rig(config, rng, population):
    """:func:`draw_truth` on a rig other than the reference one (:mod:`tembayes.bench.anyrig`)."""
    rig = bench_rig_of(config)
    high = config.fidelity == "high"
    physics = {}
    if high or config.physics == "full":
        physics = {"thomson_fraction": 1.0, "K1_per_K": float(rng.normal(0, K1_SD))}
    if config.physics == "full" and not high:  # the out-of-model bench's sensors lag by their bodies
        physics["sensor_tau_s"] = float(rng.uniform(*SENSOR_TAU_RANGE))
    mounting = anyrig.mounting_parameters(rig)
    shared = anyrig.draw_rig_values(rng, rig.parameters, [p for p in rig.parameter_names if p not in mounting])
    remount = anyrig.remount_spreads(rig, shared) if high else {}
    modules = {}
    for mid in config.module_ids:
        laws, is_out = _draw_unit(config, rng, population, mid)
        values = {**shared, **anyrig.draw_rig_values(rng, rig.parameters, sorted(mounting))}
        for k, sd in remount.items():  # within the documented range: a mounting is still this rig
            p = rig.parameter(k)
            values[k] = float(np.clip(values[k] * np.exp(sd * rng.standard_normal()), p.low, p.high))
        modules[mid] = {
            **{k: float(v) for k, v in laws.items()},
            "outlier": bool(is_out),
            "rig_bench": values,
            "rig": dict(values),
        }
    return {
        "population": {k: float(v) for k, v in population.items()},
        "modules": modules,
        "bench_layout": {"physics": physics},
    }


def batch_bench_rig(config: BenchConfig, truth: Mapping) -> RigDescription:
    """The network a batch's bench simulates.

    :func:`bench_rig_of`, or on the reference rig's out-of-model bench the network with the
    batch's drawn sensor depths (``truth`` as :func:`draw_truth` returns it, or a batch's
    ``truth.json``).
    """
    if config.fidelity == "high" and config.rig is None:
        return outside.outside_rig(truth["bench_layout"]["depth_sides"])
    return bench_rig_of(config)


def bench_rig_of(config: BenchConfig) -> RigDescription:
    """The network the bench simulates for ``config``.

    Not the reference rig's out-of-model bench, which needs its drawn sensor depths
    (:func:`batch_bench_rig`).
    """
    if config.rig is None:
        return hifi.hifi_rig(layers=config.physics == "full")
    if config.fidelity == "high":
        return anyrig.outside_bench_rig(anyrig.bench_rig(rig_file_of(config.rig)))
    return anyrig.bench_rig(rig_file_of(config.rig), layers=config.physics == "full")


def _draw_rig(rng, name, parameters):
    p = next(q for q in parameters if q.name == name)
    sd = (p.high - p.low) / 6.0
    while True:  # truncated to the documented range
        v = rng.normal(p.nominal, sd)
        if p.low <= v <= p.high:
            return v


def run_experiment(
    protocol: Protocol,
    module: dict,
    effect_params: Mapping[str, float],
    rng: np.random.Generator,
    *,
    rate: float = 5.0,
    rig: RigDescription | None = None,
    t0: float = 0.0,
    path: Path | str | None = None,
    start: str = "steady",
    slow_noise: tuple[float, float] | None = None,
) -> Experiment:
    """Run one experiment on the bench and return it as a measured Experiment.

    Parameters
    ----------
    protocol : tembayes.bench.protocols.Protocol
    module : dict
        Law parameters and ``rig_bench`` values (from :func:`draw_truth`).
    effect_params : dict
        Effect parameter name -> value (flat).
    rng : numpy.random.Generator
    rate : float
        Sampling rate [Hz].
    rig : RigDescription, optional
        Bench rig, default :func:`tembayes.bench.hifi.hifi_rig`.
    t0 : float
        Time stamp of the first sample [s].
    start : str
        ``"steady"``: the rig settled at the first level's current;
        ``"rest"``: the rig settled at 0 A and the first level switched on
        just before the first sample.
    slow_noise : tuple of float, optional
        ``(sd [K], tau [s])`` of an Ornstein-Uhlenbeck noise added to every
        temperature channel on top of the white noise.
    """
    rig = rig or hifi.hifi_rig()
    ts = sample_times(rng, protocol.duration, rate=rate)
    # resolve each current step with a 1 ms ramp (the amplifier), between samples
    steps = protocol.step_times
    pre = [ts[0] - 0.03, ts[0] - 0.02 - 1e-3, ts[0] - 0.02] if start == "rest" else []
    # and the first interval after it finely, as the models do (a sensor's lag is integrated as
    # if its input were linear between grid points)
    nxt = ts[np.minimum(np.searchsorted(ts, steps, side="right"), len(ts) - 1)]
    sub = (steps[:, None] + np.maximum(nxt - steps, 0.0)[:, None] * np.asarray(STEP_FRACTIONS)[None, :]).ravel()
    near = ts[np.clip(np.searchsorted(ts, sub), 0, len(ts) - 1)]
    sub = sub[np.abs(near - sub) > 1e-6]  # never crowd out a sample (the filter below keeps the earlier point)
    grid = np.unique(np.concatenate([pre, ts, steps - 1e-3, steps, sub]))
    grid = grid[np.concatenate([[True], np.diff(grid) > 1e-6])]
    i_true = protocol.current(grid)
    i_true[np.isin(grid, steps - 1e-3)] = protocol.current(steps - 2e-3)
    if start == "rest":  # at rest before the first level is switched on
        i_true[grid < ts[0] - 0.02 + 1e-9] = 0.0
    rooms = [name == rig.layout.leak_boundary for name in rig.boundaries]
    bounds = boundary_drifts(rng, grid, rooms, controlled=protocol.setpoint(grid))
    params = {k: module[k] for k in ("R0_ohm", "R1_ohm_per_K", "S0_V_per_K", "S1_V_per_K2", "K_W_per_K")}
    params.update(module["rig_bench"])
    # the current error is in the measurement, not in the module: applied below
    effect_params = dict(effect_params)
    meas = {k: effect_params.pop(k, 0.0) for k in ("current_gain_error", "current_offset_A")}
    params.update(effect_params)
    sim = simulate(Inputs(grid, i_true, bounds), params, rig=rig)
    sel = np.searchsorted(grid, ts)
    n = len(ts)
    noise = NOISE
    current = (1.0 + meas["current_gain_error"]) * i_true[sel] + meas["current_offset_A"]
    current = current + rng.normal(0, noise["current_A"], n)
    voltage = sim.voltage[0, sel] + rng.normal(0, noise["voltage_V"], n)
    ns = len(sim.channels)
    sensors = sim.sensors[0][:, sel] + rng.normal(0, noise["temperature_K"], (ns, n))
    measured = np.array([b[sel] + rng.normal(0, noise["temperature_K"], n) for b in bounds])
    if slow_noise is not None:
        sensors += np.stack([outside.ou_noise(rng, ts, *slow_noise) for _ in range(ns)])
    layout = rig.layout
    return experiment_from_arrays(
        ts + t0,
        current,
        voltage,
        sensors,
        measured,
        path=path,
        sensor_names=layout.sensors,
        boundary_names=layout.boundaries,
    )


def identification_run(rig: RigDescription, imax: float, hold: float) -> Protocol:
    """The identification run a lab makes on ``rig``.

    The staircase, or on plates that hold both faces (:attr:`~tembayes.physics.layout.Layout.faces_held`)
    a staircase at each plate temperature.
    """
    if rig.layout.faces_held:
        return plate_staircase(imax, hold=hold)
    return identification_staircase(imax, hold=hold)


def _protocol_json(protocol: Protocol) -> dict:
    """truth.json's ``generator.protocol``: levels [A], durations [s], and on plates each hold's setpoint [degC]."""
    out = {"levels_A": protocol.levels, "durations_s": protocol.durations}
    if protocol.setpoints is not None:
        out["setpoints_C"] = np.asarray(protocol.setpoints) - KELVIN
    return out


def _batch_rig(rig, folder):
    """The batch.toml ``[rig]`` of a bench batch; a rig file is copied into the batch folder."""
    if rig is None:
        return {"preset": "reference"}
    if "file" in rig:
        text = Path(rig["file"]).read_text(encoding="utf-8")
        (folder / "rig.toml").write_text(text, encoding="utf-8")
        return {"file": "rig.toml"}
    return dict(rig)


@dataclass(frozen=True)
class BenchSetup:
    """A batch's draws before any experiment: what :func:`run_experiment` needs per module.

    Attributes
    ----------
    truth : dict
        :func:`draw_truth`'s result.
    effects : dict
        Effect parameters of every run: the bench's own physics, then the asked-for effects.
    run : dict
        Keyword arguments of :func:`run_experiment` (``rig``, ``slow_noise``).
    module_rngs : list of numpy.random.Generator
        One stream per module, in the modules' order (adding modules does
        not change the earlier ones).
    """

    truth: dict
    effects: dict
    run: dict
    module_rngs: list


def bench_setup(config: BenchConfig) -> BenchSetup:
    """Draw a batch's type, modules and bench rig from ``config.seed`` (as :func:`simulate_batch` does)."""
    ss = np.random.SeedSequence(config.seed)
    batch_ss, *module_ss = ss.spawn(1 + config.n_modules)
    truth = draw_truth(config, np.random.default_rng(batch_ss))
    high = config.fidelity == "high"
    asked = {k: v for params in config.effects.values() for k, v in params.items()}
    rig = batch_bench_rig(config, truth)
    return BenchSetup(
        truth=truth,
        effects={**truth["bench_layout"]["physics"], **asked},
        run={"rig": rig, "slow_noise": SLOW_NOISE if high else None},
        module_rngs=[np.random.default_rng(m) for m in module_ss],
    )


def simulate_batch(
    out: Path | str, config: BenchConfig, *, overwrite: bool = False, progress: Callable[[str], None] | None = None
) -> dict:
    """Make a synthetic batch folder (``docs/data-format.md``, 'The batch folder') with ``truth.json``.

    Parameters
    ----------
    out : str or Path
        Folder to create; refused if it exists unless ``overwrite``.
    config : BenchConfig
    overwrite : bool
    progress : callable, optional
        ``progress(message)`` for each experiment; default prints to stderr.

    Returns
    -------
    dict
        The truth that was written to ``truth.json``.
    """
    if progress is None:

        def progress(msg):
            print(msg, file=sys.stderr, flush=True)

    bench = bench_setup(config)
    truth, eff_flat, run, rig = bench.truth, bench.effects, bench.run, bench.run["rig"]
    ds = config.datasheet
    high = config.fidelity == "high"
    plate_program = config.protocol is not None and config.protocol.setpoints is not None
    if config.protocol is not None and rig.layout.faces_held and not plate_program:
        raise ModelError(
            "the rig's plates hold both module faces: its identification steps the plate temperatures too; give the "
            "protocol a plate_C column (tembayes design writes one) or simulate without --protocol"
        )
    if plate_program and not rig.layout.faces_held:
        raise ModelError(
            "the protocol steps plate temperatures (plate_C), but the rig's plates do not hold both module faces; "
            "drop the plate_C column"
        )
    identification = config.protocol if config.protocol is not None else identification_run(rig, ds.imax, config.hold)
    what = f"{len(identification.levels)} levels, {identification.duration / 3600:.2f} h"
    with atomic_directory(out, overwrite=overwrite, kind="simulate") as tmp:
        write_batch_toml(tmp / "batch.toml", ds, _batch_rig(config.rig, tmp))
        for (mid, module), mrng in zip(truth["modules"].items(), bench.module_rngs):
            (tmp / mid).mkdir()
            progress(f"bench: {mid} identification ({what})")
            exp = run_experiment(
                identification,
                module,
                eff_flat,
                mrng,
                rate=config.rate,
                **run,
            )
            write_experiment_csv(tmp / mid / "identification.csv", exp)
            for v in range(config.n_validations):
                name = "validation.csv" if v == 0 else f"validation{v + 1}.csv"
                progress(f"bench: {mid} {name}")
                rest = config.validation_start == "rest"
                proto = validation_cycle(
                    mrng, ds.imax, duration=config.validation_duration, rest=0.0 if rest else 300.0
                )
                exp = run_experiment(
                    proto,
                    module,
                    eff_flat,
                    mrng,
                    rate=config.validation_rate or config.rate,
                    t0=float(np.round(mrng.uniform(0, 1000), 3)),
                    start="rest" if rest else "steady",
                    **run,
                )
                write_experiment_csv(tmp / mid / name, exp)
        truth = {
            "generator": {
                "tembayes_version": tembayes.__version__,
                "seed": config.seed,
                "rate_Hz": config.rate,
                "validation_rate_Hz": config.validation_rate or config.rate,
                "hold_s": None if config.protocol is not None else config.hold,
                "protocol": None if config.protocol is None else _protocol_json(config.protocol),
                # on plates that hold both faces: the setpoints the staircases ran at
                **({} if identification.setpoints is None else {"plate_setpoints_C": identification.setpoints_C()}),
                "n_validations": config.n_validations,
                "validation_duration_s": config.validation_duration,
                "bench_rig": rig.name,
                "rig": config.rig or {"preset": "reference"},
                "fidelity": config.fidelity,
                "physics": "high-fidelity" if high else config.physics,
                "validation_start": config.validation_start,
                "outlier_shift": config.outlier_shift,
            },
            "tref_C": T_REF - KELVIN,
            "datasheet": ds.to_table(),
            "noise_rms": NOISE,
            "unit_spread_rel": UNIT_SPREAD,
            "effects": config.effects,
            "outlier": config.outlier,
            **truth,
        }
        write_json(tmp / "truth.json", truth)
    return truth
