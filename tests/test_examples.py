"""The scripting example the README points researchers to runs as written against a served station."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ServedStation

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"


def _run(script: str, *args: str) -> subprocess.CompletedProcess[str]:
    # as a researcher's copy of the folder would run, from elsewhere: no PYTHONPATH, no user site
    # packages, nothing of the project importable but the client beside the script
    return subprocess.run([sys.executable, "-E", "-s", str(EXAMPLES / script), *args], capture_output=True,
                          text=True, timeout=240, cwd="/")


@pytest.mark.slow
def test_the_rest_example_runs_an_exercise_and_saves_its_log(tmp_path: Path) -> None:
    srv = ServedStation(tmp_path / "station", CWRR_AUTO_CONNECT="false")
    try:
        log = tmp_path / "run.csv"
        out = _run("exercise_over_rest.py", "--station", srv.url, "--person", "P-017", "--csv", str(log))
        assert out.returncode == 0, (out.stdout, out.stderr)
        lines = out.stdout.splitlines()
        # it connected the station itself (it started disconnected) and ran the thesis's SC-1 with the
        # station's default controller
        assert lines[0] == "run 1 started: SC-1, fuzzy, 1.2 N·m", lines
        assert any(line.strip().startswith("t = ") and "interaction torque" in line for line in lines), lines
        run = srv.api("GET", "/api/runs/1")
        assert run["status"] == "complete" and run["person"] == "P-017"
        assert "run 1: complete" in lines
        # the six metrics printed are the stored ones
        for key, name in (("mae", "MAE [N·m]"), ("rmse", "RMSE [N·m]"), ("maxae", "Max AE [N·m]")):
            assert f"  {name:15s} {run['metrics'][key]:.4g}" in lines, (key, lines)
        lo, hi = run["result"]["angle_range_deg"]
        assert f"  range of motion {lo:.0f}° … {hi:.0f}° (positive: pronation)" in lines
        # the log saved is the station's log format, every stored sample
        with log.open() as f:
            rows = list(csv.reader(f))
        assert rows[0] == ["t", "z_a", "z_b", "u_a", "u_b", "p_a", "p_b", "p_s", "theta", "omega", "torque"]
        assert len(rows) - 1 == srv.api("GET", "/api/runs/1/series?every=10000")["rows_total"]

        # a refused request ends it with the station's own words and nothing is started
        bad = _run("exercise_over_rest.py", "--station", srv.url, "--target", "9")
        assert bad.returncode == 1 and bad.stdout == ""
        assert bad.stderr.startswith("refused: POST /api/engine/start → 422: target_nm: "), bad.stderr
        assert "less than or equal to 3" in bad.stderr
        assert [r["id"] for r in srv.api("GET", "/api/runs")] == [1]
    finally:
        srv.stop()
    # a station that is not there is said in a line, not a traceback
    gone = _run("exercise_over_rest.py", "--station", srv.url)
    assert gone.returncode == 1 and gone.stderr.startswith(f"refused: the station at {srv.url} did not answer")


@pytest.mark.slow
def test_the_diagnosis_example_sends_a_rigs_logs_and_prints_the_verdict(tmp_path: Path) -> None:
    import json

    from app.cli import main as cli_main

    logs = tmp_path / "logs"
    assert cli_main(["protocol", str(logs), "--effect", "vane_leakage:2"]) == 0  # a rig whose vane leaks
    srv = ServedStation(tmp_path / "station", CWRR_AUTO_CONNECT="false")
    try:
        report = tmp_path / "report.json"
        out = _run("diagnose_over_rest.py", str(logs), "--station", srv.url, "--effects",
                   "vane_leakage,external_leakage,sensor_bias", "--json", str(report))
        assert out.returncode == 0, (out.stdout, out.stderr)
        lines = out.stdout.splitlines()
        assert lines[0] == "14 logs stored as runs 1–14; diagnosing"
        assert "  recalibrating the baseline on 7 logs" in lines  # what the station was doing, as it did it
        rep = json.loads(report.read_text())
        assert rep == srv.api("GET", f"/api/runs/{rep['run_id']}/report") | {"run_id": rep["run_id"]}
        assert rep["verdict"]["effects"] == ["vane_leakage"]
        i = lines.index(f"diagnosis {rep['run_id']}: {rep['verdict']['summary']}")
        assert lines[i + 1].startswith(f"  error before {rep['how_far']['e_before']:.4g}, ")
        # the ranking's head, three candidates tried: three lines
        assert lines[i + 2:] == [f"  {c['effect']:20s} GC {c['gap_closure']:+.3f}  "
                                 f"{'significant' if c['significant'] else 'not significant'}" for c in rep["ranking"]]
        assert lines[i + 2].startswith(f"  {'vane_leakage':20s} GC +0.9") and lines[i + 2].endswith("  significant")
        # a log the station refuses stops it with the station's reason, before anything is diagnosed
        bad = tmp_path / "bad"
        bad.mkdir()
        for name in ("prv_steps-1", "prv_steps-2"):
            for ext in (".json", ".csv"):
                (bad / (name + ext)).write_text((logs / (name + ext)).read_text())
        text = (bad / "prv_steps-2.csv").read_text().splitlines()
        (bad / "prv_steps-2.csv").write_text("\n".join([text[0].replace("torque", "force"), *text[1:]]))
        runs_before = len(srv.api("GET", "/api/runs?limit=200"))
        refused = _run("diagnose_over_rest.py", str(bad), "--station", srv.url)
        assert refused.returncode == 1, (refused.stdout, refused.stderr)
        assert refused.stderr.startswith("refused: POST /api/runs → 422: "), refused.stderr
        assert "prv_steps-2" in refused.stderr
        kinds = [r["kind"] for r in srv.api("GET", "/api/runs?limit=200")]
        assert len(kinds) == runs_before + 1 and kinds[0] == "imported"  # the good log only, nothing diagnosed
    finally:
        srv.stop()
