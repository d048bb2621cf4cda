"""The command line and the server's contract."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.api.main import create_app
from app.api.models import attribute_docs
from app.api.settings import Settings
from app.engine.loop import GIL_SWITCH_S


def _cwrr(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "app", *args], capture_output=True, text=True, timeout=300)


def test_sim_prints_json_summary() -> None:
    r = _cwrr("sim", "--duration", "10", "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    # speed is bench/'s to report: a cold numba cache (any change to app/ re-keys it) compiles for > 10 s here
    assert s["samples"] == 2000 and s["real_time_factor"] == pytest.approx(10.0 / s["wall_s"])
    assert 0.5 < s["torque_abs_mean_active_nm"] < 2.0


def test_sim_refuses_bad_pressure_with_gui_message() -> None:
    r = _cwrr("sim", "--pw", "9")
    assert r.returncode == 2
    assert "Working pressure can be min. 1 bar and max. 8 bar!" in r.stderr


def test_sim_writes_run_log(tmp_path: Path) -> None:
    r = _cwrr("sim", "--duration", "2", "--log-dir", str(tmp_path), "--name", "w1", "--json")
    assert r.returncode == 0, r.stderr
    head = (tmp_path / "w1.csv").read_text().splitlines()[0]
    assert head == "t,z_a,z_b,u_a,u_b,p_a,p_b,p_s,theta,omega,torque"
    meta = json.loads((tmp_path / "w1.json").read_text())
    assert meta["rig"] == "rotary" and meta["human"] is True


def test_sim_runs_one_scenario_with_one_controller_as_the_thesis_bench_scores_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`cwrr sim --scenario`: one of SPEC §5's cases in a fraction of a second, its metrics those of
    ``bench thesis``'s run of the same case; a case outside the twelve (SC-1 at −0.9 N·m) runs too."""
    from app.cli import SIM_CONTROLLERS, SIM_SCENARIOS, main
    from app.engine.diagnosis.logs import read_log
    from app.engine.scenarios import CONTROLLERS, SCENARIOS, Case, run_case

    assert SIM_SCENARIOS == SCENARIOS and SIM_CONTROLLERS == CONTROLLERS  # the parser's copies
    assert main(["sim", "--scenario", "SC-4", "--controller", "fuzzy", "--json", "--log-dir", str(tmp_path),
                 "--name", "sc4"]) == 0
    out = json.loads(capsys.readouterr().out)
    ref = run_case(Case("SC-4", 1.2, True, True), "fuzzy", seed=0)
    assert out["metrics"] == pytest.approx(ref.metrics) and out["t_d_s"] == ref.t_d
    assert (out["pdra"], out["tdra"], out["direction"]) == (True, True, "FP")
    log = read_log(tmp_path / "sc4")  # the run's log, in the format a diagnosis reads
    assert log.meta["scenario"] == "SC-4" and log.meta["controller"] == "fuzzy"
    assert main(["sim", "--scenario", "SC-1", "--target", "-0.9", "--controller", "default", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["pdra"], out["direction"]) == (False, "FS") and 0.0 < out["metrics"]["mae"] < 0.9
    # what does not go together is refused, naming why
    for argv, words in ((["--scenario", "SC-2", "--duration", "5"], "the scenario sets its length"),
                        (["--target", "1.0"], "--controller and --target go with --scenario"),
                        (["--scenario", "SC-2", "--target", "9"], "target = 9.0 N·m is outside"),
                        (["--scenario", "SC-2", "--target", "0"], "needs a torque to work against")):
        assert main(["sim", *argv]) == 2, argv
        assert words in capsys.readouterr().err, argv


@pytest.mark.parametrize("argv", [["sim", "--seed", "-1"], ["bench", "thesis", "--seed", "x"],
                                  ["identify", "rotary", "--seed", "-2"], ["protocol", "logs", "--seed", "-3"],
                                  ["modbus-plant", "--port", "-5"], ["modbus-plant", "--port", "70000"]])
def test_a_seed_or_port_that_cannot_be_one_is_refused_naming_the_argument(
        argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """A negative seed reached numpy, which answered "expected non-negative integer" without saying which
    argument; a negative port started a Modbus plant on modbus://127.0.0.1:-5."""
    from app.cli import main

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    flag = argv[-2]
    assert f"argument {flag}: '{argv[-1]}' is not a " in err, err
    assert list(tmp_path.iterdir()) == []  # nothing written


@pytest.mark.parametrize(("argv", "words"), [
    (["identify", "sweep", "--table", "missing/table.json"], "--table missing/table.json: the folder missing does not"),
    (["identify", "rotary", "--out", "afile/out"], "--out afile/out: afile is not a folder that can be written"),
    (["bench", "thesis", "--out", "afile"], "--out afile: afile is not a folder that can be written"),
    (["sim", "--duration", "1", "--log-dir", "afile"], "--log-dir afile: afile is not a folder that can be written"),
])
def test_where_a_command_writes_is_checked_before_it_runs(argv: list[str], words: str, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str],
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """A friction sweep with its table going to a missing folder ran to its end, then failed writing it."""
    from app.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("")
    assert main(argv) == 2
    assert words in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]  # nothing written


def test_an_exercise_with_no_controller_chosen_runs_one_that_does_not_chatter(
        capsys: pytest.CaptureFixture[str]) -> None:
    """What a therapist gets by pressing start: the API's, the station's and ``cwrr sim``'s default
    controller is one thing, and on the simulated rig it leaves no pressure toggle to warn about (Eq 3.26's
    Cascade PID, the default until the fifty-third session, toggles chamber b by ±0.14–0.24 bar in SC-1,
    docs/controllers.md)."""
    from app.api.models import RunRequest
    from app.cli import main
    from app.engine.metrics import TOGGLE_WARN_BAR
    from app.engine.station import RunSpec

    assert main(["sim", "--scenario", "SC-1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["controller"] == RunRequest.model_validate({}).controller == RunSpec().controller
    assert max(out["pressure_toggle_bar"].values()) < TOGGLE_WARN_BAR, out["pressure_toggle_bar"]
    page = (Path(__file__).parents[1] / "app" / "static" / "index.html").read_text()
    assert f'<option value="{out["controller"]}" selected>' in page  # the dashboard's picker starts on it too
    assert main(["sim", "--scenario", "SC-1", "--controller", "pid", "--json"]) == 0  # the toggle is there to see
    assert max(json.loads(capsys.readouterr().out)["pressure_toggle_bar"].values()) > TOGGLE_WARN_BAR


def test_health_and_openapi_with_lifespan(tmp_path: Path) -> None:
    app = create_app(Settings(rate_hz=200.0, data_dir=str(tmp_path), viser_port=0))
    with TestClient(app) as c:
        import time

        deadline = time.monotonic() + 60.0
        h = c.get("/api/health").json()
        while h["ticks"] <= 10 and time.monotonic() < deadline:
            time.sleep(0.1)
            h = c.get("/api/health").json()
        assert h["state"] == "idle" and h["backend"] == "sim" and h["ticks"] > 10
        assert "jitter_p99_ms" in h and "overruns" in h
        # the paced loop shortened the lock's switch interval, and connecting froze the start-up heap
        assert 0.0 < h["switch_interval_ms"] <= GIL_SWITCH_S * 1e3 + 1e-9
        assert h["heap_frozen"] > 10_000
        assert "/api/health" in c.get("/openapi.json").json()["paths"]
        assert c.get("/").status_code == 200


def test_every_field_of_the_api_says_what_it_is_in_the_openapi_schema(tmp_path: Path) -> None:
    # a researcher scripting the API reads /docs; the docstrings' Attributes are the text
    app = create_app(Settings(data_dir=str(tmp_path), viser_port=0))
    spec = app.openapi()
    schemas = spec["components"]["schemas"]
    params = [(f"{m} {path}", p) for path, ops in spec["paths"].items() for m, op in ops.items()
              for p in op.get("parameters", []) if p["in"] != "header"]
    assert len(params) > 15
    assert not [(where, p["name"]) for where, p in params if not (p.get("description") or "").strip()]
    ours = {n: s for n, s in schemas.items() if n not in ("HTTPValidationError", "ValidationError")}
    assert len(ours) > 30
    bare = [f"{n}.{f}" for n, s in ours.items() for f, p in (s.get("properties") or {}).items()
            if not (p.get("description") or "").strip()]
    assert not bare, bare
    target = schemas["RunRequest"]["properties"]["target_nm"]
    assert "[N·m]" in target["description"] and target["maximum"] == 3.0  # the docstring's, the limits kept


def test_every_operation_says_what_it_does_beyond_its_summary(tmp_path: Path) -> None:
    """A researcher reading /docs sees what each call does, not only its one-line summary: every
    operation's handler carries a description (20 of 40 had none)."""
    app = create_app(Settings(data_dir=str(tmp_path), viser_port=0, auto_connect=False))
    bare = [f"{m.upper()} {p}" for p, ops in app.openapi()["paths"].items() for m, op in ops.items()
            if not op.get("summary") or len(op.get("description", "")) < 40]
    assert not bare, bare


def test_each_operation_has_a_short_unique_id_a_generated_client_can_name_its_method_by(tmp_path: Path) -> None:
    """FastAPI's default ids repeated the path and the method (``list_runs_api_runs_get``); a client
    generated from the document named its methods so."""
    spec = create_app(Settings(data_dir=str(tmp_path), viser_port=0, auto_connect=False)).openapi()
    ids = {(m.upper(), p): op["operationId"] for p, ops in spec["paths"].items() for m, op in ops.items()}
    assert len(set(ids.values())) == len(ids) > 30
    assert ids[("GET", "/api/runs")] == "runs-list_runs" and ids[("GET", "/api/engine")] == "engine-status"
    assert ids[("POST", "/api/engine/start")] == "engine-start" and ids[("POST", "/api/diagnoses")] == "diagnoses-start"
    assert not [i for i in ids.values() if "_api_" in i or i.endswith(("_get", "_post", "_patch"))], ids
    # and /docs says what each group of calls is for
    used = {t for ops in spec["paths"].values() for op in ops.values() for t in op["tags"]}
    described = {t["name"] for t in spec["tags"] if len(t.get("description", "")) > 30}
    assert used <= described, used - described


def test_the_document_lists_what_each_call_can_answer_and_no_more(tmp_path: Path) -> None:
    """The export had listed a JSON answer it never gives, and every GET the 400 and 413 of a body it
    cannot have."""
    spec = create_app(Settings(data_dir=str(tmp_path), viser_port=0, auto_connect=False)).openapi()
    export = spec["paths"]["/api/runs/{run_id}/export"]["get"]["responses"]["200"]["content"]
    assert set(export) == {"text/csv", "application/vnd.apache.parquet", "application/x-matlab-data"}
    ops = [op for ops in spec["paths"].values() for op in ops.values()]
    assert not [op["operationId"] for op in ops if "requestBody" not in op and {"400", "413"} & set(op["responses"])]
    with_body = [op for op in ops if "requestBody" in op]
    assert len(with_body) > 10 and all({"400", "413"} <= set(op["responses"]) for op in with_body)


def test_the_api_docs_pages_load_their_scripts_from_the_station_not_a_cdn(tmp_path: Path) -> None:
    """A station beside a rig is often offline: /docs and /redoc loaded Swagger UI and ReDoc from
    cdn.jsdelivr.net (and fonts from Google) and stayed blank there. Every file they load now comes
    from the station itself, and each answers."""
    import re

    c = TestClient(create_app(Settings(data_dir=str(tmp_path), viser_port=0, auto_connect=False)))
    for page, needs in (("/docs", ("swagger-ui-bundle.js", "swagger-ui.css")), ("/redoc", ("redoc.standalone.js",))):
        r = c.get(page)
        assert r.status_code == 200 and "text/html" in r.headers["content-type"], page
        refs = re.findall(r"""(?:src|href|url)\s*[=:]\s*['"]([^'"]+)['"]""", r.text)
        assert not [u for u in refs if "//" in u], (page, refs)  # no other host, no scheme-relative URL
        for name in needs:
            assert any(u.endswith("/" + name) for u in refs), (page, name, refs)
        for u in refs:
            if u.startswith("/") and u != "/openapi.json":
                asset = c.get(u)
                assert asset.status_code == 200 and len(asset.content) > 100, (page, u, asset.status_code)
        assert "fonts.googleapis.com" not in r.text, page


def test_attribute_docs_reads_a_google_style_attributes_section() -> None:
    doc = """A model.

    Longer text.

    Attributes:
        alpha: First [s].
        beta_x (float): Second, which goes on
            over two lines: with a colon.
        gamma: Third.

    Example:
        not: an attribute.
    """
    assert attribute_docs(doc) == {"alpha": "First [s].",
                                   "beta_x": "Second, which goes on over two lines: with a colon.",
                                   "gamma": "Third."}
    assert attribute_docs("No sections.") == {} and attribute_docs(None) == {}


def test_ctrl_c_ends_a_command_with_one_line_and_exit_130(
        capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A diagnosis stopped with Ctrl-C had ended in a KeyboardInterrupt traceback from a thread pool's wait."""
    from app import cli

    def interrupted(args: object) -> int:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_diagnose", interrupted)
    assert cli.main(["diagnose", str(tmp_path)]) == 130
    assert capsys.readouterr().err == "cwrr diagnose: stopped\n"


def test_a_result_is_printed_for_a_person_as_key_value_lines() -> None:
    """`cwrr identify pid` printed its note as JSON, ω as \\u03c9 and ° as \\u00b0; a result without --json now
    reads as lines, nested ones indented, numbers to four digits and what a fit could not give as a dash."""
    from app.cli import human

    text = human({"Ki": 1.96480599, "note": "G(jω_c) lags 1.8°", "ok": False, "sd": float("nan"), "us": 94933.67,
                  "thesis": {"mae": 0.043, "p_bar": [0.99358, 2.98141]}, "none": None})
    assert text.splitlines() == ["Ki: 1.965", "note: G(jω_c) lags 1.8°", "ok: false", "sd: —", "us: 94934", "thesis:",
                                 "  mae: 0.043", "  p_bar: 0.9936, 2.981", "none: —"]


def test_a_friction_sweep_is_printed_as_the_thesis_lays_out_table_4_2() -> None:
    """A row per working pressure, each direction's T_s, T_c, ω_s and B across: the --json table's numbers."""
    from app.cli import sweep_table

    table = {"pw_bar": [2.0, 3.0], **{f"{k}_{d}": [s * 0.1 * (i + 1), s * 0.2 * (i + 1)]
                                      for i, k in enumerate(("ts", "tc", "ws", "b"))
                                      for d, s in (("ccw", 1.0), ("cw", -1.0))}}
    head, *rows = sweep_table(table).splitlines()
    assert head.split() == ["P_w", "[bar]", "T_s+", "[N·m]", "T_c+", "[N·m]", "ω_s+", "[rad/s]", "B+", "[N·m·s/rad]",
                            "T_s−", "[N·m]", "T_c−", "[N·m]", "ω_s−", "[rad/s]", "B−", "[N·m·s/rad]"]
    assert [r.split() for r in rows] == [["2", "0.1", "0.2", "0.3", "0.4", "-0.1", "-0.2", "-0.3", "-0.4"],
                                         ["3", "0.2", "0.4", "0.6", "0.8", "-0.2", "-0.4", "-0.6", "-0.8"]]
