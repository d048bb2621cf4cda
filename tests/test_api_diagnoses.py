"""Issue 6 over the API: start a diagnosis, read the stored report; bad requests refused."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.api.main import create_app
from app.api.settings import Settings


@pytest.fixture()
def client(tmp_path: Path) -> Iterator[TestClient]:
    app = create_app(Settings(data_dir=str(tmp_path), viser_port=0, auto_connect=False))
    with TestClient(app) as c:
        yield c


def _join(run_id: int) -> None:
    for t in threading.enumerate():
        if t.name == f"diagnosis-{run_id}":
            t.join(600)


@pytest.mark.parametrize(("body", "field", "words"), [
    ({}, "body", "exactly one of protocol or run_ids"),
    ({"protocol": {}, "run_ids": [1, 2]}, "body", "exactly one of protocol or run_ids"),
    ({"protocol": {"effects": ["friction"]}}, "effects", ""),
    ({"protocol": {"param_error": 0.9}}, "param_error", ""),
    ({"run_ids": [1, 2]}, "run_ids", "run 1 does not exist"),
])
def test_bad_diagnosis_requests_are_refused_and_store_nothing(client: TestClient, body: dict, field: str,
                                                              words: str) -> None:
    r = client.post("/api/diagnoses", json=body)
    assert r.status_code == 422, r.text
    d = r.json()["detail"][0]
    assert field in d["loc"] and words in d["msg"]
    assert client.get("/api/runs", params={"kind": "diagnosis"}).json() == []


@pytest.mark.slow
def test_a_protocol_diagnosis_is_stored_as_a_run_with_its_report(client: TestClient) -> None:
    r = client.post("/api/diagnoses", json={"protocol": {"effects": ["sensor_bias"], "magnitude": 2, "seed": 3,
                                                          "scale": 0.4}})
    assert r.status_code == 202, r.text
    rid = r.json()["run_id"]
    _join(rid)
    run = client.get(f"/api/runs/{rid}").json()
    assert run["kind"] == "diagnosis" and run["status"] == "complete", run["result"]
    rep = run["result"]
    assert rep["verdict"]["effects"][:1] == ["sensor_bias"]
    assert run["metrics"]["effects_found"] == len(rep["verdict"]["effects"])
    assert run["metrics"]["e_after"] < run["metrics"]["e_before"]
    assert {"baseline", "ranking", "verdict", "where", "how_far"} <= set(rep)
    page = client.get("/static/diagnosis.html")
    assert page.status_code == 200 and "/api/diagnoses" in page.text
