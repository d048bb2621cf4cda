"""Run logs recorded elsewhere, uploaded through the API (issue 6's format, issue 7's upload limit).

A researcher with logs from a rig (or another station) posts each ``NAME.csv`` + ``NAME.json`` pair
to ``POST /api/runs``; the log is checked like ``cwrr diagnose`` checks a directory, stored as
a run, and can then be plotted, exported and diagnosed by run id.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.api.main import create_app
from app.api.settings import Settings
from app.engine.diagnosis.logs import read_log
from app.engine.sim import LOG_COLUMNS, run_workout


def _app(tmp_path: Path, **kw: Any) -> Any:
    return create_app(Settings(data_dir=str(tmp_path), viser_port=0, auto_connect=False, **kw))


@pytest.fixture()
def client(tmp_path: Path) -> Iterator[TestClient]:
    with TestClient(_app(tmp_path)) as c:
        yield c


META = {"rig": "rotary", "sample_rate_hz": 200.0, "p_atm_bar": 1.01325, "working_pressure_bar": 3.0,
        "experiment": "workout", "human": True}


def _log(seconds: float = 2.0) -> np.ndarray:
    return run_workout(duration=seconds).log


def _csv(data: np.ndarray, header: str = ",".join(LOG_COLUMNS)) -> str:
    return header + "\n" + "\n".join(",".join(f"{v:.9g}" for v in row) for row in data) + "\n"


def _imported(client: TestClient) -> list[dict[str, Any]]:
    r = client.get("/api/runs", params={"kind": "imported"})
    assert r.status_code == 200
    return list(r.json())


def test_an_uploaded_log_is_stored_as_a_run_with_its_series_and_exports(client: TestClient, tmp_path: Path) -> None:
    data = _log()
    r = client.post("/api/runs", json={"name": "rig-isotonic-1", "meta": META, "csv": _csv(data),
                                              "notes": "from the lab's own DAQ"})
    assert r.status_code == 201, r.text
    run = r.json()
    assert run["kind"] == "imported" and run["status"] == "complete" and run["has_series"]
    assert run["result"]["rows"] == len(data) and run["result"]["duration_s"] == pytest.approx(data[-1, 0])
    assert run["notes"] == "from the lab's own DAQ"
    s = client.get(f"/api/runs/{run['id']}/series").json()
    assert s["columns"] == list(LOG_COLUMNS)
    np.testing.assert_allclose(np.asarray(s["rows"]), data, rtol=1e-8, atol=1e-12)
    assert s["meta"] == META
    assert client.get(f"/api/runs/{run['id']}/export", params={"fmt": "mat"}).status_code == 200
    # on disk it is a log pair in the fixed format, under the name it was given
    files = sorted((tmp_path / "imported").rglob("rig-isotonic-1.*"))
    assert [f.suffix for f in files] == [".csv", ".json"]
    exp = read_log(files[0])
    assert exp.name == "rig-isotonic-1" and exp.meta == META


def test_a_header_key_beyond_the_fixed_ones_that_is_nan_reads_back_as_null(client: TestClient) -> None:
    # Python's JSON reader takes NaN, which no JSON answer may carry: the run, its list and its series
    # still answer (the value as null), and the series keeps the rest of the header for its plot
    body = json.dumps({"name": "nan-note", "meta": META | {"ambient_c": float("nan")}, "csv": _csv(_log(0.5))})
    r = client.post("/api/runs", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 201, r.text
    run_id = r.json()["id"]
    assert client.get(f"/api/runs/{run_id}").json()["spec"]["meta"]["ambient_c"] is None
    assert client.get("/api/runs").status_code == 200
    s = client.get(f"/api/runs/{run_id}/series", params={"max_rows": 10})
    assert s.status_code == 200 and s.json()["meta"] == META | {"ambient_c": None}


@pytest.mark.parametrize(("change", "field", "words"), [
    ({"name": "../../etc/passwd"}, "name", "pattern"),
    ({"csv": "t,z_a,z_b\n0,1,2\n"}, "csv", "missing column(s) u_a"),
    ({"csv": "NAN"}, "csv", "row 2, column p_a is nan"),
    ({"csv": "PA"}, "csv", "looks like Pa"),
    ({"csv": "SLOW"}, "csv", "sample_rate_hz = 200"),
    ({"csv": "RAGGED"}, "csv", "is not 11 numbers"),
    ({"csv": "SEMICOLONS"}, "csv", "the columns are separated by semicolons; the format wants commas"),
    ({"meta": {k: v for k, v in META.items() if k != "human"}}, "meta", "missing key(s) human"),
    ({"meta": META | {"rig": "pendulum"}}, "meta", "'rotary' or 'linear'"),
])
def test_a_bad_log_is_refused_with_the_problem_and_leaves_nothing(client: TestClient, tmp_path: Path,
                                                                  change: dict[str, Any], field: str,
                                                                  words: str) -> None:
    data = _log(0.5)
    body: dict[str, Any] = {"name": "bad", "meta": META, "csv": _csv(data)}
    csv = change.get("csv")
    if csv == "NAN":
        data[1, LOG_COLUMNS.index("p_a")] = np.nan
        change = {"csv": _csv(data)}
    elif csv == "PA":
        data[:, LOG_COLUMNS.index("p_a")] *= 1e5
        change = {"csv": _csv(data)}
    elif csv == "SLOW":
        data[:, 0] *= 10.0
        change = {"csv": _csv(data)}
    elif csv == "RAGGED":
        change = {"csv": _csv(data) + "1,2,3\n"}
    elif csv == "SEMICOLONS":  # a spreadsheet set to a locale with decimal commas
        change = {"csv": _csv(data).replace(",", ";").replace(".", ",")}
    r = client.post("/api/runs", json=body | change)
    assert r.status_code == 422, r.text
    d = r.json()["detail"][0]
    assert field in d["loc"] and words in d["msg"], d
    assert _imported(client) == []
    left = [p for p in (tmp_path / "imported").rglob("*")] if (tmp_path / "imported").exists() else []
    assert left == []


def test_uploads_have_their_own_size_limit_and_other_requests_keep_theirs(tmp_path: Path) -> None:
    data = _log(1.0)
    body = {"name": "one-second", "meta": META, "csv": _csv(data)}
    size = len(json.dumps(body))
    assert size > 4096
    with TestClient(_app(tmp_path, max_body_bytes=4096, max_upload_bytes=size + 100)) as c:
        assert c.post("/api/runs", json=body).status_code == 201  # above the general limit: fine here
        r = c.post("/api/runs", json={"name": "too-long", "meta": META, "csv": _csv(_log(1.5))})
        assert r.status_code == 413 and "CWRR_MAX_UPLOAD_BYTES" in r.json()["detail"]
        r = c.post("/api/params", json={"kind": "workout", "name": "x" * 5000, "values": {}})
        assert r.status_code == 413 and "CWRR_MAX_BODY_BYTES" in r.json()["detail"]
        assert [run["spec"]["name"] for run in _imported(c)] == ["one-second"]


def test_an_import_needs_an_admin_token_where_tokens_are_set(tmp_path: Path) -> None:
    admin, therapist = "a" * 24, "t" * 24
    with TestClient(_app(tmp_path, admin_token=admin, therapist_token=therapist)) as c:
        body = {"name": "x", "meta": META, "csv": _csv(_log(0.5))}
        assert c.post("/api/runs", json=body).status_code == 401
        h = {"Authorization": f"Bearer {therapist}"}
        assert c.post("/api/runs", json=body, headers=h).status_code == 403
        h = {"Authorization": f"Bearer {admin}"}
        assert c.post("/api/runs", json=body, headers=h).status_code == 201


@pytest.mark.slow
def test_logs_from_elsewhere_uploaded_then_diagnosed_by_run_id(client: TestClient, tmp_path: Path) -> None:
    """The researcher's path: a rig (here the simulator with an offset on its sensors) writes the
    protocol's logs, they are uploaded one by one, and the diagnosis of those runs names the effect."""
    from app.engine.diagnosis.protocol import run_protocol
    from app.engine.diagnosis.suite import MAGNITUDES
    from app.engine.params import PlantParams

    rig = PlantParams().with_effects(sensor_bias=MAGNITUDES["sensor_bias"][1])
    logs = tmp_path / "from-the-rig"
    run_protocol(rig, seed=3, scale=0.4, outdir=logs)
    ids = []
    for csv in sorted(logs.glob("*.csv")):
        meta = json.loads(csv.with_suffix(".json").read_text())
        # a name with a dot of its own: the diagnosis had looked for "lab2.csv" beside "lab2.prv_steps_1.csv"
        r = client.post("/api/runs", json={"name": f"lab2.{csv.stem}", "meta": meta, "csv": csv.read_text()})
        assert r.status_code == 201, r.text
        ids.append(r.json()["id"])
    r = client.post("/api/diagnoses", json={"run_ids": ids})
    assert r.status_code == 202, r.text
    rid = r.json()["run_id"]
    assert client.app.state.jobs.join(f"diagnosis-{rid}", 600)  # type: ignore[attr-defined]
    run = client.get(f"/api/runs/{rid}").json()
    assert run["status"] == "complete", run["result"]
    assert run["result"]["verdict"]["effects"][:1] == ["sensor_bias"], run["result"]["verdict"]


def test_an_upload_onto_a_full_disk_answers_503_and_leaves_nothing(
        client: TestClient, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The disk fills while the log is written: a bare 500 before; now 503 saying so, no half log, no run."""
    import errno

    import app.api.routers.runs as runs_router

    def full(*a: Any, **kw: Any) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(runs_router.np, "savetxt", full)
    r = client.post("/api/runs", json={"name": "rig-1", "meta": META, "csv": _csv(_log(0.5))})
    assert r.status_code == 503, r.text
    assert r.json()["detail"] == "the log cannot be stored in the data folder: No space left on device"
    assert _imported(client) == [] and not any((tmp_path / "imported").iterdir())
    monkeypatch.undo()
    assert client.post("/api/runs", json={"name": "rig-1", "meta": META, "csv": _csv(_log(0.5))}).status_code == 201


def test_a_data_folder_moved_elsewhere_keeps_its_runs_series(tmp_path: Path) -> None:
    """A run keeps its log's path as written. A data folder moved (a new disk, a backup restored on
    another machine) had every run listed without its series, exports or diagnosis, the logs beside it."""
    from app.storage import Store

    first = tmp_path / "station"
    with TestClient(_app(first)) as c:
        run = c.post("/api/runs", json={"name": "rig-1", "meta": META, "csv": _csv(_log())}).json()
        series = c.get(f"/api/runs/{run['id']}/series").json()
    moved = tmp_path / "restored" / "cwrr-data"
    moved.parent.mkdir()
    first.rename(moved)
    with TestClient(_app(moved)) as c:
        again = c.get(f"/api/runs/{run['id']}").json()
        assert again["has_series"], again
        assert c.get(f"/api/runs/{run['id']}/series").json()["rows"] == series["rows"]
        assert c.get(f"/api/runs/{run['id']}/export", params={"fmt": "csv"}).status_code == 200
        assert [r["has_series"] for r in _imported(c)] == [True]
    # another station's runs in the same database are not taken for this one's (their logs are theirs)
    other = Store(f"sqlite:///{moved}/cwrr.sqlite3", station=f"someoneelse host:{moved}")
    try:
        row = other.run(run["id"])
        assert row is not None and not Path(row["log_csv"]).exists() and str(first) in row["log_csv"]
    finally:
        other.close()
