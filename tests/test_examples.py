"""The scripting example the README points researchers to runs as written against a served station."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ServedStation

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "exercise_over_rest.py"


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    # in a clean interpreter, as a researcher's copy of the file would run: nothing of the project imported
    return subprocess.run([sys.executable, "-I", str(EXAMPLE), *args], capture_output=True, text=True,
                          timeout=240, cwd="/")


@pytest.mark.slow
def test_the_rest_example_runs_an_exercise_and_saves_its_log(tmp_path: Path) -> None:
    srv = ServedStation(tmp_path / "station", CWRR_AUTO_CONNECT="false")
    try:
        log = tmp_path / "run.csv"
        out = _run("--station", srv.url, "--person", "P-017", "--csv", str(log))
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
        bad = _run("--station", srv.url, "--target", "9")
        assert bad.returncode == 1 and bad.stdout == ""
        assert bad.stderr.startswith("refused: POST /api/engine/start → 422: target_nm: "), bad.stderr
        assert "less than or equal to 3" in bad.stderr
        assert [r["id"] for r in srv.api("GET", "/api/runs")] == [1]
    finally:
        srv.stop()
    # a station that is not there is said in a line, not a traceback
    gone = _run("--station", srv.url)
    assert gone.returncode == 1 and gone.stderr.startswith(f"refused: the station at {srv.url} did not answer")
