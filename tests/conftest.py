"""Shared pytest fixtures: the first author's data beside the repository."""

from __future__ import annotations

import atexit
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import pytest

# Tests never write to the user's cache: the model cache (apo.io.meshes) goes to a folder of
# this test session (each xdist worker its own).
# The folder is removed when the process that made it exits (not a forked child's exit).
_CACHE_DIR = tempfile.mkdtemp(prefix="apo-test-cache-")
_CACHE_OWNER = os.getpid()
os.environ["APO_CACHE_DIR"] = _CACHE_DIR


def _remove_cache_dir() -> None:
    if os.getpid() == _CACHE_OWNER:
        shutil.rmtree(_CACHE_DIR, ignore_errors=True)


atexit.register(_remove_cache_dir)


def shared_data_dir() -> Path | None:
    """``../shared/data/apo-peg-in-hole`` beside the repository, or None if absent."""
    path = Path(__file__).resolve().parents[2] / "shared" / "data" / "apo-peg-in-hole"
    return path if path.is_dir() else None


@pytest.fixture
def real_data_dir() -> Path:
    """The first author's peg-in-hole data directory; skips the test when it is absent."""
    path = shared_data_dir()
    if path is None:
        pytest.skip("first author's data not found at ../shared/data/apo-peg-in-hole")
    return path


@pytest.fixture
def analyze_imports(tmp_path: Path) -> Callable[[list[str], str], bool]:
    """Whether ``apo analyze ARGS --out <tmp>/out``, in a fresh interpreter, imports a module."""

    def run(args: list[str], module: str) -> bool:
        code = (
            "import sys\nfrom apo.cli import main\n"
            f"main({[*args, '--out', str(tmp_path / 'out')]!r})\n"
            f"print({module!r} in sys.modules)\n"
        )
        out = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True
        )
        last = out.stdout.strip().splitlines()[-1]
        assert last in ("True", "False"), out.stdout
        return last == "True"

    return run
