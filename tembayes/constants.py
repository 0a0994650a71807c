"""Names and numbers fixed by the data contract (``docs/data-format.md``, ``docs/outputs.md``).

Everything inside tembayes is SI: temperatures in kelvin, times in seconds,
currents in amperes, voltages in volts.  The CSV's degrees Celsius appear only
at the edges (``tembayes.data``).
"""

#: Offset between degrees Celsius and kelvin [K].
KELVIN = 273.15

#: Reference temperature of the linear laws, 25 degC [K].
T_REF = 25.0 + KELVIN
#: The reference rig's sampling rate [Hz]: the bench's and the design's unless told.
RATE_HZ = 5.0

#: The columns every experiment CSV carries before its rig's temperature columns.
BASE_COLUMNS = ("time_s", "current_A", "voltage_V")

#: Law parameter names, in the order used by every parameter vector.
LAW_PARAMETERS = ("R0_ohm", "R1_ohm_per_K", "S0_V_per_K", "S1_V_per_K2")

#: Law parameters plus the module's thermal conductance.
MODULE_PARAMETERS = LAW_PARAMETERS + ("K_W_per_K",)

#: The effect catalogue (docs/outputs.md, 'Effect catalogue').
EFFECTS = (
    "k_temperature",
    "thomson",
    "sensor_lag",
    "contact_resistance",
    "joule_split",
    "current_offset",
    "quadratic_laws",
    "ambient_leak",
)
