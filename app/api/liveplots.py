"""viser live plots: uPlot charts fed from the station's ring buffer, radar charts, a 3-D handle.

A publisher thread copies the last :data:`WINDOW_S` seconds out of
:class:`~app.engine.station.LiveBuffer`, thinned to :data:`MAX_POINTS`, at
:data:`PUBLISH_HZ` and pushes them to every connected browser when a new
sample has arrived; the engine loop never waits on a client.
"""

from __future__ import annotations

import concurrent.futures
import logging
import math
import threading
import time
from typing import Any

import numpy as np
from viser._messages import GuiUpdateMessage

from app.api.compare import latest_per_controller
from app.engine.metrics import METRIC_LABELS, METRICS
from app.engine.params import LinearCylinder
from app.engine.safety import SafetyLimits
from app.engine.station import LIVE_COLUMNS, Rig, Station

PUBLISH_HZ = 25.0  # issue 5: 20–30 Hz
WINDOW_S = 10.0
# per series and push. The panel's charts are ≈ 300 px wide; 1000 points made every viewer
# receive 2.4 MB/s (20 viewers: 54 MB/s through the server's event loop).
MAX_POINTS = 400
PUBLISH_TIMEOUT_S = 5.0  # a push not done on viser's loop by then is counted as failed
LOG_EVERY = 1000  # a failure already logged is logged again at every this many failures
HANDLE_STEP_RAD = 1e-3  # the 3-D handle is re-posed (and every viewer re-renders) only on a larger turn
ARC_RADIUS_M = 0.11  # the range of motion is drawn just outside the handle's 9 cm half-length

_COL = {c: i for i, c in enumerate(LIVE_COLUMNS)}
log = logging.getLogger(__name__)
ESTOP_HINT = ("Emergency stop: vent both chambers within one control period, from any state; "
              "latched until cleared on the Station page")
ESTOP_RGB = (139, 0, 0)
"""The E-STOP's colour, the dashboard's dark red: white on viser's "red" read 3.3 : 1 (WCAG 1.4.3 asks 4.5)."""


def angle_words(deg: float) -> str:
    """An angle in the exercise's words ("12° pronation") [deg, positive: pronation]."""
    r = math.floor(abs(deg) + 0.5)  # half up, as the dashboard's Math.round (round() would go to even)
    return "neutral (0°)" if r == 0 else f"{r}° {'pronation' if deg > 0 else 'supination'}"


def range_words(lo: float, hi: float) -> str:
    """The range an exercise reached, as the dashboard words it [deg, positive: pronation]."""
    return f"from {angle_words(lo)} to {angle_words(hi)} ({math.floor(hi - lo + 0.5)}° in all)"


XSCALE: dict[str, Any] = {"x": {"time": False}}  # seconds of rig time, not a calendar date
# [top, right, bottom, left] px around each chart. viser's default, [0, 24, 0, 0], cut the y axis's
# top value in half and the sign off a value wider than the axis: "-0.025" read "0.025".
PADDING: tuple[int, int, int, int] = (10, 24, 0, 14)
# A handle at rest reads exactly 0 rad/s (the encoder's steps), and uPlot ranges an all-zero series
# over 0 … 100: a speed axis to 100 rad/s. Soft limits (uPlot's RangeConfig, mode 1: kept unless the
# data reach past them) hold it at ±1 rad/s at least.
def _soft_y(lo: float, hi: float) -> dict[str, Any]:
    """A y axis that spans at least ``lo`` … ``hi`` and grows past them with the data."""
    return XSCALE | {"y": {"range": {"min": {"soft": lo, "mode": 1, "pad": 0.1},
                                     "max": {"soft": hi, "mode": 1, "pad": 0.1}}}}


SPEED_SCALES = _soft_y(-1.0, 1.0)
# The same for the torque and the pressures, at the dashboard's own spans (±0.2 N·m; from the atmosphere,
# 1 … 1.2 bar abs): an idle rig's sensor noise, ±0.02 N·m and 0.01 bar, had filled each chart's height,
# the pressures under one labelled gridline
TORQUE_SCALES = _soft_y(-0.2, 0.2)
PRESSURE_SCALES = _soft_y(1.0, 1.2)
# and the tracking error, 0 outside an exercise (no target), which uPlot ranged 0 … 100 %
ERROR_SCALES = _soft_y(-10.0, 10.0)


def _rig_charts(rotary: bool) -> tuple[str, tuple[Any, ...], tuple[Any, ...]]:
    """The first chart's title and series and the speed chart's series, for the forearm's handle or, on
    the linear and valve set-ups, a cylinder whose load cell measures a force along its rod."""
    if rotary:
        return ("Interaction torque vs target",
                ({"label": "t [s]"}, _series("T_i [N·m]", "#1f77b4"), _series("target [N·m]", "#d62728", dash=True)),
                ({"label": "t [s]"}, _series("ω [rad/s]", "#ff7f0e")))
    return ("Cylinder force",
            ({"label": "t [s]"}, _series("F [N]", "#1f77b4"), _series("(no target)", "#d62728", dash=True)),
            ({"label": "t [s]"}, _series("v [m/s]", "#ff7f0e")))


def _series(label: str, color: str, dash: bool = False) -> Any:
    s: dict[str, Any] = {"label": label, "stroke": color, "width": 2}
    if dash:
        s["dash"] = [6, 4]
    return s


class LivePlots:
    """The viser server of the station.

    Args:
        station: The station whose live buffer is shown.
        host: Bind address.
        port: viser port.
        store: Optional run store (radar charts compare its stored runs).
    """

    def __init__(self, station: Station, host: str, port: int, store: Any = None) -> None:
        import viser

        self.station = station
        self.store = store
        self.server = viser.ViserServer(host=host, port=port, label="CWRR live", verbose=False)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_run: Any = None
        self._written = -1  # the live buffer's row count at the last push: unchanged means nothing to send
        # what /api/health says of the publisher: a chart that stops moving is then told apart from
        # a publisher that stopped pushing or one whose pushes fail
        self.pushes = 0
        self.errors = 0
        self.last_error = ""
        self._pushed_at = math.nan  # time.monotonic() of the last push [s]
        self._logged: set[str] = set()
        self._theta = math.nan
        # The pages connected now, counted by viser's websocket server: ViserServer.get_clients()
        # adds a page only once its 3-D view has sent a camera, which a browser without WebGL
        # never does, and its charts would then never move.
        self._viewers: set[int] = set()
        ws = self.server._websock_server
        ws.on_client_connect(lambda c: self._viewers.add(c.client_id))
        ws.on_client_disconnect(lambda c: self._viewers.discard(c.client_id))
        gui = self.server.gui
        # The station's state and E-STOP above the charts: a therapist watching them stops the rig
        # here, not in the dashboard's tab. The press is taken from the websocket's own messages, not
        # from the button's on_click: viser runs a button's callbacks only for a page whose 3-D view
        # has sent a camera, which a browser without WebGL never does, and that press would be lost.
        self._state_shown = ""
        self.h_state = gui.add_markdown("Station: …")
        self.h_estop = gui.add_button("E-STOP", color=ESTOP_RGB, hint=ESTOP_HINT)
        ws.register_handler(GuiUpdateMessage, self._on_gui_update)
        z = (np.zeros(2), np.zeros(2))
        title, force, speed = _rig_charts(rotary=True)
        self.h_torque = gui.add_uplot(data=(np.zeros(2), np.zeros(2), np.zeros(2)), series=force, title=title,
                                      aspect=1.5, scales=TORQUE_SCALES, padding=PADDING)
        self.h_press = gui.add_uplot(data=(np.zeros(2),) * 5,
                                     series=({"label": "t [s]"}, _series("P_a [bar]", "#2ca02c"),
                                             _series("P_a ref [bar]", "#2ca02c", dash=True),
                                             _series("P_b [bar]", "#9467bd"),
                                             _series("P_b ref [bar]", "#9467bd", dash=True)),
                                     title="Chamber pressures vs references", aspect=1.5, scales=PRESSURE_SCALES,
                                     padding=PADDING)
        self.h_speed = gui.add_uplot(data=z, series=speed, title="Speed", aspect=2.5, scales=SPEED_SCALES,
                                     padding=PADDING)
        self.h_err = gui.add_uplot(data=z, series=({"label": "t [s]"}, _series("error [% of target]", "#8c564b")),
                                   title="Tracking error", aspect=2.5, scales=ERROR_SCALES, padding=PADDING)
        self.h_metrics = gui.add_markdown("No finished run yet.")
        # drawn once now, hidden until a run has metrics: matplotlib, its fonts and viser's image
        # encoder load here, before the station freezes its heap, not on the publisher thread
        # beside a running loop after the first run (70 000 objects every full collection then
        # scanned, ≈ 50 ms with the lock held)
        self.h_radar = gui.add_image(radar_image({"pid": dict.fromkeys(METRICS, 1.0)}),
                                     label="Metrics radar (this run, and each other controller's latest complete run "
                                           "for the same person, scenario and target)", visible=False)
        self._build_scene()
        self._build_cylinder(LinearCylinder.catalogue("C3").stroke)  # hidden until a linear set-up connects
        self._rig_shown = ("rotary", "")

    def _build_scene(self) -> None:
        """The handle on its shaft, over the range it may turn through.

        The grip turns about the shaft (z) by the measured angle, its thumb
        end (the sphere) along +y at neutral. Under it: the range of motion between the end stops (red),
        the no-action zone inside each (orange), and which way is pronation.
        A label on the shaft gives the measured angle in degrees.
        """
        scene = self.server.scene
        self.h_rotary = scene.add_frame("/rig", show_axes=False)
        scene.add_box("/rig/base", color=(120, 120, 130), dimensions=(0.12, 0.12, 0.06), position=(0.0, 0.0, -0.05))
        self.h_handle = scene.add_frame("/rig/handle", show_axes=False)
        scene.add_box("/rig/handle/grip", color=(30, 110, 200), dimensions=(0.03, 0.18, 0.03))
        scene.add_icosphere("/rig/handle/thumb", radius=0.018, color=(240, 200, 40), position=(0.0, 0.09, 0.0))
        self.h_angle = scene.add_label("/rig/angle", "angle: –", position=(0.0, 0.0, 0.06))
        # the handle is 18 cm long: start the camera close enough to see it turn
        self.server.initial_camera.position = (0.28, -0.32, 0.30)
        self.server.initial_camera.look_at = (0.0, 0.0, 0.0)
        # the rotary rig's limits as the station's safety applies them (a configuration may move them)
        lim = SafetyLimits.for_rig("rotary", **self.station.limit_overrides)
        if lim.rom_deg is None:  # configured without angle checks: no range to draw
            return
        half = math.radians(lim.rom_deg / 2.0)
        soft = half - math.radians(lim.soft_margin_deg)
        r, z = ARC_RADIUS_M, -0.018

        def on_arc(phi: np.ndarray) -> np.ndarray:  # the thumb's direction at angle phi (CCW from +y)
            return np.stack([-r * np.sin(phi), r * np.cos(phi), np.full_like(phi, z)], axis=-1)

        def segments(a: float, b: float) -> np.ndarray:
            pts = on_arc(np.linspace(a, b, max(2, int(abs(b - a) / 0.05) + 1)))
            return np.stack([pts[:-1], pts[1:]], axis=1)

        scene.add_line_segments("/rig/range", segments(-soft, soft), (150, 150, 150), thickness=0.003)
        scene.add_line_segments(
            "/rig/no_action", np.concatenate([segments(soft, half), segments(-half, -soft)]), (240, 150, 30),
            thickness=0.005)
        stops = np.array([[on_arc(np.array([a]))[0] * k for k in (0.85, 1.15)] for a in (-half, half)])
        stops[..., 2] = z
        self.h_stops = scene.add_line_segments("/rig/end_stops", stops, (210, 40, 40), thickness=0.006)
        label_at = on_arc(np.array([min(half, math.pi / 2), -min(half, math.pi / 2)])) * 1.3
        scene.add_label("/rig/pronation", "pronation (+)", position=(*label_at[0, :2], z))
        scene.add_label("/rig/supination", "supination (−)", position=(*label_at[1, :2], z))

    def _build_cylinder(self, stroke: float) -> None:
        """The linear rig: a cylinder along x whose rod extends by the measured position.

        Args:
            stroke: The cylinder's stroke [m]; the piston runs from 0 (retracted) to it.
        """
        scene = self.server.scene
        self._stroke = stroke
        self.h_cylinder = scene.add_frame("/cylinder", show_axes=False, visible=False)
        # the barrel a little see-through, so that the piston is seen inside it
        scene.add_box("/cylinder/barrel", color=(150, 155, 165), dimensions=(stroke + 0.04, 0.05, 0.05),
                      opacity=0.35)
        self.h_rod = scene.add_frame("/cylinder/rod", show_axes=False, position=(-stroke / 2.0, 0.0, 0.0))
        scene.add_box("/cylinder/rod/piston", color=(30, 110, 200), dimensions=(0.012, 0.046, 0.046))
        scene.add_box("/cylinder/rod/bar", color=(200, 200, 210), dimensions=(stroke + 0.05, 0.012, 0.012),
                      position=((stroke + 0.05) / 2.0, 0.0, 0.0))
        self.h_extension = scene.add_label("/cylinder/extension", "extension: –", position=(0.0, 0.0, 0.06))
        self._pos = math.nan

    def _show_rig(self, rig: Rig) -> None:
        """The 3-D view and the first charts' names for the rig the station drives: the forearm's handle,
        or on the linear and valve set-ups a cylinder, whose load cell measures a force along its rod."""
        stroke = rig.stroke  # none on the forearm robot
        rotary = stroke is None
        if stroke is not None:
            self._build_cylinder(stroke)
        self.h_rotary.visible = rotary
        self.h_cylinder.visible = not rotary
        self.h_torque.title, self.h_torque.series, self.h_speed.series = _rig_charts(rotary)
        self._theta = self._pos = math.nan  # re-posed at the next push

    def _on_gui_update(self, _client_id: int, message: GuiUpdateMessage) -> None:
        if message.uuid == self.h_estop._impl.uuid:
            self.station.estop("viser live plots")

    def start(self) -> None:
        """Start publishing."""
        self._thread = threading.Thread(target=self._run, name="cwrr-viser", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop publishing and the viser server."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self.server.stop()

    def _run(self) -> None:
        while not self._stop.wait(1.0 / PUBLISH_HZ):
            self.step()

    def step(self) -> None:
        """One publish, as the thread makes it: a failure is counted and logged, and the next goes on.

        A plotting hiccup must never take the publisher down, nor pass unseen: each kind of
        failure is logged once with its traceback, then every :data:`LOG_EVERY` th failure,
        so one that repeats 25 times a second neither floods the log nor hides in it.
        """
        # on viser's own event loop: a handle's update pulses an asyncio.Event there, and from this
        # thread that pulse raced the loop ("deque mutated during iteration" in Event.set, fresh-clone
        # CI of ed71e5c). The event was then left set with its waiter never woken, and that page's
        # sender waited for good: a page whose charts stopped moving while the run went on
        done: concurrent.futures.Future[None] = concurrent.futures.Future()

        def publish_on_loop() -> None:
            try:
                self.publish()
                done.set_result(None)
            except Exception as e:
                done.set_exception(e)

        try:
            self.server.get_event_loop().call_soon_threadsafe(publish_on_loop)
            done.result(timeout=PUBLISH_TIMEOUT_S)
        except Exception as e:
            self.errors += 1
            what = f"{type(e).__name__}: {e}"[:300]
            self.last_error = what
            if (what not in self._logged and len(self._logged) < 100) or self.errors % LOG_EVERY == 0:
                self._logged.add(what)
                log.exception("live plots: a push failed (%d failed so far)", self.errors)

    def status(self) -> dict[str, Any]:
        """The publisher's counters for ``/api/health``.

        Returns:
            ``viewers`` (pages connected now), ``pushes`` (chart updates sent since start-up),
            ``last_push_age_s`` (time since the last [s]; None before the first), ``errors``
            (publishes that raised) and ``last_error`` (the last one's type and message).
        """
        age = time.monotonic() - self._pushed_at
        return {"viewers": len(self._viewers), "pushes": self.pushes,
                "last_push_age_s": None if math.isnan(age) else round(age, 3), "errors": self.errors,
                "last_error": self.last_error}

    def publish(self) -> None:
        """Push the latest window to every client (one call; the thread calls it at :data:`PUBLISH_HZ`).

        With nobody watching, the charts are left alone: viser would still encode each of them
        for the state it replays to a newcomer, ≈ 1.1 ms of interpreter time per push beside
        the loop (25 pushes a second). A viewer who connects sees the charts as last pushed,
        then fresh ones within one push. A finished run's metrics and radar chart are drawn
        when the run ends whoever watches: drawn later, for a viewer who connects during the
        next exercise, matplotlib would hold the interpreter for tens of milliseconds mid-run.
        """
        state = self.station.state.value
        if state != self._state_shown:  # sent on a change only: an idle station costs the viewers nothing
            self._state_shown = state
            fault = f" ({self.station.fault_message})" if state == "fault" and self.station.fault_message else ""
            self.h_state.content = f"Station: **{state}**{fault}"
        rig = self.station.rig
        if (rig.kind, rig.cylinder) != self._rig_shown:
            self._rig_shown = (rig.kind, rig.cylinder)
            self._show_rig(rig)
        last = self.station.last_run
        if last is not None and last is not self._last_run:
            self._last_run = last
            self._show_run(last)
        if not self._viewers:
            return
        written, r = self.station.live.window(WINDOW_S, MAX_POINTS)
        if written != self._written and len(r) >= 2:
            self._written = written
            t = r[:, _COL["t"]]
            tq, tgt = r[:, _COL["torque"]], r[:, _COL["target"]]
            # Outside an exercise there is no target and no reference (NaN in the buffer); uPlot
            # blanks a whole chart on NaN in a binary series, so those samples show what holds
            # then: no torque target, references equal to the measured pressures, no error.
            idle = ~np.isfinite(tgt)
            tgt = np.where(idle, 0.0, tgt)
            p_a, p_b = r[:, _COL["p_a"]], r[:, _COL["p_b"]]
            ref_a = np.where(idle, p_a, r[:, _COL["p_ref_a"]])
            ref_b = np.where(idle, p_b, r[:, _COL["p_ref_b"]])
            self.h_torque.data = (t, tq, tgt)
            self.h_press.data = (t, p_a, ref_a, p_b, ref_b)
            self.h_speed.data = (t, r[:, _COL["omega"]])
            with np.errstate(invalid="ignore", divide="ignore"):
                err = np.where(np.abs(tgt) > 0, 100.0 * (tgt - tq) / np.abs(tgt), 0.0)
            self.h_err.data = (t, np.nan_to_num(err, nan=0.0, posinf=0.0, neginf=0.0))
            self.pushes += 1
            self._pushed_at = time.monotonic()
            th = float(r[-1, _COL["theta"]])
            if self._rig_shown[0] != "rotary":  # the position column holds the piston's [m]
                if not abs(th - self._pos) < 1e-3:  # a whole millimetre, as the label reads it
                    self._pos = th
                    x = min(max(th, 0.0), self._stroke)
                    self.h_rod.position = (x - self._stroke / 2.0, 0.0, 0.0)
                    self.h_extension.text = f"extension: {1000 * th:.0f} of {1000 * self._stroke:.0f} mm"
            elif not abs(th - self._theta) < HANDLE_STEP_RAD:  # also true for the first (NaN)
                self._theta = th
                self.h_handle.wxyz = (math.cos(th / 2.0), 0.0, 0.0, math.sin(th / 2.0))
                text = f"angle: {math.degrees(th):+.0f}°"
                if text != self.h_angle.text:  # a whole degree: the label is read, not measured off
                    self.h_angle.text = text

    def _show_run(self, last: dict[str, Any]) -> None:
        m = last.get("metrics")
        if not m:
            self.h_metrics.content = f"Run {last.get('run_id')}: {last.get('status')}"
            return
        # named with their units, as the dashboard's result panel names them
        rows = "\n".join(f"| {METRIC_LABELS.get(k, k)} | {'–' if v is None else format(v, '.4g')} |"
                         for k, v in m.items())
        head = f"**Run {last.get('run_id')}** ({last.get('status')})"
        notes = "".join(f"\n\n**Note:** {w}" for w in last.get("warnings") or ())
        reached = last.get("angle_range_deg")
        if reached is not None:
            notes = f"\n\nRange of motion reached: {range_words(*reached)}.{notes}"
        self.h_metrics.content = f"{head}\n\n| metric | value |\n|---|---|\n{rows}{notes}"
        values = self._latest_per_controller(last.get("run_id"))
        if values:
            self.h_radar.image = radar_image(values)
            self.h_radar.visible = True

    def _latest_per_controller(self, run_id: Any) -> dict[str, dict[str, float]]:
        if self.store is None or run_id is None:
            return {}
        return latest_per_controller(self.store, int(run_id))


def radar_image(values: dict[str, dict[str, float]]) -> np.ndarray:
    """The thesis's radar chart rendered to an RGB array (uPlot has no polar plot)."""
    from app.thesis_bench import _plt, radar_figure

    plt = _plt()
    # drawn for viser's side panel (about 300 px wide), where the report's 6.4 in figure came out
    # with 4 px labels; twice the pixels it is shown at, so it stays sharp on a HiDPI screen. The
    # image's label above it says what it compares, so it has no title of its own
    fig = radar_figure("", values, figsize=(3.3, 3.5), fontsize=7.0)
    fig.set_dpi(200)
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return img
