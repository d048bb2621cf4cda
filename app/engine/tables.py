"""Golden tables from the thesis and datasheets, each with its source.

These are data, not code: the simulator and the controllers read them through
:mod:`app.engine.params`.
"""

from __future__ import annotations

import numpy as np

# Thesis Table 4.2 (SPEC §2): Stribeck parameters of the FESTO DRVS-32-270-P
# vane cylinder against working pressure. CW values keep the thesis's sign
# convention (T_s, T_c, ω_s negative; B positive).
FRICTION_PW_BAR = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
FRICTION_TS_CCW = np.array([1.196, 1.223, 1.296, 1.334, 1.362, 1.320])
FRICTION_TC_CCW = np.array([0.528, 0.619, 0.627, 0.610, 0.592, 0.571])
FRICTION_WS_CCW = np.array([0.537, 0.546, 0.924, 0.774, 0.869, 0.974])
FRICTION_B_CCW = np.array([0.097, 0.099, 0.150, 0.163, 0.167, 0.186])
FRICTION_TS_CW = np.array([-1.199, -1.221, -1.316, -1.400, -1.410, -1.370])
FRICTION_TC_CW = np.array([-0.654, -0.702, -0.703, -0.634, -0.660, -0.686])
FRICTION_WS_CW = np.array([-0.550, -0.351, -1.000, -0.366, -1.000, -1.000])
FRICTION_B_CW = np.array([0.085, 0.089, 0.123, 0.135, 0.153, 0.165])

# Thesis Tables 4.5–4.6 (SPEC §2), automated method: (extension, retraction).
LINEAR_FRICTION = {
    "C1": {"Fs": (4.714, -4.918), "Fc": (1.958, -1.954), "vs": (0.062, -0.0708), "B": (19.99, 20.635)},
    "C2": {"Fs": (4.656, -4.944), "Fc": (1.626, -2.032), "vs": (0.0511, -0.0544), "B": (20.302, 20.923)},
    "C3": {"Fs": (14.437, -14.536), "Fc": (4.479, -4.017), "vs": (0.004, -0.005), "B": (45.796, 47.283)},
}

# FESTO MPYE-5 spool characteristic (Y. Zhu PhD 2006, Table 2-2, via
# refdata/valve_curves/valve_data.csv): command above 5 V [V] vs orifice area
# [mm²]. Only the shape (area fraction vs spool displacement) is used; the
# 1/8" valve's capacity comes from its datasheet C (Table 3.3).
MPYE_DISPLACEMENT_V = np.array(
    [0.0, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875, 1.0, 1.125, 1.25, 1.375, 1.5, 1.625, 1.75,
     1.875, 2.0, 2.125, 2.25, 2.375, 2.5, 2.625, 2.75, 2.875, 3.0, 3.125, 3.25, 3.375, 3.5, 3.625,
     3.75, 3.875, 4.0, 4.125, 4.25, 4.375, 4.5, 4.625, 4.75, 4.875]
)
MPYE_AREA_MM2 = np.array(
    [0.0, 0.0418, 0.1175, 0.2141, 0.3270, 0.4533, 0.5909, 0.7385, 0.8946, 1.0582, 1.2284, 1.4043,
     1.5853, 1.7707, 1.9598, 2.1521, 2.3470, 2.5439, 2.7423, 2.9417, 3.1416, 3.3415, 3.5409, 3.7393,
     3.9362, 4.1310, 4.3233, 4.5125, 4.6978, 4.8788, 5.0548, 5.2250, 5.3886, 5.5447, 5.6922, 5.8299,
     5.9562, 6.0691, 6.1657, 6.2413]
)
MPYE_AREA_FRACTION = MPYE_AREA_MM2 / MPYE_AREA_MM2[-1]

# Thesis Table 4.1 subsonic index ε(u) at P_s = 5 bar (dimensionless, so usable
# as is, unlike α1/α2 whose magnitudes fit no unit system — SPEC §3).
TABLE41_U_FILL = np.array([4.5, 4.6, 4.7, 4.8, 4.9, 5.0, 5.1, 5.2, 5.3, 5.4, 5.5])
TABLE41_EPS_FILL = np.array([0.500, 0.700, 0.750, 0.592, 0.654, 0.816, 0.950, 1.04, 0.900, 1.288, 1.020])
TABLE41_U_EXH = np.array([4.7, 4.8, 4.9, 5.0, 5.1, 5.2, 5.3, 5.4, 5.5, 5.6, 5.7, 5.8, 5.9])
TABLE41_EPS_EXH = np.array(
    [1.735, 1.344, 1.550, 1.484, 1.648, 1.646, 1.462, 1.649, 1.596, 0.932, 1.010, 1.126, 1.016]
)

# Thesis Eq 4.2 / 4.3: supply-pressure coefficients k(P_s), P_s in bar (abs),
# highest power first (numpy.polyval order). k(5 bar) ≈ 1 for both, i.e. they
# normalise to the P_s = 5 bar identification.
K_FILL_POLY = np.array([-0.0106, 0.153, -0.749, 2.231])
K_EXH_POLY = np.array([-0.0437, 0.879, -6.381, 19.496, -19.5])
