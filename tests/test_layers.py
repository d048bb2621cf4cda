"""The one-way data flow, as imports: hardware/sim → estimators → controllers → safety → actuators;
runs → metrics → storage → API/plots.

Every ``import`` and ``from … import`` in a module is read from its syntax tree, those inside
functions too (a lazy import is still a dependency), and checked against the layer rules of the
developers' brief: ``app/engine`` never imports ``app/api``; controllers never import hardware
backends (only the interface's data types, ``hardware.base``).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

APP = Path(__file__).resolve().parents[1] / "app"


def module_name(path: Path, root: Path = APP.parent) -> str:
    """``app/engine/sim.py`` → ``app.engine.sim`` (relative to ``root``); a package's ``__init__`` is the package."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path, root: Path = APP.parent) -> set[str]:
    """Every module ``path`` imports, absolute (relative imports resolved against its package)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            out.add(base)
            # ``from app.engine import sim`` imports the module app.engine.sim
            out.update(f"{base}.{a.name}" for a in node.names)
    return out


def modules_under(*parts: str) -> list[Path]:
    root = APP.joinpath(*parts)
    return sorted(root.rglob("*.py")) if root.is_dir() else [root.with_suffix(".py")]


def within(name: str, *prefixes: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def offenders(paths: list[Path], forbidden: tuple[str, ...], allowed: tuple[str, ...] = (),
              root: Path = APP.parent) -> dict[str, list[str]]:
    """Per module, what it imports from ``forbidden`` (outside ``allowed``)."""
    found = {}
    for p in paths:
        bad = sorted(i for i in imports_of(p, root) if within(i, *forbidden) and not within(i, *allowed))
        if bad:
            found[module_name(p, root)] = bad
    return found


# (what, the modules, what they must not import, the exceptions)
RULES = [
    ("the engine never imports the API, the store or the command line above it",
     modules_under("engine"), ("app.api", "app.storage", "app.cli", "app.benchmarks", "app.thesis_bench"), ()),
    ("the controllers import no hardware backend (the interface's data types only), nor the safety stage, "
     "the loop or the station downstream of them",
     modules_under("engine", "control"),
     ("app.engine.hardware", "app.engine.safety", "app.engine.loop", "app.engine.station", "app.engine.runlog"),
     ("app.engine.hardware.base",)),
    ("the plant's physics is the bottom layer: no controller, estimator, safety, loop, backend or diagnosis",
     modules_under("engine", "physics"),
     ("app.engine.control", "app.engine.safety", "app.engine.loop", "app.engine.station", "app.engine.hardware",
      "app.engine.diagnosis", "app.engine.ident", "app.engine.sim", "app.engine.scenarios"), ()),
    ("the safety stage judges commands and measurements without knowing who made them",
     modules_under("engine", "safety"),
     ("app.engine.control", "app.engine.loop", "app.engine.station", "app.engine.sim", "app.engine.physics"),
     ()),
    ("the store keeps runs without knowing how they are served",
     modules_under("storage"), ("app.api",), ()),
]


@pytest.mark.parametrize(("what", "paths", "forbidden", "allowed"), RULES, ids=[r[0][:40] for r in RULES])
def test_imports_follow_the_data_flow(what: str, paths: list[Path], forbidden: tuple[str, ...],
                                      allowed: tuple[str, ...]) -> None:
    assert paths and all(p.is_file() for p in paths), paths
    assert offenders(paths, forbidden, allowed) == {}, what


def test_the_import_reader_sees_lazy_relative_and_aliased_imports(tmp_path: Path) -> None:
    """The rules above can only fail if the reader finds what a module imports: a function-level
    import, a relative one and ``from package import module`` are each found."""
    pkg = tmp_path / "app" / "engine" / "control"
    pkg.mkdir(parents=True)
    probe = pkg / "probe.py"
    probe.write_text("import numpy as np\n"
                     "def f():\n    from app.api import models\n    return models\n"
                     "from ..hardware import modbus\n"
                     "from . import pipeline\n", encoding="utf-8")
    found = imports_of(probe, tmp_path)
    assert {"numpy", "app.api", "app.api.models", "app.engine.hardware.modbus",
            "app.engine.control.pipeline"} <= found, found
    assert offenders([probe], ("app.engine.hardware", "app.api"), ("app.engine.hardware.base",), tmp_path) == {
        "app.engine.control.probe": ["app.api", "app.api.models", "app.engine.hardware",
                                     "app.engine.hardware.modbus"]}
