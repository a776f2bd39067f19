"""The package layout of docs/architecture.md: layers, plain imports, optional extras."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "apo"
CORE = ("spatial", "jsonform", "geometry", "contact", "dof", "transitions", "correction", "task")
# What the core may import from apo: the core itself and the leaf modules below it.
CORE_OK = (*CORE, "arrays", "constants", "errors", "typing")


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


def test_one_pose_rule_from_input_to_contacts(tmp_path: Path) -> None:
    # Recognition, the contact search, correction and the transition analysis apply the same
    # rule (apo.spatial.pose_defect, tol.rotation): a rotation block off by 4e-5 (a matrix
    # printed with 5 digits) is accepted by all of them; one off by 1e-3 is refused by all,
    # as an InputFormatError (a ValueError) naming the pose. The pose-file writers too.
    import numpy as np

    from apo.contact import ContactFinder
    from apo.errors import InputFormatError
    from apo.io.poses import write_pose_csv
    from apo.recognition import check_sequence
    from apo.shapes import box
    from apo.spatial import check_poses

    finder = ContactFinder(box([0.1, 0.1, 0.1]), box([1.0, 1.0, 0.1], center=[0, 0, -0.1]))
    for scale, ok in ((1 + 2e-5, True), (1 + 5e-4, False)):
        X = np.stack([np.eye(4)] * 3)
        X[1, :3, :3] *= scale
        checks = (
            check_poses,
            finder.find_batch,
            lambda x: check_sequence(None, x),
            lambda x: write_pose_csv(tmp_path / "p.csv", [0.0, 1.0, 2.0], x, units="m"),
        )
        for check in checks:
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
    **dict.fromkeys(("arrays", "constants", "errors", "typing", "workers"), 1),
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


# Functions are short (developers' guide: about 80 lines at most). A function's length is
# counted from its first statement after the docstring to its last line (comments and blank
# lines inside it count; the docstring and the signature do not). The allowlist names the
# functions allowed to be longer, each with its owner and why; an entry that is no longer
# needed (the function was split, renamed or removed) fails too, so the list only shrinks.
MAX_FUNCTION_LINES = 80
LONG_FUNCTIONS_ALLOWED: dict[str, str] = {
    # split pending (session 2): each owner removes its entry when it splits the function.
}


def _function_lengths_in(source: str, module: str) -> dict[str, int]:
    """``{"module.Class.function": lines}`` of every function (nested ones too) in ``source``."""
    lengths: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = f"{prefix}.{child.name}"
                body = child.body
                doc = body[0]
                if (
                    len(body) > 1
                    and isinstance(doc, ast.Expr)
                    and isinstance(doc.value, ast.Constant)
                    and isinstance(doc.value.value, str)
                ):
                    body = body[1:]
                first = body[0]
                decorators = getattr(first, "decorator_list", [])
                start = min([first.lineno] + [d.lineno for d in decorators])
                assert child.end_lineno is not None
                lengths[name] = child.end_lineno - start + 1
                visit(child, name)
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}.{child.name}")
            else:
                visit(child, prefix)

    visit(ast.parse(source), module)
    return lengths


def _function_lengths() -> dict[str, int]:
    """Lengths of every function in ``src/apo``, named ``package.module.Class.function``."""
    lengths: dict[str, int] = {}
    for path in _modules("."):
        module = ".".join(path.relative_to(SRC).with_suffix("").parts)
        text = path.read_text(encoding="utf-8")
        lengths |= _function_lengths_in(text, module.removesuffix(".__init__"))
    return lengths


def test_functions_are_short() -> None:
    lengths = _function_lengths()
    long = {n: k for n, k in lengths.items() if k > MAX_FUNCTION_LINES}
    new = sorted(f"{n} ({k} lines)" for n, k in long.items() if n not in LONG_FUNCTIONS_ALLOWED)
    assert not new, f"functions over {MAX_FUNCTION_LINES} lines (split them): {new}"
    stale = sorted(n for n in LONG_FUNCTIONS_ALLOWED if n not in long)
    assert not stale, f"remove from LONG_FUNCTIONS_ALLOWED (now short or gone): {stale}"


def test_function_length_counts_the_body_after_the_docstring() -> None:
    source = """
def f(
    a,
):
    '''Doc.

    More.
    '''
    x = a

    # comment
    return x
class C:
    def m(self):
        @staticmethod
        def g():
            return 1
        return g
def h():
    '''Only a docstring.'''
"""
    assert _function_lengths_in(source, "mod") == {
        "mod.f": 4,
        "mod.C.m": 4,
        "mod.C.m.g": 1,
        "mod.h": 1,
    }


# Numeric tolerances live in apo.constants (the dataclass `tol`, each field saying why it
# differs from its neighbours). A float literal of the core that looks like a tolerance
# (0 < |x| < 0.01, or within 0.01 of +-1 but not +-1, like 1e-9 or 0.999) must be a field of
# `tol` instead; the allowlist names the few that are not tolerances, with the reason.
TOLERANCE_MODULES = (*CORE, "shapes")
TOLERANCE_LIKE_ALLOWED: dict[tuple[str, float], str] = {
    ("contact/separating_normals.py", 1e-3): (
        "_CENTRE_WEIGHT: a tie-break weight (1/rad) of a score, not a tolerance"
    ),
}


def _tolerance_like(x: float) -> bool:
    return 0 < abs(x) < 0.01 or 0 < abs(abs(x) - 1) < 0.01


def _tolerance_literals(source: str) -> list[tuple[int, float]]:
    return sorted(
        (node.lineno, node.value)
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.Constant)
        and isinstance(node.value, float)
        and _tolerance_like(node.value)
    )


def test_tolerances_only_in_constants() -> None:
    found: set[tuple[str, float]] = set()
    new: list[str] = []
    for path in _modules(*TOLERANCE_MODULES):
        rel = str(path.relative_to(SRC))
        for line, value in _tolerance_literals(path.read_text(encoding="utf-8")):
            found.add((rel, value))
            if (rel, value) not in TOLERANCE_LIKE_ALLOWED:
                new.append(f"{rel}:{line}: {value!r}")
    assert not new, f"tolerance literals outside apo.constants (add a field to tol): {new}"
    stale = sorted(k for k in TOLERANCE_LIKE_ALLOWED if k not in found)
    assert not stale, f"remove from TOLERANCE_LIKE_ALLOWED (no longer found): {stale}"


def test_tolerance_literal_detector() -> None:
    source = "a = 1e-9\nb = x < 0.999\nc = 0.5 * y\nd = 1.0 + 2.0\ne = -1e-12\nf = 1.001\n"
    assert _tolerance_literals(source) == [(1, 1e-9), (2, 0.999), (5, 1e-12), (6, 1.001)]


def _drawn_layers(text: str) -> dict[str, int]:
    """``{package: layer}`` read from the layer drawing of docs/architecture.md."""
    block = text.split("## Layers", 1)[1].split("```", 2)[1]
    layers: dict[str, int] = {}
    layer = 0
    for line in block.splitlines():
        m = re.match(r"^ (\d)  (\S.*)$", line) or re.match(r"^ {4}(\S.*)$", line)
        if not m:
            continue
        if len(m.groups()) == 2:
            layer = int(m.group(1))
        head = m.groups()[-1].split("   ")[0]  # the names, before the description
        if "(" in head:  # "core (pure maths, ...)": a title, not a package
            continue
        for name in re.findall(r"([a-z_]+)(?:/|\.py)", head):
            layers[name] = layer
    return layers


def test_layers_match_the_drawing_of_the_architecture_document() -> None:
    # docs/architecture.md draws the layers; LAYERS is that drawing (a new package gets a
    # line in both, in the same layer).
    doc = SRC.parents[1] / "docs" / "architecture.md"
    assert _drawn_layers(doc.read_text(encoding="utf-8")) == LAYERS
