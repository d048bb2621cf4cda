"""Physical constants of air and the ISO 6358 reference state (SI units).

The thesis writes pressures in bar absolute and commands in volts; inside the
engine everything is SI (Pa, m, kg, s, K, rad) and bar/volts appear only at the
edges (commands, logs, API).
"""

from __future__ import annotations

R_AIR: float = 287.05
"""Specific gas constant of dry air [J/(kg·K)]."""
CP_AIR: float = 1005.0
"""Specific heat at constant pressure [J/(kg·K)]."""
CV_AIR: float = CP_AIR - R_AIR
"""Specific heat at constant volume [J/(kg·K)]."""
GAMMA_AIR: float = CP_AIR / CV_AIR
"""Ratio of specific heats [-]."""
T_ATM: float = 293.15
"""Ambient (and supply) temperature [K]; thesis 3.2.5 assumes T_a = T_u = T_atm."""
P_ATM: float = 1.01325e5
"""Atmospheric pressure [Pa]. The thesis rounds it to 1 bar; we keep the standard value."""
RHO0_ISO: float = 1.185
"""ISO 6358 reference density [kg/m³] (T0 = 293.15 K, p0 = 1 bar, 65 % RH)."""
T0_ISO: float = 293.15
"""ISO 6358 reference temperature [K]."""
BAR: float = 1.0e5
"""Pascal per bar."""
P_ATM_BAR: float = P_ATM / BAR
"""The standard atmosphere [bar abs]: the default wherever a lab has not said its own."""
SONIC_CONDUCTANCE_UNIT: float = 1.0e-3 / 1.0e5
"""One l/(s·bar) expressed in m³/(s·Pa), the unit used by FESTO datasheets for C."""
