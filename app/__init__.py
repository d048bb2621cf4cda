"""CWRR lab station."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path


def _numba_cache_dir() -> None:
    # numba's on-disk cache is invalidated per source file only: a compiled
    # function that inlines or calls a function from another module keeps the
    # old callee after that module changes. Keying the cache directory by a
    # hash of all our sources makes a stale cache impossible.
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(p.relative_to(root).as_posix().encode())
        h.update(p.read_bytes())
    base = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "cwrr" / "numba"
    target = base / h.hexdigest()[:16]
    try:
        target.mkdir(parents=True, exist_ok=True)
    except OSError:  # read-only home (some containers): a private temp dir still caches per process tree
        import tempfile

        target = Path(tempfile.gettempdir()) / "cwrr-numba" / h.hexdigest()[:16]
        target.mkdir(parents=True, exist_ok=True)
    os.environ["NUMBA_CACHE_DIR"] = str(target)


_numba_cache_dir()
