"""Issue 5: the API fuzzed from its own OpenAPI schema answers no 5xx (schemathesis, in CI).

The server runs for real (uvicorn, full lifespan, engine connected to the
simulator) and schemathesis's own command line drives it through its
examples, coverage (boundary values), fuzzing and stateful phases, so
state-changing calls (connect, start, estimate, stop …) interleave as a careless
client would make them. Every check is on except ``positive_data_acceptance``:
rules the JSON schema cannot state (the thesis GUIs' cross-field rules, SC-3/4
pronation only, references to stored sets) answer 422 by design.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from app.api.settings import Settings
from tests.conftest import free_port, live_server

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def base_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    settings = Settings(data_dir=str(tmp_path_factory.mktemp("fuzz")), viser_port=0, port=free_port())
    with live_server(settings) as base:
        yield base


def test_no_request_from_the_schema_gets_a_server_error(base_url: str, tmp_path: Path) -> None:
    cli = Path(sys.executable).parent / "schemathesis"
    out = subprocess.run(
        [str(cli), "run", f"{base_url}/openapi.json", "--exclude-checks", "positive_data_acceptance",
         "--max-examples", "30", "--seed", "1", "--generation-database", "none", "--no-color",
         "--report", "junit", "--report-dir", str(tmp_path)],
        capture_output=True, text=True, timeout=600)
    tail = out.stdout[-6000:]
    assert out.returncode == 0, tail
    import re

    tested = re.search(r"Tested: (\d+)", tail)
    cases = re.search(r"(\d+) generated, (\d+) passed", tail)
    assert tested and int(tested.group(1)) >= 20, tail  # every operation of the schema, not a subset
    assert cases and int(cases.group(1)) == int(cases.group(2)) >= 1000, tail
    # the engine survived the fuzzing and still answers
    import urllib.request

    with urllib.request.urlopen(f"{base_url}/api/health", timeout=5) as r:
        assert r.status == 200
