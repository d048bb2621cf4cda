"""The README's and docs' relative links lead somewhere: every file exists and every ``#anchor`` is a heading there."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation but hyphens dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    fenced = False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            fenced = not fenced
        m = None if fenced else re.match(r"^#{1,6}\s+(.*)", line)
        if m:
            s = _slug(m.group(1))
            n = seen.get(s, 0)
            seen[s] = n + 1
            out.add(s if n == 0 else f"{s}-{n}")
    return out


def test_the_slug_follows_githubs_rule() -> None:
    assert _slug("The withheld-effect suite (`python bench/withheld.py`; `docs/figures/x.json`)") == (
        "the-withheld-effect-suite-python-benchwithheldpy-docsfiguresxjson")


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_relative_link_leads_to_a_file_and_heading_that_exist(page: Path) -> None:
    broken = []
    for target in LINK.findall(page.read_text(encoding="utf-8")):
        if re.match(r"^[a-z]+:", target):
            continue  # http(s), mailto: not checked offline
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target}: no heading #{anchor} in {dest.name}")
    assert not broken, f"{page.name}: " + "; ".join(broken)


@pytest.mark.parametrize("path", sorted((ROOT / "docs" / "figures").rglob("*.json")),
                         ids=lambda p: str(p.relative_to(ROOT / "docs" / "figures")))
def test_every_saved_figure_is_strict_json(path: Path) -> None:
    import json

    def refuse(token: str) -> float:
        raise AssertionError(f"{path.name}: bare {token}, which JSON.parse and jq refuse")

    json.loads(path.read_text(encoding="utf-8"), parse_constant=refuse)


def test_the_stations_settings_table_lists_every_setting_and_flag() -> None:
    """A lab configures the station from docs/station.md's table: every field of ``Settings`` is
    there as its environment variable, with ``cwrr serve``'s flag where it has one."""
    import argparse

    from app.api.settings import Settings
    from app.cli import build_parser

    text = (ROOT / "docs" / "station.md").read_text(encoding="utf-8")
    section = text.split("\n## Settings\n", 1)[1].split("\n## ", 1)[0]
    rows: dict[str, str] = {}
    for line in section.splitlines():
        cells = [c.strip().strip("`") for c in line.strip().strip("|").split("|")]
        if line.startswith("| `CWRR_"):
            rows[cells[0]] = cells[1]
    assert set(rows) == {f"CWRR_{name.upper()}" for name in Settings.model_fields}
    # the serve flags, read off the parser itself
    ap = build_parser()
    sub = next(a for a in ap._actions if isinstance(a, argparse._SubParsersAction))
    flags = {o for a in sub.choices["serve"]._actions for o in a.option_strings} - {"-h", "--help"}
    assert {f for f in rows.values() if f} == flags


def test_the_rest_api_table_lists_every_call_with_the_role_it_needs() -> None:
    """A researcher scripts the API from docs/station.md's table: every route is there, none that is
    gone, each with the role its dependencies demand."""
    from collections.abc import Iterable, Iterator

    from fastapi.dependencies.models import Dependant
    from fastapi.routing import APIRoute

    from app.api import auth
    from app.api.main import create_app

    def routes(rs: Iterable[Any]) -> Iterator[APIRoute]:
        for r in rs:
            if hasattr(r, "original_router"):  # an included router, resolved lazily by FastAPI
                yield from routes(r.original_router.routes)
            elif isinstance(r, APIRoute) and r.include_in_schema:
                yield r

    def calls(dep: Dependant) -> Iterator[Any]:
        for d in dep.dependencies:
            yield d.call
            yield from calls(d)

    def who(route: APIRoute) -> str:
        needs = set(calls(route.dependant))
        for dep, name in ((auth.ADMIN, "admin"), (auth.THERAPIST, "therapist"), (auth.READ, "any role")):
            if dep.dependency in needs:
                return name
        return "anyone (no token)"

    served = {f"{m} {r.path}": who(r) for r in routes(create_app().routes) for m in r.methods or ()}
    text = (ROOT / "docs" / "station.md").read_text(encoding="utf-8")
    section = text.split("\n## The REST API\n", 1)[1].split("\n## ", 1)[0]
    listed = {m.group(1): m.group(2) for m in re.finditer(r"^\| `([A-Z]+ /\S+)` \| ([^|]+?) \|", section, re.M)}
    assert listed == served, {k: (listed.get(k), served.get(k)) for k in listed.keys() ^ served.keys()
                              or {k for k in served if listed[k] != served[k]}}
    assert len(served) > 30
