"""Issue 5: the dashboard's main flow in headless Chromium (Debian's /usr/bin/chromium, driven by Playwright).

A therapist's walk: the guided form refuses an out-of-range value with the
thesis GUI's message, connect, start a scenario and see live torque and
pressure arrive within 2 s, stop, read the metrics, export the run, open the
viser live plots. Screenshots go to ``docs/screenshots/`` (the README shows
them), so each test run refreshes the pictures from what the browser saw.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import ServedStation, free_port

CHROMIUM = "/usr/bin/chromium"
SHOTS = Path(__file__).resolve().parent.parent / "docs" / "screenshots"
pytestmark = [pytest.mark.slow, pytest.mark.serial,
              pytest.mark.skipif(not os.path.exists(CHROMIUM), reason="Debian chromium not installed "
                                 "(./dev test installs it where apt and root are available)")]


AUDIT_TAGS = ["wcag2a", "wcag2aa", "wcag21a", "wcag21aa", "wcag22aa"]
"""axe-core's tags for WCAG 2.2's levels A and AA (its best-practice rules are advice, and left out)."""
VISER_OWN = [".mantine-ActionIcon-root", "a > img", "[data-dock-minimize]"]
"""viser's own chrome, which the station does not draw: its panel's icon buttons, which have no name,
its logo's link, whose image has no text, and its panel's 18-px drag handle (viser 1.1.x)."""


def _accessible(page: Any, where: str, exclude: list[str] | None = None) -> None:
    """axe-core finds no WCAG 2.2 A/AA violation on the page as it stands.

    axe-core (Deque's engine, bundled by axe-playwright-python) checks what a machine can: text
    contrast (4.5 : 1 for small text), a name on every control, image and form field, landmarks, valid
    ARIA, targets a pointer can hit. Checked at each state the walks stop at, not only on the first
    load: a result, a chart's legend and a running state put new text on the page.

    Args:
        page: The Playwright page.
        where: What the page shows, for the message.
        exclude: CSS selectors of parts the station does not draw (viser's own chrome).
    """
    from axe_playwright_python.sync_playwright import Axe

    context = {"exclude": [[sel] for sel in exclude]} if exclude else None
    res = Axe().run(page, context=context, options={"runOnly": {"type": "tag", "values": AUDIT_TAGS},
                                                    "resultTypes": ["violations"]})
    found = [f"{v['id']} ({v['impact']}): {v['help']}: "
             + "; ".join(f"{n['target']} {' '.join((n.get('failureSummary') or '').split())[:160]}"
                         for n in v["nodes"][:5])
             for v in res.response["violations"]]
    assert not found, f"{where}:\n" + "\n".join(found)


@pytest.fixture(scope="module")
def station(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    # the README's `cwrr serve` in a process of its own, as a therapist's browser meets it: in a thread
    # of this process the paced loop shared the interpreter lock with Playwright's driver
    vport = free_port()
    srv = ServedStation(tmp_path_factory.mktemp("browser"), viser_port=vport, CWRR_AUTO_CONNECT="false")
    try:
        yield srv.url, f"http://127.0.0.1:{vport}"
    finally:
        srv.stop()


@pytest.fixture(autouse=True)
def _report_the_engine(station: tuple[str, str]) -> Iterator[None]:
    """Print the station's state and safety fault after each test (shown when one fails)."""
    import json
    import urllib.request

    yield
    with urllib.request.urlopen(station[0] + "/api/engine", timeout=10) as r:
        st = json.loads(r.read())
    print("engine after the test:", st["state"], st.get("fault"), (st.get("safety") or {}).get("fault"))


def _call(base: str, method: str, path: str, body: dict[str, object] | None = None) -> dict[str, Any]:
    """One JSON request to the station (as a script would make it, beside the browser)."""
    import json
    import urllib.request

    req = urllib.request.Request(base + path, method=method, data=json.dumps(body or {}).encode(),
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=10) as r:
        out: dict[str, Any] = json.loads(r.read())
        return out


def _connected_and_idle(base: str) -> None:
    """Bring the station to idle, whatever an earlier test left it doing."""
    state = _call(base, "GET", "/api/engine")["state"]
    if state in ("running", "identifying"):
        _call(base, "POST", "/api/engine/stop")
        deadline = time.monotonic() + 30
        while (state := _call(base, "GET", "/api/engine")["state"]) not in ("idle", "fault"):
            assert time.monotonic() < deadline, state
            time.sleep(0.1)
    if state == "fault":
        _call(base, "POST", "/api/engine/clear")
        state = "disconnected"
    if state == "disconnected":
        _call(base, "POST", "/api/engine/connect")


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=[
            "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
            "--disable-component-update", "--disable-sync"])
        yield b
        b.close()


def test_a_therapist_walks_the_main_flow(station: tuple[str, str], browser: object, tmp_path: Path) -> None:
    import json
    import urllib.request

    from playwright.sync_api import Browser, expect

    assert isinstance(browser, Browser)
    base, _viser = station
    SHOTS.mkdir(parents=True, exist_ok=True)
    # a slower exercise shape (a quarter of the default 0.3 rad/s: ≈ 34 s instead of ≈ 9.5 s), stored the
    # way a researcher would, so that STOP lands mid-run however long the screenshots take on a loaded
    # machine (on a fresh clone's CI the default run once ended on its own before STOP was pressed, and
    # half the default once did beside a suite run); STOP ends it, so the test takes no longer
    req = urllib.request.Request(base + "/api/params", method="POST", headers={"Content-Type": "application/json"},
                                 data=json.dumps({"kind": "workout", "name": "slow and steady",
                                                  "values": {"speed": 0.075}}).encode())
    with urllib.request.urlopen(req, timeout=10) as r:
        shape_id = json.loads(r.read())["id"]
    page = browser.new_page(viewport={"width": 1400, "height": 1000}, accept_downloads=True)
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(base)
    expect(page.locator("#state")).to_have_text("disconnected")
    for action in ("start", "stop", "disconnect"):  # buttons follow the state machine
        expect(page.locator(f"[data-action={action}]").first).to_be_disabled()
    # a screen reader finds the live charts as pictures with a name, not as unnamed canvases
    expect(page.get_by_role("img", name="Live chart: interaction torque")).to_be_visible()
    expect(page.get_by_role("img", name="Live chart: chamber pressures")).to_be_visible()

    # guided entry (thesis Appendix 1): an impossible range of motion is refused with the GUI's words
    rom = page.locator("#f-rom_deg")
    rom.fill("400")
    rom.dispatch_event("change")
    expect(page.locator("#ident-msg")).to_contain_text("Please enter a reasonable value")
    expect(page.locator("#ident-msg")).to_have_class("msg bad")
    expect(rom).not_to_have_class("valid")
    expect(page.locator("#f-vane_area_mm2")).to_be_disabled()  # fields unlock in order
    page.screenshot(path=str(SHOTS / "1-refused-value.png"))
    _accessible(page, "1-refused-value")
    for name, value in (("rom_deg", 270), ("vane_area_mm2", 855), ("radius_mm", 23), ("ns", 30), ("nd", 30),
                        ("pw_bar", 3)):
        f = page.locator(f"#f-{name}")
        expect(f).to_be_enabled()
        f.fill(str(value))
        f.dispatch_event("change")
        expect(f).to_have_class("valid")
    expect(page.locator("#ident-msg")).to_have_class("msg ok")

    page.click("[data-action=connect]")
    # the first connect of a fresh install compiles the simulator's kernels (numba cache) before the loop starts
    expect(page.locator("#state")).to_have_text("idle", timeout=60000)
    expect(page.locator("#estimate")).to_be_enabled()  # the form is complete and the rig is idle
    # the GUI's "please connect to proceed", once connected, says what to press instead
    expect(page.locator("#ident-msg")).to_have_text(
        "Parameters has been defined successfully, please connect to proceed. The station is connected: Run "
        "identification starts the experiments.")
    # the viser live plots and 3-D handle are one click away; open them before the exercise
    link = page.locator("#viser-link")
    expect(link).to_be_visible()
    viser = browser.new_page(viewport={"width": 1400, "height": 900})
    viser.goto(link.get_attribute("href") or "")
    viser.wait_for_selector("canvas", timeout=20000)
    page.bring_to_front()
    page.select_option("#scenario", "SC-1")
    page.select_option("#controller", "pid")
    page.fill("#target", "1.2")
    # a name where the pseudonym goes is refused in words, not as the API's pattern, and the field as labelled
    page.fill("#person", "Jane Doe")
    page.click("#new-session")
    expect(page.locator("#session-msg")).to_have_text(
        "Person id: 'Jane Doe' holds a space: a person id is a pseudonym such as P-007, made of letters, digits, "
        "'-', '_' and '.' (no names)")
    page.click("#start")
    expect(page.locator("#start-msg")).to_contain_text("Person id: 'Jane Doe' holds a space")
    assert page.locator("#state").inner_text() == "idle"
    page.fill("#person", " P-007 ")  # the spaces around it are the typing's, not the id's
    page.locator("#person").dispatch_event("change")
    # a therapy session for the person, which the run is stored under
    page.fill("#session-notes", "left arm, week 3")
    page.click("#new-session")
    expect(page.locator("#session-msg")).to_contain_text("opened for P-007")
    expect(page.locator("#session option:checked")).to_contain_text("0 runs · left arm, week 3")
    session_id = int(page.locator("#session").input_value())
    page.select_option("#workout-set", str(shape_id))
    t0 = time.monotonic()
    page.click("#start")
    expect(page.locator("#state")).to_have_text("running")
    expect(page.locator("#stop")).to_be_enabled()
    page.wait_for_function("Number(document.getElementById('c-torque').dataset.samples || 0) > 0", timeout=2000)
    assert time.monotonic() - t0 < 2.0  # issue 5: live torque and pressure within 2 s of Start
    page.wait_for_timeout(5000)  # pressurise, engage, converge: enough of the window to score
    page.screenshot(path=str(SHOTS / "2-live-exercise.png"))
    _accessible(page, "2-live-exercise")
    # the handle's angle, live, between the end stops (±135°) and inside their no-action zones (10° each)
    expect(page.locator("#handle-gauge")).to_be_visible()
    # read at one instant: the next poll moves the mark (two reads that straddled a poll, 0.16 % of the bar
    # apart, failed once in CI)
    deg, x, said = page.evaluate("""() => { const m = document.getElementById('handle-mark');
        return [Number(m.dataset.deg), parseFloat(m.getAttribute('x')),
                document.getElementById('handle-angle').textContent]; }""")
    assert 5.0 < deg < 135.0, deg  # SC-1's +1.2 N·m turns the handle towards pronation
    assert x == pytest.approx(50 + 50 * deg / 135, abs=0.01)
    # (data-deg keeps two decimals of the angle the text rounds)
    assert said in {f"Handle: {math.floor(deg + 0.5 + e)}° pronation" for e in (-0.01, 0.01)}, (said, deg)
    zones = page.locator("#handle-svg rect[fill='#f0a040']")
    assert [float((zones.nth(k).get_attribute("width") or "").rstrip("%")) for k in (0, 1)] == \
        pytest.approx([100 * 10 / 270] * 2)
    # the charts' gridlines sit at round values (1, 2, 2.5 or 5 × 10^k apart), not at the span cut in four
    for chart in ("#c-torque", "#c-press"):
        ticks = [float(v) for v in (page.locator(chart).get_attribute("data-ticks") or "").split()]
        steps = np.diff(ticks)
        assert len(ticks) >= 3 and np.allclose(steps, steps[0]), (chart, ticks)
        mantissa = steps[0] / 10 ** math.floor(math.log10(steps[0]) + 1e-9)
        assert any(math.isclose(mantissa, m) for m in (1, 2, 2.5, 5)), (chart, ticks)
        assert all(math.isclose(t / steps[0], round(t / steps[0]), abs_tol=1e-6) for t in ticks), (chart, ticks)
    assert page.evaluate("niceTicks(-0.32, 1.40)") == {"ticks": [0, 0.5, 1], "digits": 1}
    # a background tab is throttled: its charts had drawn only up to 4 s of a 9 s run, or not at all, when
    # captured from behind the dashboard; in front for a moment it draws what it has been sent
    viser.bring_to_front()
    viser.wait_for_timeout(700)
    # the four charts hold the run and keep drawing it: their canvases change as samples arrive (the
    # publisher sends nothing when no new sample came, so a frozen chart would read the same twice)
    drawn = "() => [...document.querySelectorAll('.uplot canvas')].map(c => c.toDataURL())"
    before = viser.evaluate(drawn)
    assert len(before) == 4, len(before)
    # each redrawn within 10 s (25 pushes a second; a loaded machine had left one unchanged after 600 ms).
    # viser applies what it receives in its 3-D view's frame loop (MessageHandler.tsx: useFrame), so a
    # page whose frames stall draws nothing new: on a fresh clone's CI, 2 of about 60 runs had left a
    # chart unchanged for 5 s, which 30 runs here, 12 of them beside a busy core, never did. A chart
    # that does not move then is named, with whether the page was visible and drew frames. That is not
    # the whole story: one more CI failure (forty-fifth session) had all four unchanged for 10 s with the
    # page visible, 59 frames a second and the run going on, so no update reached the charts (open). The
    # station's /api/health now says whether its publisher counted the page, pushed and failed: named too
    try:
        viser.wait_for_function("b => [...document.querySelectorAll('.uplot canvas')].every((c, i) => "
                                "c.toDataURL() !== b[i])", arg=before, timeout=10000)
    except Exception:
        frames = viser.evaluate("""() => new Promise(done => { let n = 0; const t0 = performance.now();
            const f = () => { n += 1; if (performance.now() - t0 < 1000) requestAnimationFrame(f); else done(n); };
            requestAnimationFrame(f); })""")
        after = viser.evaluate(drawn)
        raise AssertionError(f"charts {[i for i in range(4) if after[i] == before[i]]} (torque, pressures, speed, "
                             f"error) unchanged for 10 s; the page "
                             f"{viser.evaluate('document.visibilityState')}, {frames} frames in the next second; "
                             f"the station {_call(base, 'GET', '/api/engine')['state']}, its publisher "
                             f"{_call(base, 'GET', '/api/health')['live_plots']}") from None
    # headless Chromium draws WebGL in software and viser says so in a toast, which a lab's screen with
    # a GPU would not show: closed for the picture
    for close in viser.locator(".mantine-Notification-closeButton").all():
        close.click()
    # the station's state and an E-STOP above the charts (its press: tests/test_api.py, from a page
    # without WebGL, whose button callbacks viser itself would drop)
    expect(viser.locator("p", has_text="Station:")).to_have_text("Station: running")
    expect(viser.get_by_role("button", name="E-STOP")).to_be_visible()
    viser.screenshot(path=str(SHOTS / "4-viser-live-plots.png"))
    _accessible(viser, "4-viser-live-plots", exclude=VISER_OWN)
    viser.close()
    page.bring_to_front()
    expect(page.locator("#state")).to_have_text("running")  # still exercising when STOP is pressed
    page.fill("#session-notes", "left arm, week 3; tired towards the end")  # noted while exercising

    page.click("#stop")
    expect(page.locator("#state")).to_have_text("idle")
    expect(page.locator("#metrics")).to_be_visible(timeout=5000)
    # "Exercise started (run N)." under Start is not left there once it has ended
    expect(page.locator("#start-msg")).to_have_text(re.compile(r"^Exercise \d+ was stopped: its result is under "
                                                                r"Last result\.$"))
    expect(page.locator("#last")).to_contain_text("stopped")
    # what the exercise was, as the history names it, not its number alone
    expect(page.locator("#last p").first).to_contain_text("(SC-1 · pid · 1.2 N·m, P-007): stopped")
    mae = float(page.locator("#metrics tr").first.locator("td").nth(1).inner_text())
    assert 0.0 < mae < 0.5, mae  # scored over the part of the window reached (live SC-1 PID: ≈ 0.13 N·m)
    row = page.locator("#runs tbody tr").first
    expect(row).to_contain_text("P-007")
    # the kind in plain words; the API's code, which /api/runs?kind= takes, in the tooltip
    expect(row.locator("td").nth(1)).to_have_text("Exercise")
    expect(row.locator("td").nth(1)).to_have_attribute("title", "kind=workout")
    run_id = int(row.get_attribute("data-run") or 0)
    # nothing yet to set the stopped PID run beside (tests/test_api.py has runs that are; the radar is
    # drawn in test_an_exercise_is_drawn_beside_the_other_controllers_on_a_radar): said, and what would be
    expect(page.locator(f"#last-compare-{run_id}")).to_have_text(
        "No complete SC-1 at 1.2 N·m for P-007 yet with Default or Cascade fuzzy adaptive PID: such an "
        "exercise, run to its end, is drawn here beside this one.")
    # the whole exercise stays on the page once the live chart has moved on: torque against target,
    # from the stored run, decimated to what the chart can draw
    trace = page.locator("#c-trace")
    expect(trace).to_be_visible(timeout=5000)
    expect(trace).to_have_attribute("data-run", str(run_id))
    with urllib.request.urlopen(f"{base}/api/runs/{run_id}/series?every=10000", timeout=10) as r:
        stored = json.loads(r.read())["rows_total"]
    every = -(-stored // 1800)
    assert int(trace.get_attribute("data-samples") or 0) == len(range(0, stored, every)), stored
    # the scored window it tints is the stored result's, moved onto the log's clock
    with urllib.request.urlopen(f"{base}/api/runs/{run_id}", timeout=10) as r:
        res = json.loads(r.read())["result"]
    tinted = [float(x) for x in (trace.get_attribute("data-window") or "").split(",")]
    assert tinted == pytest.approx([x + res["program_start_s"] for x in res["window_s"]], abs=1e-3), (tinted, res)
    # and beneath it the chambers' pressures against what their regulators were commanded, the same rows
    press = page.locator("#c-trace-press")
    expect(press).to_be_visible()
    expect(press).to_have_attribute("data-run", str(run_id))
    assert press.get_attribute("data-samples") == trace.get_attribute("data-samples")
    assert float(press.get_attribute("data-atm") or "nan") == pytest.approx(1.01325)
    with urllib.request.urlopen(f"{base}/api/sessions/{session_id}", timeout=10) as r:
        assert json.loads(r.read())["runs"] == [run_id]
    expect(page.locator("#session option:checked")).to_contain_text(" · 1 run · left arm")
    # the run's end recounted the session's runs without wiping the notes being typed; saved, they are stored
    expect(page.locator("#session-notes")).to_have_value("left arm, week 3; tired towards the end")
    page.click("#save-session-notes")
    expect(page.locator("#session-msg")).to_contain_text(f"Notes of session {session_id} saved")
    with urllib.request.urlopen(f"{base}/api/sessions/{session_id}", timeout=10) as r:
        assert json.loads(r.read())["notes"] == "left arm, week 3; tired towards the end"
    expect(page.locator("#session option:checked")).to_contain_text("tired towards")
    # and the run's own notes, under its result
    expect(page.locator("#save-run-notes")).to_have_text(f"Save notes on run {run_id}")
    page.fill("#run-notes", "stopped: asked for a break")
    page.click("#save-run-notes")
    expect(page.locator("#run-notes-msg")).to_have_text(f"Notes on run {run_id} saved.")
    with urllib.request.urlopen(f"{base}/api/runs/{run_id}", timeout=10) as r:
        assert json.loads(r.read())["notes"] == "stopped: asked for a break"
    page.evaluate("window.scrollTo(0, 0)")  # the sticky header is drawn where the page is scrolled to
    page.screenshot(path=str(SHOTS / "3-metrics-and-history.png"), full_page=True)
    _accessible(page, "3-metrics-and-history")

    with page.expect_download() as dl:
        row.get_by_text("CSV").click()
    text = Path(dl.value.path()).read_text()
    rows = list(csv.reader(io.StringIO(text)))
    assert rows[0] == ["t", "z_a", "z_b", "u_a", "u_b", "p_a", "p_b", "p_s", "theta", "omega", "torque"]
    assert len(rows) > 200 * 5  # > 5 s at 200 Hz
    with page.expect_download() as dl:
        row.get_by_text("PARQUET").click()
    assert Path(dl.value.path()).read_bytes()[:4] == b"PAR1"
    # the history narrows to one person: nobody else's runs, and a plain "none" for a person without any
    page.fill("#hist-person", "P-008")
    page.locator("#hist-person").dispatch_event("change")
    expect(page.locator("#hist-msg")).to_have_text("no runs of P-008")
    expect(page.locator("#runs tbody tr")).to_have_count(0)
    page.fill("#hist-person", "P-007")
    page.locator("#hist-person").dispatch_event("change")
    expect(page.locator("#hist-msg")).to_have_text("runs 1–1 of P-007")
    expect(page.locator("#runs tbody tr").first).to_contain_text("P-007")
    expect(page.locator("#hist-older")).to_be_disabled()
    # the person's progress: complete exercises only (this one was stopped), then three stored ones as the
    # store would answer them (served by the page's network layer, so the drawing is what is tested)
    expect(page.locator("#progress-chart")).to_be_hidden()
    fake = [{"id": 9 - k, "kind": "workout", "status": "complete", "started": 1.8e9 - 86400 * k, "ended": None,
             "spec": {"scenario": sc, "controller": "fuzzy", "target_nm": 1.2}, "metrics": {"mae": mae},
             "result": reached, "person": "P-007", "notes": "", "session_id": None, "has_series": False}
            for k, (sc, mae, reached) in enumerate((("SC-1", 0.06, {"angle_range_deg": [-12.4, 61.0]}),
                                                     ("SC-2", 0.09, None),  # stored before ranges were
                                                     ("SC-1", 0.12, {"angle_range_deg": [0.2, 44.6]})))]
    page.route("**/api/runs?kind=workout*", lambda route: route.fulfill(json=fake))
    page.locator("#hist-person").dispatch_event("change")
    expect(page.locator("#progress-chart")).to_contain_text("Progress of P-007")
    expect(page.locator("#progress-chart circle")).to_have_count(3)
    titles = page.locator("#progress-chart circle title").all_text_contents()
    assert titles[0].startswith("run 7,") and "SC-1 · fuzzy · 1.2 N·m — MAE 0.120 N·m" in titles[0], titles
    assert titles[1].startswith("run 8,") and "SC-2" in titles[1] and titles[2].startswith("run 9,"), titles
    expect(page.locator("#progress-chart")).to_contain_text("SC-2")  # the legend: a colour per scenario
    # under it, the range of motion each of those exercises reached, where the run carries one
    bars = page.locator("#progress-chart svg[aria-label='range of motion'] rect")
    expect(bars).to_have_count(2)
    assert bars.locator("title").all_text_contents() == [
        "run 7: from neutral (0°) to 45° pronation (44° in all)",
        "run 9: from 12° supination to 61° pronation (73° in all)"]
    box = [bars.nth(k).bounding_box() for k in (0, 1)]
    assert box[0] and box[1] and box[1]["height"] > box[0]["height"] and box[1]["x"] > box[0]["x"]  # oldest first
    # and all of the person's exercises as one table, from the store (the stopped one is in it)
    with page.expect_download() as dl:
        page.click("#progress-csv")
    assert dl.value.suggested_filename == "exercises-P-007.csv"
    table = list(csv.DictReader(io.StringIO(Path(dl.value.path()).read_text())))
    assert [(r["run"], r["person"], r["status"]) for r in table] == [(str(run_id), "P-007", "stopped")], table
    page.unroute("**/api/runs?kind=workout*")
    # a station that does not answer is said so where the answer would show (its requests had failed as
    # uncaught errors, the history and the form left as they were): the history, the identification form
    page.route("**/api/runs?limit=*", lambda route: route.abort())
    page.locator("#hist-person").dispatch_event("change")
    expect(page.locator("#hist-msg")).to_have_text(
        "The run history could not be loaded: the station did not answer (is it running?)")
    expect(page.locator("#hist-msg")).to_have_class("msg bad")
    page.unroute("**/api/runs?limit=*")
    page.locator("#hist-person").dispatch_event("change")
    expect(page.locator("#hist-msg")).to_have_text("runs 1–1 of P-007")
    page.route("**/api/forms/*", lambda route: route.abort())
    page.click("#ident-clear")
    expect(page.locator("#ident-msg")).to_have_text(
        "The form could not be checked: the station did not answer (is it running?)")
    expect(page.locator("#estimate")).to_be_disabled()
    page.unroute("**/api/forms/*")
    page.click("#ident-clear")
    expect(page.locator("#f-rom_deg")).to_be_visible()
    expect(page.locator("#ident-msg")).not_to_contain_text("could not be checked")
    # a run picked in the history shows its result where the last one shows, fetched from the store
    page.evaluate("document.getElementById('last').textContent = ''")
    page.evaluate("(() => { const c = document.getElementById('c-trace'); c.hidden = true; c.dataset.run = ''; })()")
    page.locator("#runs tbody tr").first.locator("td").nth(2).click()
    expect(page.locator("#last")).to_contain_text("Exercise ")
    expect(page.locator("#runs tbody tr").first).to_have_class("shown")
    expect(trace).to_be_visible()
    expect(trace).to_have_attribute("data-run", str(run_id))
    assert float(page.locator("#metrics tr").first.locator("td").nth(1).inner_text()) == pytest.approx(mae, rel=1e-3)
    # a metric the run could not give is stored as null: it reads "–" (its toPrecision had thrown, the panel empty)
    with urllib.request.urlopen(f"{base}/api/runs/{run_id}", timeout=10) as r:
        stored = json.loads(r.read())
    # and what the station noticed about the run (here as a run whose pressure loop chattered would carry it)
    # is said under its metrics
    warning = "Chamber b's pressure toggled every control period (±0.24 bar, median over the scored window): …"
    page.route(f"**/api/runs/{run_id}", lambda route: route.fulfill(
        json={**stored, "metrics": {**stored["metrics"], "evar": None},
              "result": {**stored["result"], "warnings": [warning]}}))
    page.evaluate("document.getElementById('last').textContent = ''")
    page.locator("#runs tbody tr").first.locator("td").nth(2).click()
    expect(page.locator("#metrics tr").nth(3)).to_have_text("e_var [N²·m²]–")
    expect(page.locator(f"#last-warn-{run_id}")).to_have_text(warning)
    expect(page.locator(f"#last-warn-{run_id}")).to_have_class("msg bad")
    # and from the keyboard: the run's number is a link Tab reaches (a row takes no focus), Enter opens it
    page.evaluate("document.getElementById('last').textContent = ''")
    page.locator("#runs tbody tr").first.get_by_role("link", name=f"run {run_id}: show its result").focus()
    page.keyboard.press("Enter")
    expect(page.locator(f"#last-warn-{run_id}")).to_have_text(warning)
    # how far the arm went, in the words viser uses too
    from app.api.liveplots import range_words

    expect(page.locator(f"#last-range-{run_id}")).to_have_text(
        f"Range of motion reached: {range_words(*stored['result']['angle_range_deg'])}.")
    expect(page.locator("#hist-msg")).not_to_contain_text(f"run {run_id}:")
    page.unroute(f"**/api/runs/{run_id}")

    # issue 7: the emergency stop is always there and always enabled; it latches until cleared
    estop = page.locator("#estop")
    expect(estop).to_be_visible()
    expect(estop).to_be_enabled()
    estop.click()
    expect(page.locator("#state")).to_have_text("fault")
    expect(page.locator("#engine-msg")).to_contain_text("[estop]")
    expect(page.locator("[data-action=start]").first).to_be_disabled()
    page.click("[data-action=clear]")
    expect(page.locator("#state")).to_have_text("disconnected")

    assert not errors, errors


@pytest.mark.slow
def test_a_researcher_tunes_a_pressure_loop_and_exercises_with_the_gains(station: tuple[str, str],
                                                                         browser: object) -> None:
    import json
    import urllib.request

    from playwright.sync_api import Browser, expect

    assert isinstance(browser, Browser)
    base, _viser = station
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(base)
    # read the state only once the page has polled it: before, it shows "…" and Connect was skipped (seen in CI)
    expect(page.locator("#state")).to_have_text(re.compile("^(disconnected|idle)$"), timeout=10_000)
    if page.locator("#state").inner_text() == "disconnected":
        page.click("[data-action=connect]")
    expect(page.locator("#state")).to_have_text("idle", timeout=60000)
    expect(page.locator("#dcv-box")).to_be_hidden()  # valve identification needs the valve set-up
    page.select_option("#pid-side", "b")
    page.fill("#pid-bw", "10")  # ω_c = 10 rad/s: the experiment lasts 3 periods of 1 rad/s (19 s)
    page.click("#tune-pid")
    expect(page.locator("#state")).to_have_text("identifying")
    expect(page.locator("#pid-result")).to_be_visible(timeout=90000)
    expect(page.locator("#pid-result")).to_contain_text("thesis Eq 3.26")
    # the Bode chart: the plant measured at the five test frequencies, each gain set's loop over them
    expect(page.locator("#c-bode")).to_be_visible()
    expect(page.locator("#c-bode")).to_have_attribute("data-points", "5")
    expect(page.locator("#c-bode")).to_have_attribute("data-lines", "3")
    expect(page.locator("#bode-legend")).to_contain_text("plant G measured (coherence ")
    page.evaluate("window.scrollTo(0, document.getElementById('last').getBoundingClientRect().top + scrollY - 120)")
    page.screenshot(path=str(SHOTS / "5-pid-tuning.png"))
    _accessible(page, "5-pid-tuning")
    page.click("#save-gains")
    expect(page.locator("#pid-msg")).to_contain_text("Saved as gain set")
    set_id = page.locator("#pid-msg").inner_text().split("gain set ")[1].split(";")[0]
    expect(page.locator(f"#gains-set option[value='{set_id}']")).to_have_count(1)
    page.select_option("#gains-set", set_id)
    page.click("#start")
    expect(page.locator("#state")).to_have_text("running")
    page.click("#stop")
    expect(page.locator("#state")).to_have_text("idle")
    with urllib.request.urlopen(f"{base}/api/runs?kind=workout&limit=1") as r:
        run = json.load(r)[0]
    with urllib.request.urlopen(f"{base}/api/params/{set_id}") as r:
        stored = json.load(r)["payload"]
    assert run["spec"]["gains"] == stored and stored["kp_a"] == 0.45  # the untuned side keeps Eq 3.26

    # the valve set-up swaps the tuning panel for the valve identification
    page.click("[data-action=disconnect]")
    expect(page.locator("#state")).to_have_text("disconnected")
    page.select_option("#rig", "cpr:C3")
    expect(page.locator("#dcv-box")).to_be_visible()
    expect(page.locator("#pid-box")).to_be_hidden()
    page.click("[data-action=connect]")
    expect(page.locator("#state")).to_have_text("idle", timeout=60000)
    expect(page.locator("#estimate-dcv")).to_be_enabled()
    expect(page.locator("#estimate")).to_be_disabled()  # friction identification is not for this set-up
    expect(page.locator("#start")).to_be_disabled()
    # why, and what the live chart's first trace is there: the cylinder's load cell, in newtons
    expect(page.locator("#start-msg")).to_have_text(
        "Exercises run on the forearm robot: disconnect, choose it under Rig and connect.")
    expect(page.locator("#live-force")).to_have_text("cylinder force [N]")
    expect(page.locator("#live-target")).to_be_hidden()
    page.click("[data-action=disconnect]")
    expect(page.locator("#state")).to_have_text("disconnected")
    page.select_option("#rig", "rotary")
    expect(page.locator("#live-force")).to_have_text("interaction torque [N·m]")
    expect(page.locator("#start-msg")).to_have_text("")
    assert not errors, errors


def _show_as_a_finished_run(page: Any, base: str, lr: dict[str, Any]) -> None:
    """Show ``lr`` in "Last result" as the page shows a run that just ended, once the page has drawn the
    station's own last run or newest stored one (an earlier test's): drawn after, that one had replaced
    ``lr`` (seen in CI)."""
    import json
    import urllib.request

    from playwright.sync_api import expect

    with urllib.request.urlopen(base + "/api/engine", timeout=10) as r:
        last = json.loads(r.read())["last_run"]
    with urllib.request.urlopen(base + "/api/runs?limit=1&with_result=false", timeout=10) as r:
        stored = json.loads(r.read())
    if last is not None or stored:  # without a last run in memory the page shows the newest stored one
        expect(page.locator("#last")).not_to_have_text("No run finished yet.")
    # and its notes box as the page's poll does with it (a run the store does not hold has none): left
    # alone, the box stayed on the newest stored run's notes under this result, as the README's picture showed
    page.evaluate("lr => { showLast(lr); return showRunNotes(lr.run_id); }", lr)
    expect(page.locator("#run-notes-box")).to_be_hidden()


def test_an_exercise_is_drawn_beside_the_other_controllers_on_a_radar(station: tuple[str, str],
                                                                      browser: object) -> None:
    """Thesis Fig 4.26 in the dashboard: an exercise's six metrics beside each other controller's latest
    like run (`GET /api/runs/{id}/comparison`, answered here as the station would, so that no three
    exercises have to run in real time for it; tests/test_api.py checks what the station answers), each
    axis scaled by its largest value, the best of each metric in bold, each controller a link to its run."""
    from playwright.sync_api import Browser, Route, expect

    assert isinstance(browser, Browser)
    base, _viser = station
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    metrics = {"fuzzy": [0.04, 0.28, 0.75, 0.004, 0.065, 0.43], "pid": [0.06, 0.41, 1.29, 0.0067, 0.082, 0.42],
               "default": [0.046, 0.31, 0.93, 0.0041, 0.0645, 0.37]}
    keys = ["mae", "iae", "itae", "evar", "rmse", "maxae"]
    runs: list[dict[str, Any]] = [
        {"controller": c, "run_id": 4242 - k, "status": "complete", "started": 1.8e9 + k,
         "metrics": dict(zip(keys, metrics[c], strict=True))} for k, c in enumerate(("fuzzy", "pid", "default"))]
    scale = {m: max(r["metrics"][m] for r in runs) for m in keys}
    best = {m: min(runs, key=lambda r: r["metrics"][m])["controller"] for m in keys}
    answer = {"run_id": 4242, "scenario": "SC-2", "target_nm": 1.2, "person": "P-009", "runs": runs,
              "scale": scale, "best": best, "missing": []}

    def comparison(route: Route) -> None:
        route.fulfill(json=answer)

    page.route("**/api/runs/4242/comparison", comparison)
    page.goto(base)
    _show_as_a_finished_run(page, base, {"run_id": 4242, "status": "complete", "metrics": runs[0]["metrics"],
                                         "result": {}, "run": {"id": 4242, "kind": "workout", "has_series": False,
                                                               "spec": {"scenario": "SC-2", "controller": "fuzzy",
                                                                        "target_nm": 1.2}}})
    box = page.locator("#last-compare-4242")
    expect(box).to_contain_text("Compared with the other controllers: SC-2 at 1.2 N·m for P-009, each one's "
                                "latest complete exercise")
    radar = box.locator("svg[role=img]")
    expect(radar.locator("polygon[data-controller]")).to_have_count(3)
    # each vertex's distance from the centre is its metric over the largest of the three (the rim: 92 px)
    for r in runs:
        pts = radar.locator(f"polygon[data-controller={r['controller']}]").get_attribute("points") or ""
        xy = np.array([[float(v) for v in p.split(",")] for p in pts.split()])
        got = np.hypot(xy[:, 0] - 165, xy[:, 1] - 132) / 92
        assert got == pytest.approx([r["metrics"][m] / scale[m] for m in keys], abs=0.002), r["controller"]
        assert radar.locator(f"polygon[data-controller={r['controller']}]").get_attribute("data-run") == \
            str(r["run_id"])
    # the first axis (MAE) points up and is labelled with its rim
    expect(radar.locator("text").first).to_have_text(f"MAEmax {scale['mae']:#.3g}")  # toPrecision(3)
    table = box.locator("#compare-table")
    expect(table.locator("th a")).to_have_text(["Cascade fuzzy adaptive PID", "Cascade PID", "Default"])
    _accessible(page, "a radar of three controllers")  # the links' words in the page's colours, not the lines'
    expect(table.locator("th small").first).to_have_text("run 4242 (this one)")
    for i, m in enumerate(keys):
        cells = table.locator("tr").nth(i + 1).locator("td")
        bold = [cells.nth(1 + k).locator("b").count() for k in range(3)]
        assert bold == [int(r["controller"] == best[m]) for r in runs], (m, bold)
    assert best["maxae"] == "default" and best["mae"] == "fuzzy"  # the table's bold moves from column to column
    assert table.locator("th a").nth(1).get_attribute("data-show-run") == "4241"
    # saved for a report: the drawing as a file of its own, its legend inside it
    with page.expect_download() as dl:
        box.get_by_text("Save the chart (SVG)").click()
    assert dl.value.suggested_filename == "comparison-run-4242.svg"
    saved = Path(dl.value.path()).read_text()
    assert saved.startswith('<?xml version="1.0" encoding="UTF-8"?>') and saved.count("<polygon") == 4 + 3
    for text in ("Cascade fuzzy adaptive PID, run 4242 (this one)", "Cascade PID, run 4241", "Default, run 4240"):
        assert text in saved, text
    assert not errors, errors


def test_a_friction_identification_shows_each_parameter_with_its_interval_and_both_models(
        station: tuple[str, str], browser: object) -> None:
    """Thesis Fig 3.19's results: the parameters per direction, now with their 95 % intervals (one that runs
    onto a bound of Table 3.4 said to be not pinned down), the tests used, the Coulomb + viscous fit beside
    the Stribeck one (SPEC §6: show both), on a chart with its speeds and torques marked. The report is
    the one a station stores (``friction_report``) for a simulated identification, shown as a finished run
    is: a paced one takes about ten minutes."""
    import json

    from playwright.sync_api import Browser, expect

    from app.engine.ident.fitting import friction_report
    from app.engine.ident.runner import identify_rotary_sim
    from app.storage import strict_json

    assert isinstance(browser, Browser)
    base, _viser = station
    res, run = identify_rotary_sim(3.0, 30, 30, seed=0)
    rep = json.loads(strict_json(friction_report(run.procedure.data, res)))
    errors: list[str] = []  # the pages' script errors, at either width

    def seen(e: object) -> None:
        errors.append(str(e))

    for width in (1400, 390):
        page = browser.new_page(viewport={"width": width, "height": 900})
        page.on("pageerror", seen)
        page.goto(base)
        _show_as_a_finished_run(page, base, {"run_id": 99, "status": "finished", "result": rep})
        expect(page.locator("#last")).to_contain_text(
            "Identification 99: finished — 60 breakaway and 60 moving tests run")
        loose = []
        for d in ("ccw", "cw"):
            fit = rep["fits"][d]
            row = page.locator(f"#ident-result tr[data-dir={d}]")
            expect(row.locator("td[data-param=fs]")).to_contain_text(" ± ")
            expect(row.locator("td[data-param=fs]")).to_contain_text("(SD)")
            for k in ("fs", "fc", "vs", "b"):
                expect(row.locator(f"td[data-param={k}] small")).to_contain_text("95 %: ")
                assert (row.locator(f"td[data-param={k}] small.loose").count() == 1) == fit["ci"][k]["at_bound"], (d, k)
                loose += [k] if fit["ci"][k]["at_bound"] else []
            note = page.locator(f"#ident-notes li[data-dir={d}]")
            expect(note).to_contain_text(f"{fit['n_static']} breakaway and {fit['n_dynamic']} moving tests used")
            rule = {"stribeck": "Stribeck", "coulomb_viscous": "Coulomb + viscous"}[fit["choice"]["thesis_rule"]]
            expect(note).to_contain_text(f"The thesis GUI's rule would say: {rule}.")
            expect(note).to_contain_text("Coulomb + viscous alone: T_c ")
        # whatever this draw leaves loose is said once, under the table
        expect(page.locator("#ident-loose")).to_have_count(1 if loose else 0)
        expect(page.locator("#friction-cv")).to_be_visible()
        chart = page.locator("#c-friction")
        n_points = len(rep["points"]["static"]) + len(rep["points"]["dynamic"])
        expect(chart).to_have_attribute("data-points", str(n_points))
        assert chart.evaluate("c => c.width === Math.round(c.clientWidth)")  # drawn at the size it is shown
        for attr in ("data-ticks", "data-vticks"):  # both axes marked at round values, zero among them
            ticks = [float(v) for v in (chart.get_attribute(attr) or "").split()]
            assert len(ticks) >= 3 and 0.0 in ticks and np.allclose(np.diff(ticks), ticks[1] - ticks[0]), (attr, ticks)
        if width == 1400:
            page.locator("xpath=//div[@id='last']/..").screenshot(path=str(SHOTS / "7-friction-identification.png"))
            _accessible(page, "7-friction-identification")
        # on a phone the table scrolls inside its box; the page itself stays as wide as the screen
        assert page.evaluate("document.documentElement.scrollWidth") <= width
        page.close()
    assert not errors, errors


def test_a_valve_map_is_drawn_as_the_thesis_figures_draw_it(station: tuple[str, str], browser: object) -> None:
    """A valve identification's result (the shape ``tests/test_api.py``'s CPR run checks) shows its Table 4.1
    rows and the critical-pressure-ratio map a(u) per supply pressure, filling and exhausting (Figures
    4.1–4.2), where it had shown the tables alone."""
    from playwright.sync_api import Browser, expect

    assert isinstance(browser, Browser)
    base, _viser = station
    row = {"u": 5.0, "a": 0.97, "eps": 0.61, "g": 0.0079, "r2": 0.99}
    maps = {"filling": {"u_cpr": [4.2, 4.6, 5.0, 5.4], "ps_cpr": [3.0, 5.0],
                        "a": [[1.0, 1.0], [1.0, 1.0], [0.95, 0.97], [None, 0.33]], "table_4_1": [row]},
            "exhausting": {"u_cpr": [4.6, 5.0, 5.4, 5.8], "ps_cpr": [5.0],
                           "a": [[0.2], [0.21], [0.61], [1.0]], "table_4_1": [row]}}
    result = {"parameters": maps, "tests": {"cpr": 12, "validation": 0}}
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    errors: list[str] = []

    def seen(e: object) -> None:
        errors.append(str(e))

    page.on("pageerror", seen)
    page.goto(base)
    _show_as_a_finished_run(page, base, {"run_id": 98, "status": "finished", "result": result})
    expect(page.locator("#last .dcv-table")).to_have_count(2)
    chart = page.locator("#c-cpr")
    expect(chart).to_be_visible()
    expect(chart).to_have_attribute("data-points", "11")  # every a the map holds; the missing one is left out
    expect(page.locator("#cpr-legend")).to_contain_text("P_s = 3.00 bar")
    expect(page.locator("#cpr-legend")).to_contain_text("P_s = 5.00 bar")
    _accessible(page, "a valve map")  # its legend keyed in eight colours, the orange of P_s = 5 bar among them
    # another kind of result takes the chart away again
    page.evaluate("lr => showLast(lr)", {"run_id": 97, "status": "stopped", "result": {}})
    expect(chart).to_be_hidden()
    assert not errors, errors
    page.close()


def test_on_the_linear_rig_the_live_bar_shows_the_piston_along_the_cylinders_stroke(
        station: tuple[str, str], browser: object) -> None:
    """The bar above the live charts showed the handle's angle on the forearm robot and nothing on the
    linear set-ups; it now shows the piston's travel along the catalogue's stroke (the station's status
    says it), and the rig list shows the rig connected, also when a script connected it."""
    from playwright.sync_api import Browser, expect

    assert isinstance(browser, Browser)
    base, _viser = station
    _connected_and_idle(base)
    _call(base, "POST", "/api/engine/disconnect")
    st = _call(base, "POST", "/api/engine/connect", {"rig": "linear", "cylinder": "C1"})
    assert st["rig"] == {"kind": "linear", "cylinder": "C1", "stroke_mm": 225.0}
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    try:
        page.goto(base)
        expect(page.locator("#rig")).to_have_value("linear:C1", timeout=10_000)
        expect(page.locator("#gauge-caption")).to_have_text("left: retracted · right: extended (225 mm, the C1 stroke)")
        # the simulated piston rests retracted: the live samples put the mark at the left end
        expect(page.locator("#handle-angle")).to_have_text("Piston: 0 of 225 mm extended", timeout=10_000)
        _accessible(page, "the dashboard on the linear rig")
        mark = page.locator("#handle-mark")
        assert float(mark.get_attribute("x").rstrip("%")) < 1.0  # type: ignore[union-attr]
        # 100 mm of the 225, read at once (the next live poll puts the mark back where the piston is)
        said, x = page.evaluate("""() => { moveGauge(0.1);
            return [document.getElementById('handle-angle').textContent,
                    parseFloat(document.getElementById('handle-mark').getAttribute('x'))]; }""")
        assert said == "Piston: 100 of 225 mm extended" and x == pytest.approx(100 * 100 / 225, abs=0.01)
        # the friction form is the linear GUI's, suggesting C1's catalogue stroke (it had suggested C3's
        # 300 mm on every cylinder, which sends C1's static tests past the end of its 225 mm)
        expect(page.locator("#ident-title")).to_have_text("Friction identification (linear test cylinder C1)")
        expect(page.locator("#f-stroke_mm")).to_have_attribute("placeholder", "suggested: 225")
        page.fill("#f-stroke_mm", "225")
        page.locator("#f-stroke_mm").dispatch_event("change")
        expect(page.locator("#f-piston_diameter_mm")).to_have_attribute("placeholder", "suggested: 25")
        # C3 connected instead: the form starts over with its geometry (C1's 225 mm typed there is not C3's)
        _call(base, "POST", "/api/engine/disconnect")
        _call(base, "POST", "/api/engine/connect", {"rig": "linear", "cylinder": "C3"})
        expect(page.locator("#ident-title")).to_have_text("Friction identification (linear test cylinder C3)",
                                                          timeout=10_000)
        expect(page.locator("#f-stroke_mm")).to_have_value("")
        expect(page.locator("#f-stroke_mm")).to_have_attribute("placeholder", "suggested: 300")
        # back on the forearm robot, the angle again
        _call(base, "POST", "/api/engine/disconnect")
        _call(base, "POST", "/api/engine/connect", {"rig": "rotary"})
        expect(page.locator("#rig")).to_have_value("rotary", timeout=10_000)
        expect(page.locator("#f-rom_deg")).to_have_attribute("placeholder", "suggested: 270")
        expect(page.locator("#gauge-caption")).to_contain_text("supination", timeout=10_000)
        expect(page.locator("#handle-angle")).to_contain_text("Handle: ", timeout=10_000)
    finally:
        page.close()
        _connected_and_idle(base)
        if _call(base, "GET", "/api/engine")["rig"]["kind"] != "rotary":
            _call(base, "POST", "/api/engine/disconnect")


def test_every_page_works_on_a_station_with_no_internet(station: tuple[str, str], browser: object) -> None:
    """A station beside a rig is often offline. With every request off the station refused, the API's
    reference (/docs, /redoc: they had loaded Swagger UI and ReDoc from a CDN and stayed blank), the
    dashboard, the diagnosis page and the viser page all draw, and none of them asks another host."""
    from playwright.sync_api import Browser, Route, expect

    assert isinstance(browser, Browser)
    base, viser = station
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    elsewhere: list[str] = []
    errors: list[str] = []

    def offline(route: Route) -> None:
        url = route.request.url
        if url.startswith(("http://127.0.0.1:", "ws://127.0.0.1:", "data:", "blob:")):
            route.continue_()
        else:
            elsewhere.append(url)
            route.abort()

    def seen(e: object) -> None:
        errors.append(str(e))

    page.route("**/*", offline)
    page.on("pageerror", seen)
    page.goto(base + "/docs")
    expect(page.locator(".swagger-ui .info .title")).to_contain_text("CWRR Lab Station", timeout=20_000)
    expect(page.locator(".opblock-summary-path", has_text="/api/health").first).to_be_visible()
    page.goto(base + "/redoc")
    expect(page.locator("h1", has_text="CWRR Lab Station").first).to_be_visible(timeout=20_000)
    expect(page.get_by_text("/api/health").first).to_be_attached()
    page.goto(base)
    expect(page.locator("#state")).not_to_have_text("…", timeout=10_000)  # the engine answered
    page.goto(base + "/static/diagnosis.html")
    expect(page.locator("h1")).to_contain_text("gap diagnosis", ignore_case=True)
    page.goto(viser)
    expect(page.locator("canvas").first).to_be_attached(timeout=60_000)
    page.wait_for_timeout(1000)  # what a scene fetches once it draws (an environment map, a font)
    # ReDoc's own "by Redocly" logo is the one request off the station: its image hides itself when it
    # cannot load (redoc.standalone.js: onError), and nothing else on the page depends on it
    assert [u for u in elsewhere if u != "https://cdn.redoc.ly/redoc/logo-mini.svg"] == [], elsewhere
    assert not errors, errors
    page.close()


def test_on_a_station_with_tokens_the_dashboard_asks_for_one_and_uses_it(browser: object,
                                                                         tmp_path: Path) -> None:
    from playwright.sync_api import Browser, expect

    assert isinstance(browser, Browser)
    therapist = "therapist-browser-" + "0123456789"
    vport = free_port()
    srv = ServedStation(tmp_path, viser_port=vport, CWRR_AUTO_CONNECT="false", CWRR_THERAPIST_TOKEN=therapist,
                        CWRR_ADMIN_TOKEN="admin-browser-" + "0123456789")
    base = srv.url
    try:
        page = browser.new_page(viewport={"width": 1400, "height": 1000}, accept_downloads=True)
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(base)
        expect(page.locator("#signin")).to_be_visible(timeout=30000)
        expect(page.locator("#state")).to_have_text("sign in")
        _accessible(page, "the sign-in prompt")
        page.fill("#token", "not-the-token-" + "0123456789")
        page.click("#signin-btn")
        expect(page.locator("#who")).to_have_text("token not accepted")
        page.fill("#token", therapist)
        page.click("#signin-btn")
        expect(page.locator("#who")).to_have_text("signed in: therapist")
        expect(page.locator("#signin")).to_be_hidden()
        expect(page.locator("#state")).to_have_text("disconnected", timeout=10000)
        # the live plots: a stranger's browser is refused, the signed-in one gets in by the link
        stranger = browser.new_page()
        stranger.goto(f"http://127.0.0.1:{vport}/")
        expect(stranger.locator("h1")).to_have_text("Sign in first")
        stranger.close()
        with page.expect_popup() as popup:
            page.click("#viser-link")
        viser = popup.value
        # the panel's charts come over viser's websocket, so they show only if it got through too
        expect(viser.get_by_text("Interaction torque vs target")).to_be_visible(timeout=30000)
        assert "ticket" not in viser.url
        viser.close()
        page.click("[data-action=connect]")
        expect(page.locator("#state")).to_have_text("idle", timeout=60000)
        # tuning is an admin's: the idle rig would allow it, the therapist's tab offers no button that 403s
        expect(page.locator("#tune-pid")).to_be_disabled()
        expect(page.locator("#pid-box .admin-note")).to_be_visible()
        expect(page.locator("#pid-box .admin-note")).to_have_text(
            "Needs the admin role: this tab is signed in as a therapist.")
        _accessible(page, "a therapist's tab")
        page.click("[data-action=start]")
        expect(page.locator("#state")).to_have_text("running", timeout=30000)
        page.wait_for_timeout(1500)  # 1.5 s of the run (300 periods) before the therapist stops it
        assert int(page.locator("#c-torque").get_attribute("data-samples") or 0) > 0  # live data came, with the token
        page.click("#stop")
        expect(page.locator("#state")).to_have_text("idle", timeout=30000)
        # the export link carries the token too (a plain link would get 401)
        link = page.locator("#runs a", has_text="CSV").first
        expect(link).to_be_visible(timeout=30000)
        with page.expect_download() as dl:
            link.click()
        text = Path(dl.value.path()).read_text()
        assert text.startswith("t,") and text.count("\n") > 100  # ≥ 0.5 s of the run at 200 Hz
        assert "token" not in page.url and not errors, errors
        # the gap diagnosis is an admin's: the page says so at once and offers no button that would 403
        page.locator("a[href='/static/diagnosis.html']").first.click()
        expect(page.locator("#msg")).to_contain_text("A gap diagnosis needs the admin role; this tab is signed in "
                                                     "with a therapist token", timeout=10000)
        expect(page.locator("#go")).to_be_disabled()
        # a stored report opened there keeps its own message (here: that there is no such run)
        page.goto(base + "/static/diagnosis.html?report=99999")
        expect(page.locator("#msg")).to_contain_text("run 99999: ", timeout=10000)
        page.wait_for_timeout(500)
        expect(page.locator("#msg")).not_to_contain_text("admin role")
        expect(page.locator("#go")).to_be_disabled()
        # a researcher tries the API from /docs: refused without a token, answered once signed in there
        # (the document had declared no bearer scheme, so /docs had no Authorize button)
        docs = browser.new_page(viewport={"width": 1400, "height": 1000})
        docs.goto(base + "/docs")
        op = docs.locator(".opblock-get:has(.opblock-summary-path[data-path='/api/engine'])")
        expect(op).to_be_visible(timeout=20000)
        op.locator(".opblock-summary").click()
        op.locator("button.try-out__btn").click()
        op.locator("button.execute").click()
        status = op.locator(".live-responses-table .response .response-col_status").first
        expect(status).to_have_text("401", timeout=10000)
        docs.locator(".scheme-container button.authorize").click()
        docs.locator(".modal-ux input").first.fill(therapist)
        docs.locator(".modal-ux button.authorize").click()
        docs.locator(".modal-ux button.btn-done").click()
        op.locator("button.execute").click()
        expect(status).to_have_text("200", timeout=10000)
        expect(op.locator(".live-responses-table .response .response-col_description").first).to_contain_text(
            '"state": "idle"')
        docs.close()
        # restarted since that run, the station keeps no last run in memory: the dashboard shows the newest
        # stored one (it had said "No run finished yet" over a history of runs), once signed in
        page.goto(base)
        run_id = page.locator("#runs tbody tr").first.get_attribute("data-run")
        srv.stop()
        srv = ServedStation(tmp_path, viser_port=0, CWRR_AUTO_CONNECT="false", CWRR_THERAPIST_TOKEN=therapist,
                            CWRR_ADMIN_TOKEN="admin-browser-" + "0123456789")
        page.goto(srv.url)
        page.fill("#token", therapist)
        page.click("#signin-btn")
        # (1.5 s of it reached no scored window: "Run N: stopped (an evaluation window needs …)")
        expect(page.locator("#last")).to_contain_text(f"Run {run_id}: stopped", timeout=15000)
        expect(page.locator(f"#runs tr[data-run='{run_id}']")).to_have_class("shown")
        # a page opened during the restarted station's first run shows the one before it, not that run as
        # "Run N: running" under "Last result"
        page.click("[data-action=connect]")
        expect(page.locator("#state")).to_have_text("idle", timeout=60000)
        page.click("[data-action=start]")
        expect(page.locator("#state")).to_have_text("running", timeout=30000)
        page.reload()  # the token stays with the tab
        expect(page.locator("#state")).to_have_text("running", timeout=15000)
        expect(page.locator("#last")).to_contain_text(f"Run {run_id}: stopped", timeout=15000)
        assert not errors, errors  # (the run is left to the server's stop: it may have ended by now)
    finally:
        srv.stop()


def test_a_researcher_uploads_rig_logs_on_the_diagnosis_page(station: tuple[str, str], browser: object,
                                                              tmp_path: Path) -> None:
    """Issue 6's logs from a rig, through the page: a lone .csv is refused before anything is sent, a
    log in the wrong unit is refused with the reason, good pairs become runs and a diagnosis of them
    starts."""
    import json
    import urllib.request

    import numpy as np
    from playwright.sync_api import Browser, expect

    from app.engine.sim import LOG_COLUMNS, run_workout

    assert isinstance(browser, Browser)
    base, _viser = station
    meta = {"rig": "rotary", "sample_rate_hz": 200.0, "p_atm_bar": 1.01325, "working_pressure_bar": 3.0,
            "experiment": "workout", "human": True}

    def write(name: str, data: np.ndarray) -> list[str]:
        np.savetxt(tmp_path / f"{name}.csv", data, delimiter=",", header=",".join(LOG_COLUMNS), comments="")
        (tmp_path / f"{name}.json").write_text(json.dumps(meta))
        return [str(tmp_path / f"{name}.csv"), str(tmp_path / f"{name}.json")]

    def imported() -> list[dict]:
        with urllib.request.urlopen(base + "/api/runs?kind=imported", timeout=10) as r:
            return list(json.loads(r.read()))

    before = len(imported())
    good = write("isotonic-1", run_workout(duration=1.0, seed=1).log) + \
        write("isotonic-2", run_workout(duration=1.0, seed=2).log)
    pa = run_workout(duration=1.0).log
    pa[:, LOG_COLUMNS.index("p_a")] *= 1e5
    bad = write("in-pascal", pa)
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(base + "/static/diagnosis.html")
    # the protocol table comes from the engine (GET /api/diagnoses/protocol), not a copy in the page
    expect(page.locator("#protocol")).to_contain_text("fill_shut")
    expect(page.locator("#protocol")).to_contain_text("heat transfer, external leakage, vane leakage")
    expect(page.locator("#effects input")).to_have_count(9)  # one check box per candidate the engine names
    # a simulated rig off parameter by parameter: what the page asks for (answered here, nothing runs)
    from app.engine.params import EFFECT_NAMES

    sent: list[dict[str, Any]] = []

    def refuse(route: Any) -> None:
        sent.append(json.loads(route.request.post_data or "{}"))
        route.fulfill(status=409, content_type="application/json", body='{"detail": "not now (test)"}')

    page.route("**/api/diagnoses", refuse)
    page.check("#effects input[value=heat_transfer]")
    page.select_option("#errs", "each")
    # a range measured on the rig narrows the recalibration's (the engine's parameters and defaults);
    # one that reaches beyond the default is refused with the server's rules, before anything runs
    page.click("#ranges summary")
    expect(page.locator("#range-rows")).to_contain_text("chamber dead volumes × nominal (default 0.200 … 5.00")
    page.fill("[data-bound=friction_scale][data-end='1']", "5")
    page.click("#go")
    expect(page.locator("#msg")).to_contain_text(
        "bound on friction_scale: 0.3 … 5 reaches outside the default range 0.3 … 3")
    assert sent == []
    page.fill("[data-bound=friction_scale][data-end='1']", "")
    page.fill("[data-bound=dead_volume_scale][data-end='0']", "0.9")
    page.fill("[data-bound=dead_volume_scale][data-end='1']", "1.1")
    page.fill("[data-bound=gain_a][data-end='1']", "1.05")  # the other end stays the default's
    # the candidates to try: all nine ticked (none sent); with none ticked nothing is sent, and one left out
    # is sent as the list of the others
    page.click("#tried summary")
    expect(page.locator("#tried-effects input:checked")).to_have_count(9)
    for box in page.locator("#tried-effects input").all():
        box.uncheck()
    page.click("#go")
    expect(page.locator("#msg")).to_have_text("tick at least one candidate effect to try")
    assert sent == []
    for box in page.locator("#tried-effects input").all():
        box.check()
    page.uncheck("#tried-effects input[value=valve_dynamics]")
    page.click("#go")
    expect(page.locator("#msg")).to_contain_text("not now (test)")
    assert sent == [{"protocol": {"effects": ["heat_transfer"], "magnitude": 2, "param_error": 0.2,
                                  "errors": "each", "seed": 0, "scale": 1},
                     "bounds": {"dead_volume_scale": [0.9, 1.1], "gain_a": [0.8, 1.05]},
                     "effects": [e for e in EFFECT_NAMES if e != "valve_dynamics"]}], sent
    page.check("#tried-effects input[value=valve_dynamics]")
    for end in ("0", "1"):
        page.fill(f"[data-bound=dead_volume_scale][data-end='{end}']", "")
    page.fill("[data-bound=gain_a][data-end='1']", "")
    page.unroute("**/api/diagnoses")
    # a station that does not answer is said so, not left as an uncaught "Failed to fetch" and a button
    # that did nothing
    page.route("**/api/diagnoses", lambda route: route.abort())
    page.click("#go")
    expect(page.locator("#msg")).to_have_text(
        "the station did not answer POST /api/diagnoses (is it running?)")
    page.unroute("**/api/diagnoses")
    page.select_option("#src", "files")
    expect(page.locator("#logfiles")).to_be_visible()
    page.set_input_files("#logfiles", good[:1])
    page.click("#go")
    expect(page.locator("#msg")).to_contain_text("needs both isotonic-1.csv and isotonic-1.json")
    page.set_input_files("#logfiles", bad)
    page.click("#go")
    expect(page.locator("#msg")).to_contain_text("in-pascal: ")
    expect(page.locator("#msg")).to_contain_text("looks like Pa")
    assert len(imported()) == before  # refused logs leave nothing
    page.set_input_files("#logfiles", good)
    page.click("#go")
    expect(page.locator("#msg")).to_contain_text("running", timeout=30_000)
    names = sorted(r["spec"]["name"] for r in imported()[: 2])
    assert names == ["isotonic-1", "isotonic-2"]
    page.screenshot(path=str(SHOTS / "diagnosis_upload.png"))
    _accessible(page, "diagnosis_upload")
    # the station's run history lists them beside the finished diagnosis (whose metrics are not a workout's)
    deadline = time.monotonic() + 120
    while True:
        with urllib.request.urlopen(base + "/api/runs?kind=diagnosis&limit=1", timeout=10) as r:
            diag = json.loads(r.read())[0]
        if diag["status"] != "running":
            break
        assert time.monotonic() < deadline, "the diagnosis did not finish"
        time.sleep(0.5)
    assert diag["status"] == "complete" and diag["metrics"], diag
    page.goto(base)
    expect(page.locator("#runs tbody")).to_contain_text("Imported log isotonic-2")
    expect(page.locator("#runs tbody")).to_contain_text("Gap diagnosis")
    # the protocol on the connected (simulated) rig from the page: the engine runs it, the prompts
    # show, and its experiments' runs are diagnosed
    with urllib.request.urlopen(base + "/api/engine", timeout=10) as r:
        if json.loads(r.read())["state"] == "disconnected":
            urllib.request.urlopen(urllib.request.Request(base + "/api/engine/connect", method="POST"), timeout=10)
    page.goto(base + "/static/diagnosis.html")
    page.select_option("#src", "rig")
    expect(page.locator("#rkinds input")).to_have_count(7)
    for box in page.locator("#rkinds input").all():
        if box.get_attribute("value") != "hold_closed":
            box.uncheck()
    page.fill("#rscale", "0.2")
    # a short protocol is allowed, and said to pin the baseline down less
    expect(page.locator("#rscale-note")).to_be_visible()
    expect(page.locator("#rscale-note")).to_contain_text("A protocol 0.2 × as long pins the model's nominal values")
    page.fill("#rperson", "P-021")
    # the protocol's progress is read off the header's poll of the engine, not off a second poll of its own
    polls: list[float] = []
    page.on("request", lambda q: polls.append(time.monotonic()) if q.url == base + "/api/engine" else None)
    page.click("#go")
    expect(page.locator("#msg")).to_contain_text("hold_closed, repetition", timeout=15_000)
    t_proto = time.monotonic()
    expect(page.locator("#rstop")).to_be_visible()
    expect(page.locator("#msg")).to_contain_text("diagnosis", timeout=60_000)
    # one a second (the page's own poll had doubled that: 20 in 10 s)
    elapsed, during = time.monotonic() - t_proto, [t for t in polls if t >= t_proto]
    assert len(during) <= 1.25 * elapsed + 2, (len(during), elapsed)
    expect(page.locator("#verdict")).not_to_have_text("—", timeout=120_000)
    expect(page.locator("#detail")).to_contain_text("Held out: hold_closed-2")
    # each channel's RMS beside the floor the bars are read against, not the bare sensor noise
    expect(page.locator("#where tr").first).to_contain_text("noise floor")
    expect(page.locator("#where tr").first).to_contain_text("follows input")  # the input a residual follows
    # what the recalibration made of each nominal value, in the engine's words
    expect(page.locator("#recal")).to_contain_text("chamber dead volumes × nominal")
    expect(page.locator("#recal tr")).to_have_count(14)  # a header and the rotary rig's 13 parameters
    # where in time: the held-out log's channel furthest above its floor, each prediction's error against
    # the noise floor's band; the measured values beside the predictions one choice away
    expect(page.locator("#trace-box")).to_be_visible()
    expect(page.locator("#trace-log option")).to_have_text(["hold_closed-2"])
    with urllib.request.urlopen(base + "/api/runs?kind=diagnosis&limit=1", timeout=10) as r:
        newest = json.loads(r.read())[0]["id"]
    with urllib.request.urlopen(f"{base}/api/diagnoses/{newest}/traces", timeout=10) as r:
        tr = json.loads(r.read())
    # the baseline's, the verdict model's if it names an effect, and each effect it cannot tell from its own
    n_pred = 1 + bool(tr["model"]) + len(tr["confusable"])
    expect(page.locator("#trace")).to_have_attribute("data-series", str(n_pred))
    expect(page.locator("#trace-legend")).to_contain_text("± noise floor")
    page.select_option("#trace-view", "values")
    expect(page.locator("#trace")).to_have_attribute("data-series", str(n_pred + 1))
    expect(page.locator("#trace-legend")).to_contain_text("measured")
    page.select_option("#trace-view", "residual")
    page.screenshot(path=str(SHOTS / "6-gap-diagnosis.png"), full_page=True)
    _accessible(page, "6-gap-diagnosis")
    # the person typed on the page went with the protocol's run and its experiments' runs
    with urllib.request.urlopen(base + "/api/runs?kind=diagnosis_protocol&limit=1", timeout=10) as r:
        (proto,) = json.loads(r.read())
    assert proto["person"] == "P-021", proto
    with urllib.request.urlopen(base + "/api/runs?kind=protocol&limit=2", timeout=10) as r:
        assert [x["person"] for x in json.loads(r.read())] == ["P-021", "P-021"]
    # a verdict weighed against a baseline of another form (docs/diagnosis-record.md, "A sensor offset or
    # friction per direction") is said under it: that report, as the engine writes it, shown by the page
    with urllib.request.urlopen(base + "/api/runs?kind=diagnosis&limit=1", timeout=10) as r:
        diag_id = json.loads(r.read())[0]["id"]
        rep = json.loads(urllib.request.urlopen(f"{base}/api/runs/{diag_id}", timeout=10).read())["result"]
    stored = json.loads(json.dumps(rep))  # as stored: rep is altered below to show other findings
    # the report as stored, to download
    expect(page.locator("#download")).to_be_visible()
    assert page.locator("#download").get_attribute("download") == f"diagnosis-{diag_id}.json"
    with page.expect_download() as dl:
        page.click("#download")
    assert json.loads(Path(dl.value.path()).read_text())["verdict"] == rep["verdict"]
    assert rep["alternatives"] == [] or rep["verdict"]["effects"] == ["sensor_bias"], rep["verdict"]
    far = rep["baseline"]["recalibration"]["far"]
    expect(page.locator("#recal tr.far")).to_have_count(len(far))
    expect(page.locator("#recal-note")).to_contain_text(
        "The recalibration moved" if far else "No nominal value moved further than a tolerance explains")
    # a closed hold never moves the handle at speed: inertia is said to be not ruled out, not absent
    assert "inertia" in rep["verdict"]["untested"], rep["experiments"]["unshown"]
    expect(page.locator("#detail")).to_contain_text("Not ruled out, since no held-out log shows them: ")
    expect(page.locator("#detail")).to_contain_text("inertia (needs fast motion: run friction_sweep or sine_sweep)")
    if not rep["verdict"]["effects"]:  # which "no significant effect" it is: nothing above the noise, or a gap
        above = rep["baseline"]["gap"]["above_noise"]
        expect(page.locator("#detail")).to_contain_text(
            "No candidate closes what the baseline leaves. Gap left unexplained: 100 %" if above
            else "The baseline is not significantly above the noise: E ")
        quiet = json.loads(json.dumps(rep))
        quiet["baseline"]["gap"] |= {"e": 0.0102, "e_floor": 0.01, "ci90": [-0.0003, 0.0006], "above_noise": False}
        quiet["verdict"]["effects"], quiet["alternatives"] = [], []
        page.evaluate("rep => show(rep)", quiet)
        expect(page.locator("#detail")).to_contain_text(
            "The baseline is not significantly above the noise: E 0.0102 against a floor of 0.0100 (90 % CI of "
            "the difference -3.00e-4 … 6.00e-4); more or longer held-out logs would tell a small gap from none.")
        expect(page.locator("#detail")).not_to_contain_text("Gap left unexplained")
    # all nine were tried; a diagnosis asked for fewer says which it left out, as it could not name them
    expect(page.locator("#detail")).not_to_contain_text("Tried only")
    fewer = json.loads(json.dumps(rep))
    fewer["ranking"] = fewer["ranking"][:3]
    page.evaluate("rep => show(rep)", fewer)
    expect(page.locator("#detail")).to_contain_text(
        f"Tried only {', '.join(r['effect'] for r in fewer['ranking'])}, as asked: ")
    expect(page.locator("#detail")).to_contain_text("were left out, so the verdict cannot name them.")
    rep["verdict"] |= {"effects": ["sensor_bias"], "alternatives": ["friction_per_direction"]}
    rep["alternatives"] = [{"explanation": "friction_per_direction", "instead_of": "sensor_bias",
                            "description": "friction off per direction", "separate_by": "tare the sensors",
                            "gap_closure": 0.65, "effect_gap_closure": 0.66, "gc_difference_ci90": [-0.06, 0.11],
                            "confusable": True, "better": False, "dropped": False}]
    rep["ranking"][0]["dropped_for"] = ["friction_per_direction"]  # as where the alternative explains more
    rep["how_far"]["model"] = ["sensor_bias"]
    rep["experiments"]["flat_channels"] = {"isotonic-1": {"torque": 0.0}}
    rep["ranking"][0]["rebased_gap_closure"] = 0.0123
    # the verdict's own fit moved a nominal value past a tolerance: its column marks it
    for row in rep["baseline"]["recalibration"]["params"]:
        row |= {"in_model": row["value"], "in_model_far": False}
    rep["baseline"]["recalibration"]["params"][2] |= {"in_model": 0.36, "in_model_far": True}
    rep["verdict"]["baseline_beaten"] = {"by": "heat_transfer", "gap_closure": -0.46, "rebased_gap_closure": 0.202,
                                         "switched_off": False, "rereferenced": True}
    # the rig's own logs were written the way the format says: nothing was read reversed
    assert not stored["experiments"]["pressure_order"]["swapped"], stored["experiments"]["pressure_order"]
    assert not stored["experiments"]["angle_sign"]["reversed"], stored["experiments"]["angle_sign"]
    assert not stored["experiments"]["torque_sign"]["reversed"], stored["experiments"]["torque_sign"]
    assert not any(w["mirrored"] for w in stored["experiments"]["dcv_wiring"].values())
    # a torque and an angle read reversed, with too few settled fills to say which chamber is which
    rep["experiments"] |= {"pressure_order": {"swapped": False, "agreement": 1.0, "samples": 40},
                           "torque_sign": {"reversed": True, "agreement": 0.004, "samples": 900},
                           "angle_sign": {"reversed": True, "dissipation": -0.991, "samples": 1234}}
    page.evaluate("rep => show(rep)", rep)
    expect(page.locator("#detail")).to_contain_text(
        "The angle and speed were read with their signs reversed: as written, the chambers' and the measured torque "
        "fed the vane's motion power back instead of losing it to friction (net -0.991 of the power over 1234 "
        "samples in motion); with the torque reversed too, this is also what p_a and p_b written in each other's "
        "columns look like, which no settled fill at two pressures in these logs can tell.")
    expect(page.locator("#detail")).to_contain_text("if its sign is right, p_a and p_b are swapped")
    # which chamber is which, settled: the pressures were swapped, and that alternative is no longer offered
    rep["experiments"]["pressure_order"] = {"swapped": True, "agreement": 0.0, "samples": 1982}
    rep["experiments"]["angle_sign"]["reversed"] = False
    rep["experiments"]["dcv_wiring"] = {"a": {"mirrored": False, "agreement": 1.0, "samples": 9000},
                                        "b": {"mirrored": True, "agreement": 0.0, "samples": 9100}}
    page.evaluate("rep => show(rep)", rep)
    expect(page.locator("#detail")).to_contain_text(
        "DCV-b's command was read mirrored about 5 V: fully open, chamber b stood near the atmosphere where the "
        "format's wiring fills it and near its regulator's pressure where it exhausts it, in 100 % of 9100 settled "
        "samples.")
    expect(page.locator("#detail")).not_to_contain_text("DCV-a's command")
    expect(page.locator("#detail")).to_contain_text(
        "p_a and p_b were read swapped: with both chambers filling from regulators set at least 0.5 V apart, their "
        "pressures stood in the other order in 100 % of 1982 settled samples.")
    expect(page.locator("#detail")).not_to_contain_text("if its sign is right")
    expect(page.locator("#detail")).not_to_contain_text("The angle and speed were read")
    expect(page.locator("#ranking")).to_contain_text("GC without the effect")
    expect(page.locator("#recal td.far")).to_have_count(1)
    expect(page.locator("#recal td.far")).to_have_text("0.360")
    expect(page.locator("#ranking")).to_contain_text("0.0123")
    # a candidate that is not significant says which tests it failed
    why = [c["not_significant_because"] for c in rep["ranking"] if not c["significant"]]
    assert why and all(why), rep["ranking"]
    expect(page.locator("#ranking")).to_contain_text("(" + "; ".join(why[-1]) + ")")
    # where the gap lies, per held-out log too, with its share of each channel's squared error
    for name in rep["experiments"]["held_out"]:
        share = round(100 * rep["where"][0]["experiments"][name]["share"])
        expect(page.locator("#where-logs")).to_contain_text(f"{name}")
        expect(page.locator("#where-logs tr", has_text=name)).to_contain_text(f"({share} %)")
    expect(page.locator("#detail")).to_contain_text(
        "heat_transfer's fit, with the effect taken out, still closes 0.202 of the gap: the baseline's own "
        "parameters, refitted beside it, did; the baseline was recalibrated from there and every candidate judged "
        "against that.")
    expect(page.locator("#detail")).to_contain_text(
        "a sensor reading nothing bends the fit to match it): isotonic-1 (torque = 0.00).")
    expect(page.locator("#detail")).to_contain_text("Gap left unexplained with sensor_bias: ")
    # the verdict and every ranked candidate in plain words, the engine's (GET /api/diagnoses/protocol)
    expect(page.locator("#verdict-meaning")).to_have_text("sensor_bias: pressure or torque sensors reading off zero.")
    expect(page.locator("#ranking")).to_contain_text("air leaking across the vane's seal from one chamber to the other")
    # one finding per line, not a run-on paragraph
    expect(page.locator("#detail li", has_text="Held out: ")).to_have_count(1)
    expect(page.locator("#howfar-legend")).to_contain_text("after with sensor_bias")
    expect(page.locator("#ranking")).to_contain_text("(not the verdict: friction_per_direction explains more)")
    expect(page.locator("#detail")).to_contain_text(
        "Or friction_per_direction (friction off per direction) instead of sensor_bias: these logs cannot tell them "
        "apart (gap closure 0.650 against 0.660 for sensor_bias). To tell: tare the sensors.")
    # the station's page shows the protocol's run with a link that takes its experiments' runs here
    page.goto(base)
    page.locator("#runs tbody tr", has_text="Diagnosis protocol on the rig").first.locator("td").nth(2).click()
    expect(page.locator("#last")).to_contain_text(f"Diagnosis protocol {proto['id']}: finished")
    ids = ", ".join(str(i) for i in proto["result"]["run_ids"])
    page.click("#diagnose-runs")
    expect(page.locator("#runids")).to_have_value(ids)
    expect(page.locator("#src")).to_have_value("runs")
    expect(page.locator("#runs")).to_be_visible()
    # a stored diagnosis reopens from the station's history with its whole report
    page.goto(base)
    page.locator(f"#runs tbody tr[data-run='{diag_id}'] td").nth(2).click()
    expect(page.locator("#last")).to_contain_text(f"Gap diagnosis {diag_id}: complete")
    page.click("#open-report")
    expect(page.locator("#msg")).to_contain_text(f"diagnosis {diag_id} complete")
    # the form says what this diagnosis ran on (it had shown the defaults: the simulated protocol)
    with urllib.request.urlopen(f"{base}/api/runs/{diag_id}", timeout=10) as r:
        diag_runs = json.loads(r.read())["spec"]["run_ids"]
    expect(page.locator("#src")).to_have_value("runs")
    expect(page.locator("#runids")).to_have_value(", ".join(str(i) for i in diag_runs))
    expect(page.locator("#runs")).to_be_visible()
    expect(page.locator("#verdict")).to_have_text(" + ".join(stored["verdict"]["effects"]) or "no significant effect")
    from app.engine.params import EFFECT_MEANING

    expect(page.locator("#verdict-meaning")).to_have_text(
        " ".join(f"{e}: {EFFECT_MEANING[e]}." for e in stored["verdict"]["effects"]))
    expect(page.locator("#ranking tr")).to_have_count(1 + len(stored["ranking"]))
    # a run that is not a diagnosis is said to be one, not shown as a failed diagnosis
    page.goto(f"{base}/static/diagnosis.html?report={proto['id']}")
    expect(page.locator("#msg")).to_have_text(f"run {proto['id']} is a diagnosis_protocol run, not a diagnosis")
    # a long diagnosis started by mistake is stopped from the page, which frees the station for the next
    page.goto(base + "/static/diagnosis.html")
    page.fill("#scale", "10")
    expect(page.locator("#dstop")).to_be_hidden()
    page.click("#go")
    expect(page.locator("#msg")).to_contain_text("running", timeout=30_000)
    expect(page.locator("#dstop")).to_be_visible()
    page.click("#dstop")
    expect(page.locator("#msg")).to_contain_text("stopped: ", timeout=30_000)
    expect(page.locator("#msg")).to_contain_text("(stopped on request)")
    expect(page.locator("#dstop")).to_be_hidden()
    # reopened, the stopped one shows the simulated protocol it was asked for, at 10 × its length
    with urllib.request.urlopen(base + "/api/runs?kind=diagnosis&limit=1", timeout=10) as r:
        stopped_id = json.loads(r.read())[0]["id"]
    page.goto(base + "/static/diagnosis.html")
    expect(page.locator("#scale")).to_have_value("1")
    page.goto(f"{base}/static/diagnosis.html?report={stopped_id}")
    expect(page.locator("#msg")).to_contain_text(f"diagnosis {stopped_id} stopped: ")
    expect(page.locator("#src")).to_have_value("protocol")
    expect(page.locator("#scale")).to_have_value("10")
    expect(page.locator("#effects input:checked")).to_have_count(0)
    expect(page.locator("#tried-effects input:checked")).to_have_count(9)  # it was asked with all nine
    assert not errors, errors


_SLOW_SERVER = """
// every poll's answer arrives late (a loaded server); count the requests in flight per path
window.__inflight = {}; window.__maxInflight = {};
const fetch0 = window.fetch.bind(window);
window.fetch = async (url, opts) => {
  const path = String(url).split('?')[0];
  if (path !== '/api/live' && path !== '/api/engine') return fetch0(url, opts);
  window.__inflight[path] = (window.__inflight[path] || 0) + 1;
  window.__maxInflight[path] = Math.max(window.__maxInflight[path] || 0, window.__inflight[path]);
  try {
    await new Promise(r => setTimeout(r, path === '/api/live' ? 350 : 1200));
    return await fetch0(url, opts);
  } finally { window.__inflight[path] -= 1; }
};
"""


def test_a_slow_server_gets_one_poll_at_a_time_and_the_plot_holds_each_sample_once(
        station: tuple[str, str], browser: object) -> None:
    """A loaded server answers late: the dashboard must not pile up requests on it.

    With ``setInterval`` a 100 ms poll answered in 350 ms had four requests in
    flight; answers arrived out of order, the plot appended the same samples
    twice, and a late empty answer reset it and refetched 3000 rows.
    """
    import itertools

    from playwright.sync_api import Browser

    assert isinstance(browser, Browser)
    base, _viser = station

    def call(method: str, path: str, body: dict[str, object] | None = None) -> dict[str, Any]:
        return _call(base, method, path, body)

    _connected_and_idle(base)
    page = browser.new_page(viewport={"width": 1200, "height": 800})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.add_init_script(_SLOW_SERVER)
    page.goto(base)
    call("POST", "/api/engine/start", {"scenario": "SC-1", "controller": "pid", "target_nm": 1.2})
    try:
        page.wait_for_function("Number(document.getElementById('c-torque').dataset.samples || 0) > 0",
                               timeout=10000)
        page.wait_for_timeout(4000)
        most = page.evaluate("window.__maxInflight")
        assert most == {"/api/live": 1, "/api/engine": 1}, most
        t = page.evaluate("live.map(r => r[0])")
        assert len(t) > 200 and all(b > a for a, b in itertools.pairwise(t)), t[:20]
    finally:
        if call("GET", "/api/engine")["state"] == "running":
            call("POST", "/api/engine/stop")
        page.close()
    assert not errors, errors


@pytest.mark.parametrize("width", [390, 820])
def test_on_a_phone_or_tablet_both_pages_fit_and_the_stop_buttons_stay_on_screen(
        station: tuple[str, str], browser: object, width: int) -> None:
    """At 390 px the second column and E-STOP had been pushed past the screen's right edge."""
    from playwright.sync_api import Browser, expect

    assert isinstance(browser, Browser)
    base, _viser = station
    page = browser.new_page(viewport={"width": width, "height": 800})
    try:
        overflow = "() => document.scrollingElement.scrollWidth - window.innerWidth"

        def stop_buttons_on_screen() -> None:
            for button in ("#stop", "#estop"):
                box = page.locator(button).bounding_box()
                assert box is not None and box["x"] >= 0 and box["x"] + box["width"] <= width, (button, box)
                assert box["y"] + box["height"] <= 800, (button, box)  # in the header, before any scrolling

        page.goto(base + "/")
        expect(page.locator("#state")).not_to_have_text("…")
        assert page.evaluate(overflow) <= 0, page.evaluate(overflow)
        stop_buttons_on_screen()
        _accessible(page, f"the dashboard {width} px wide")
        if width < 720:
            # one column in an exercise's order: the live charts right after the exercise form, the
            # identification and tuning forms after the history
            ys = {name: page.locator(sel).bounding_box()["y"]  # type: ignore[index]
                  for name, sel in (("exercise", "#start"), ("live", "#c-torque"), ("history", "#runs"),
                                    ("identification", "#ident-title"), ("tuning", "#tune-pid"))}
            assert ys["exercise"] < ys["live"] < ys["history"] < ys["identification"] < ys["tuning"], ys
            # a chart is drawn at the size it is shown, not squeezed from 900 px (its labels with it)
            sizes = page.evaluate("""() => { const c = document.getElementById('c-torque');
                draw(c, [[1, '#1f77b4']], -0.2, 0.2, [[0, 0.1], [1, -0.1]]);
                return [c.width, c.clientWidth, c.height, c.clientHeight]; }""")
            assert sizes[0] == sizes[1] < 400 and sizes[2] == sizes[3], sizes
            # the header in two rows whatever the state says: the title, then the page link, the
            # state and both stop buttons (with the longest state label the station shows)
            page.evaluate("() => { document.getElementById('state').textContent = 'disconnected'; }")
            row = [page.locator(sel).bounding_box() for sel in ("header > a", "#state", "#stop", "#estop")]
            mids = [b["y"] + b["height"] / 2 for b in row if b is not None]
            assert len(mids) == 4 and max(mids) - min(mids) < 8, row
            assert row[-1]["x"] + row[-1]["width"] <= width, row  # type: ignore[index]
        # and still there once the page is scrolled down to the history (the header stays on top)
        page.locator("#runs").scroll_into_view_if_needed()
        box = page.locator("#estop").bounding_box()
        assert box is not None and 0 <= box["y"] and box["y"] + box["height"] <= 800, box
        page.goto(base + "/static/diagnosis.html")
        expect(page.locator("#protocol tr").nth(1)).to_be_visible()  # built from the server's table
        expect(page.locator("#state")).not_to_have_text("…")
        assert page.evaluate(overflow) <= 0, page.evaluate(overflow)
        stop_buttons_on_screen()  # the diagnosis page has them too (it runs its protocol on the rig)
        _accessible(page, f"the diagnosis page {width} px wide")
    finally:
        page.close()


def test_the_diagnosis_page_shows_the_engine_and_stops_it_from_its_header(station: tuple[str, str],
                                                                         browser: object) -> None:
    """The gap diagnosis runs its protocol on the connected rig, perhaps with a person's arm in it, and its
    page had no state, no STOP and no E-STOP: stopping the rig meant going back to the Station page
    (issue 7: an always-visible emergency stop)."""
    from playwright.sync_api import Browser, expect

    assert isinstance(browser, Browser)
    base, _viser = station
    _connected_and_idle(base)
    page = browser.new_page(viewport={"width": 1200, "height": 800})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    exercise = {"scenario": "SC-1", "controller": "pid", "target_nm": 1.2}
    try:
        page.goto(base + "/static/diagnosis.html")
        expect(page.locator("#state")).to_have_text("idle")
        expect(page.locator("#stop")).to_be_disabled()  # nothing to stop
        expect(page.locator("#estop")).to_be_enabled()
        # the state follows what the station does, whoever started it
        run_id = _call(base, "POST", "/api/engine/start", exercise)["run_id"]
        expect(page.locator("#state")).to_have_text("running")
        _accessible(page, "the diagnosis page while the rig runs")  # the green badge had read 4.4 : 1
        page.click("#stop")
        expect(page.locator("#state")).to_have_text("idle")
        assert _call(base, "GET", f"/api/runs/{run_id}")["status"] == "stopped"
        # E-STOP on screen with the page scrolled to its end, and it latches the fault from a run
        _call(base, "POST", "/api/engine/start", exercise)
        expect(page.locator("#state")).to_have_text("running")
        # a press the station does not confirm says so, and the next polls' "running" does not hide it
        unconfirmed = "E-STOP NOT CONFIRMED: the station could not latch it (test)"
        page.route("**/api/engine/estop", lambda route: route.fulfill(
            status=500, content_type="application/json", body='{"detail": "the station could not latch it (test)"}'))
        page.click("#estop")
        expect(page.locator("#state")).to_have_text(unconfirmed)
        page.wait_for_timeout(2200)  # two of the page's polls, each answered "running"
        expect(page.locator("#state")).to_have_text(unconfirmed)
        page.unroute("**/api/engine/estop")
        page.locator("#protocol tr").last.scroll_into_view_if_needed()
        assert page.evaluate("window.scrollY") > 0
        box = page.locator("#estop").bounding_box()
        assert box is not None and 0 <= box["y"] and box["y"] + box["height"] <= 800, box
        page.click("#estop")
        expect(page.locator("#state")).to_have_text("fault")
        # what latched it, on the badge: the diagnosis page has no other place to say it
        expect(page.locator("#state")).to_have_attribute(
            "title", "emergency stop (API): latched until cleared on the Station page")
        st = _call(base, "GET", "/api/engine")
        assert st["state"] == "fault" and st["fault"] == "emergency stop (API)", st
        expect(page.locator("#stop")).to_be_disabled()
        expect(page.locator("#estop")).to_be_enabled()  # pressed again, it still answers
        _accessible(page, "the diagnosis page with a fault latched")
    finally:
        if _call(base, "GET", "/api/engine")["state"] == "fault":
            _call(base, "POST", "/api/engine/clear")
        page.close()
    assert not errors, errors


def test_a_running_diagnosis_shows_what_it_is_doing(station: tuple[str, str], browser: object) -> None:
    """The page said "running (roughly 15–30 s per 83 s of logs …)" for as long as a diagnosis took; it now
    shows the run's ``progress`` from each poll, and a stop asked for stays said until the run has ended."""
    from playwright.sync_api import Browser, expect

    assert isinstance(browser, Browser)
    base, _viser = station
    page = browser.new_page(viewport={"width": 1200, "height": 800})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    said = ["recalibrating the baseline on 7 logs"]
    run = {"id": 4243, "kind": "diagnosis", "status": "running", "started": 1.0, "ended": None, "spec": {},
           "metrics": None, "result": None, "person": "", "notes": "", "has_series": False}
    page.route("**/api/runs/4243", lambda route: route.fulfill(json=run | {"progress": said[-1]}))
    page.route("**/api/diagnoses/4243/stop", lambda route: route.fulfill(json=run))
    try:
        page.goto(base + "/static/diagnosis.html?report=4243")
        expect(page.locator("#msg")).to_have_text("diagnosis 4243 running: recalibrating the baseline on 7 logs…")
        said.append("candidate 4 of 9 fitted (heat_transfer)")
        expect(page.locator("#msg")).to_have_text("diagnosis 4243 running: candidate 4 of 9 fitted (heat_transfer)…")
        page.click("#dstop")
        expect(page.locator("#msg")).to_have_text("stopping diagnosis 4243…")
        _accessible(page, "a diagnosis being stopped")
        said.append("candidate 5 of 9 fitted (tube_dynamics)")
        page.wait_for_timeout(1700)  # one more poll, answered "running" with news: the stop stays said
        expect(page.locator("#msg")).to_have_text("stopping diagnosis 4243…")
    finally:
        page.close()
    assert not errors, errors
