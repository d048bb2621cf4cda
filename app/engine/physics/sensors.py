"""Sensor models as the Q8-USB DAQ sees them (thesis Table 3.2).

Pressure sensors: analog 0–5 V over 0–10 bar, 16-bit ADC on ±10 V, white
noise, optional gain error and offset. Torque: TS70a ±10 N·m through a ±10 V
amplifier (1 N·m/V), saturating. Encoder: 1024-line quadrature (4096
counts/rev); speed is the backward difference of the quantised angle through
a first-order low-pass, as the thesis derives speed ("derivative, then a
transfer-function filter", 3.2.4).
"""

from __future__ import annotations

import math
from collections import namedtuple
from typing import Any

import numpy as np
from numba import njit

from app.engine.constants import BAR
from app.engine.params import PlantParams
from app.engine.physics.jit import NO_REFCOUNT

SensorConst: Any = namedtuple(
    "SensorConst",
    [
        "p_noise", "p_fs", "p_span", "gain_a", "gain_b", "bias_a", "bias_b",
        "t_noise", "t_range", "t_gain", "t_bias", "enc_res", "adc_lsb", "speed_wc", "rotary", "ps_at_prv_a",
    ],
)

# sensor state: previous quantised angle, filtered speed, initialised flag
S_PREV, S_WF, S_INIT = 0, 1, 2
NS = 3
# measurement vector: p_a, p_b, p_s [bar abs], pos [rad|m], vel [rad/s|m/s], torque [N·m|N]
M_PA, M_PB, M_PS, M_POS, M_VEL, M_TQ = 0, 1, 2, 3, 4, 5
NM = 6


def build_sensor_const(p: PlantParams) -> Any:
    """Sensor constants of a rig (:func:`measure` takes the time between samples itself)."""
    s = p.sensors
    bias = p.effects.sensor_bias
    enc = 2.0 * math.pi / s.encoder_counts if p.rig == "rotary" else 1.0e-5  # ESKON linear encoder: 0.01 mm
    return SensorConst(
        p_noise=s.pressure_noise_bar, p_fs=s.pressure_full_scale_bar, p_span=s.pressure_span_v,
        gain_a=s.pressure_gain_a, gain_b=s.pressure_gain_b,
        bias_a=bias.p_a_bar if bias else 0.0, bias_b=bias.p_b_bar if bias else 0.0,
        t_noise=s.torque_noise_nm, t_range=s.torque_range_nm, t_gain=s.torque_gain,
        t_bias=bias.torque_nm if bias else 0.0,
        enc_res=enc, adc_lsb=2.0 * s.adc_range_v / (1 << s.adc_bits),
        speed_wc=2.0 * math.pi * s.speed_filter_hz, rotary=p.rig == "rotary",
        ps_at_prv_a=s.supply_tap == "prv_a",
    )


@njit(cache=True, inline="always", error_model="numpy", **NO_REFCOUNT)
def _quant(v: float, lsb: float) -> float:
    return math.floor(v / lsb + 0.5) * lsb


@njit(cache=True, error_model="numpy", **NO_REFCOUNT)
def measure(
    pa: float, pb: float, ps: float, pos: float, ti: float, sc: Any, noise: np.ndarray, st: np.ndarray, dt: float,
    out: np.ndarray,
) -> None:
    """Sample every sensor once.

    Args:
        pa: True chamber-a pressure [Pa abs].
        pb: True chamber-b pressure [Pa abs].
        ps: True supply pressure [Pa abs].
        pos: True position [rad or m].
        ti: True interaction torque [N·m] (force [N] on the linear rig).
        sc: Sensor constants.
        noise: Four standard-normal draws (p_a, p_b, p_s, torque).
        st: Sensor state (speed estimator), updated.
        dt: Time since the previous sample [s]: the period when the sample is
            on time, longer after a late one (the speed estimate divides the
            encoder's step by it; dividing by the period reported a 65 ms
            stall's 0.5 rad/s as 3.6 rad/s).
        out: Measurement vector (NM), written.
    """
    vpb = sc.p_span / sc.p_fs  # volts per bar
    pa_b = ((pa / BAR) * sc.gain_a + sc.bias_a + sc.p_noise * noise[0]) * vpb
    pb_b = ((pb / BAR) * sc.gain_b + sc.bias_b + sc.p_noise * noise[1]) * vpb
    ps_b = ((ps / BAR) + sc.p_noise * noise[2]) * vpb
    out[M_PA] = _quant(pa_b, sc.adc_lsb) / vpb
    out[M_PB] = _quant(pb_b, sc.adc_lsb) / vpb
    out[M_PS] = _quant(ps_b, sc.adc_lsb) / vpb
    tq = ti * sc.t_gain + sc.t_bias + sc.t_noise * noise[3]
    tq = min(max(tq, -sc.t_range), sc.t_range)
    out[M_TQ] = _quant(tq * 10.0 / sc.t_range, sc.adc_lsb) * sc.t_range / 10.0
    q = math.floor(pos / sc.enc_res + 0.5) * sc.enc_res
    out[M_POS] = q
    if st[S_INIT] < 0.5:
        st[S_PREV] = q
        st[S_WF] = 0.0
        st[S_INIT] = 1.0
    raw = (q - st[S_PREV]) / dt
    st[S_WF] += (1.0 - math.exp(-sc.speed_wc * dt)) * (raw - st[S_WF])
    st[S_PREV] = q
    out[M_VEL] = st[S_WF]
