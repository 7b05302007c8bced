"""Import another tree's hybridqcm next to this one, for old-vs-new timings in one process.

    solver = load_baseline("/tmp/i33old").estimation.solver

``path`` is a checkout (its src/hybridqcm is used) or a folder holding hybridqcm/. Its package is
copied to a temporary folder as ``hybridqcm_baseline`` with every ``hybridqcm`` import renamed, so
both versions run side by side in one process (alternating timings see the same machine load).
A pristine copy of main: ``git worktree add /tmp/old main`` or
``mkdir /tmp/old && git archive main src | tar -x -C /tmp/old``.
"""

from __future__ import annotations

import atexit
import importlib
import re
import shutil
import sys
import tempfile
from pathlib import Path

NAME = "hybridqcm_baseline"
_IMPORT = re.compile(r"(?<![\w/.])hybridqcm(?=[.\s,])")


def load_baseline(path: str | Path):
    """The baseline package (imported as ``hybridqcm_baseline``) from the tree at ``path``."""
    if NAME in sys.modules:
        return sys.modules[NAME]
    root = Path(path)
    source = root / "src" / "hybridqcm" if (root / "src" / "hybridqcm").is_dir() else root / "hybridqcm"
    if not (source / "__init__.py").is_file():
        raise SystemExit(f"--baseline {path}: no hybridqcm package in {root}/src or {root}")
    target = Path(tempfile.mkdtemp(prefix="hybridqcm_baseline_"))
    atexit.register(shutil.rmtree, target, True)
    shutil.copytree(source, target / NAME, ignore=shutil.ignore_patterns("__pycache__"))
    for file in (target / NAME).rglob("*.py"):
        file.write_text(_IMPORT.sub(NAME, file.read_text()))
    sys.path.insert(0, str(target))
    package = importlib.import_module(NAME)
    for module in ("estimation.solver", "estimation.response", "estimation.problems", "testing", "physics"):
        importlib.import_module(f"{NAME}.{module}")
    return package
