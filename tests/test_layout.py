"""The package layout of docs/architecture.md: layers, plain imports, optional extras."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "apo"
CORE = ("spatial", "jsonform", "geometry", "contact", "dof", "transitions", "correction", "task")
# What the core may import from apo: the core itself and the leaf modules below it.
CORE_OK = (*CORE, "constants", "errors", "typing")


def _modules(*parts: str) -> list[Path]:
    out: list[Path] = []
    for p in parts:
        path = SRC / p
        out += sorted(path.rglob("*.py")) if path.is_dir() else [path.with_suffix(".py")]
    return out


def _imports(path: Path) -> set[str]:
    """Every module name imported by ``path`` (at top level or inside functions)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


@pytest.mark.parametrize("path", _modules(*CORE), ids=lambda p: str(p.relative_to(SRC)))
def test_core_imports_only_numpy_scipy_and_the_core(path: Path) -> None:
    # Pure maths never imports I/O, plotting, perception, motion, simulation or the CLI.
    for name in _imports(path):
        top = name.split(".")[0]
        if top == "apo":
            assert name.split(".")[1] in CORE_OK, f"{path.name} imports {name}"
        else:
            assert top in {"numpy", "scipy", "highspy", "__future__"} or top in (
                sys.stdlib_module_names
            ), f"{path.name} imports {name}"


def test_no_importlib_calls_in_the_library() -> None:
    # Imports tools can see: no importlib.import_module / __import__ in apo.
    for path in _modules("."):
        text = path.read_text(encoding="utf-8")
        assert "import_module(" not in text and "__import__(" not in text, path


def test_every_module_imports_without_the_optional_extras() -> None:
    # Optional extras (Open3D, OpenCV, MuJoCo, Selenium) are imported inside the functions
    # that use them, so every module (and its doctests) loads without them.
    code = """
import importlib, pkgutil, sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in {'open3d', 'cv2', 'mujoco', 'selenium'}:
            raise ImportError('blocked ' + name)
sys.meta_path.insert(0, Block())
import apo
for m in pkgutil.walk_packages(apo.__path__, 'apo.'):
    if not m.name.endswith('__main__'):
        importlib.import_module(m.name)
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-2000:]


def test_one_pose_rule_from_input_to_contacts() -> None:
    # Recognition, the contact search, correction and the transition analysis apply the same
    # rule (apo.spatial.pose_defect, tol.rotation): a rotation block off by 4e-5 (a matrix
    # printed with 5 digits) is accepted by all of them; one off by 1e-3 is refused by all,
    # as an InputFormatError (a ValueError) naming the pose.
    import numpy as np

    from apo.contact import ContactFinder
    from apo.errors import InputFormatError
    from apo.recognition import check_sequence
    from apo.shapes import box
    from apo.spatial import check_poses

    finder = ContactFinder(box([0.1, 0.1, 0.1]), box([1.0, 1.0, 0.1], center=[0, 0, -0.1]))
    for scale, ok in ((1 + 2e-5, True), (1 + 5e-4, False)):
        X = np.stack([np.eye(4)] * 3)
        X[1, :3, :3] *= scale
        for check in (check_poses, finder.find_batch, lambda x: check_sequence(None, x)):
            if ok:
                check(X)
            else:
                with pytest.raises(InputFormatError, match="1"):
                    check(X)


def test_one_definition_of_the_array_aliases_and_the_units_table() -> None:
    for path in _modules("."):
        if path.name in ("typing.py", "constants.py"):
            continue
        text = path.read_text(encoding="utf-8")
        for alias in ("FloatArray", "IntArray", "BoolArray"):
            assert f"\n{alias} = " not in text, f"{path}: import {alias} from apo.typing"
        assert '"in": 0.0254' not in text, f"{path}: use apo.constants.UNITS"


LAYERS = {
    **dict.fromkeys(("constants", "errors", "typing"), 1),
    **dict.fromkeys(
        (
            "spatial",
            "jsonform",
            "geometry",
            "shapes",
            "contact",
            "dof",
            "transitions",
            "correction",
            "task",
        ),
        2,
    ),
    **dict.fromkeys(
        ("io", "outputs", "recognition", "motion", "perception", "synthetic", "symmetry"), 3
    ),
    **dict.fromkeys(("report", "sim"), 4),
    "cli": 5,
}


@pytest.mark.parametrize("path", _modules("."), ids=lambda p: str(p.relative_to(SRC)))
def test_imports_point_down_the_layers(path: Path) -> None:
    # docs/architecture.md: a module imports only from its own layer or the layers below
    # (cli on top; report, sim; io, outputs, recognition, motion, perception; the core; the
    # leaves). Planning (motion) never imports the simulator, the report or the CLI.
    rel = path.relative_to(SRC)
    own = rel.parts[0].removesuffix(".py")
    if own in ("__init__", "py"):
        return
    assert own in LAYERS, f"{rel}: add its package to LAYERS and to docs/architecture.md"
    for name in _imports(path):
        parts = name.split(".")
        if parts[0] != "apo" or len(parts) < 2 or parts[1] == own:
            continue
        assert LAYERS[parts[1]] <= LAYERS[own], f"{rel} imports {name} (a layer above)"
