"""``apo dof`` command line: table, --json lines, bad input reported without a traceback."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from apo.cli import main

BLOCK = {
    "contacts": [
        {"point": [x, y, 0.0], "normals": [[0.0, 0.0, 1.0]]} for x in (0, 1) for y in (0, 1)
    ]
}
VE = {"contacts": [{"point": [0, 0, 0], "normals": [[0, 1, 1], [0, -1, 1]]}]}


def write(tmp_path: Path, name: str, data: object) -> str:
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return str(path)


def test_json_lines(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    files = [
        write(tmp_path, "block.json", BLOCK),
        write(tmp_path, "ve.json", VE),
        write(tmp_path, "empty.json", {"contacts": []}),
    ]
    assert main(["dof", *files, "--json"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 3
    objs = [json.loads(line) for line in lines]
    assert [o["file"] for o in objs] == files
    block, ve, empty = objs
    assert block["singular"] is False
    assert block["fig25"] == [2, 1, 0, 1, 2, 0, 1, 2]
    assert block["rotation"] == {
        "maintaining": 1,
        "detaching": 2,
        "constraining": 0,
        "detaching_type1": 2,
        "detaching_type2": 0,
    }
    assert set(block["translation"]) == {"maintaining", "detaching", "constraining"}
    assert block["all"] == {"maintaining": 3, "detaching": 3, "constraining": 0}
    assert ve["singular"] is True
    assert ve["singular_dof"]["translation"]["maintaining"] == 3
    assert ve["restraining"] == {"translation": 2, "rotation": 0, "all": 2}
    assert empty["fig25"] == [3, 0, 0, 3, 0, 0, 0, 0]


def test_table(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = write(tmp_path, "block.json", BLOCK)
    assert main(["dof", f]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].split() == [
        "file", "singular", "tM", "tD", "tC", "rM", "rD", "rC", "r_t", "r_r", "rD_I", "rD_II",
        "r_a",
    ]  # fmt: skip
    assert out[1].split() == [f, "no", "2", "1", "0", "1", "2", "0", "1", "2", "2", "0", "3"]


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (
            '{"contacts": [\n  {"point": [0, 0, 0],, }]}',
            "not valid JSON: Expecting property name enclosed in double quotes"
            " at line 2, column 23",
        ),
        (
            {"contacts": [{"point": [0, 0, 0], "normals": [[0, 0, 0]]}]},
            "contact 0: normal 0 is zero",
        ),
        (
            {"contacts": [{"point": [0, 0, "x"], "normals": [[0, 0, 1]]}]},
            "contact 0: point: expected 3 numbers",
        ),
        ({"contacts": [{"point": [0, 0], "normals": [[0, 0, 1]]}]}, "contact 0: point: expected"),
        ({"contacts": [{"point": [0, 0, 0]}]}, 'contact 0: expected an object with "point"'),
        ({"points": []}, 'expected an object with a "contacts" list'),
    ],
)
def test_bad_input(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: object, message: str
) -> None:
    good = write(tmp_path, "good.json", BLOCK)
    bad = write(tmp_path, "bad.json", content)
    assert main(["dof", "--json", bad, good]) == 2
    captured = capsys.readouterr()
    assert len(captured.out.splitlines()) == 1  # the good file is still reported
    assert json.loads(captured.out)["file"] == good
    assert captured.err.startswith(f"apo dof: error: {bad}: ")
    assert message in captured.err
    assert "Traceback" not in captured.err


def test_nan_normal(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = write(tmp_path, "nan.json", '{"contacts": [{"point": [0,0,0], "normals": [[NaN,0,1]]}]}')
    assert main(["dof", bad]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: contact 0: normals are not finite" in err


def test_missing_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = str(tmp_path / "nope.json")
    assert main(["dof", missing]) == 2
    assert f"apo dof: error: {missing}: file not found" in capsys.readouterr().err


# ---- added by the audit of issue 2 --------------------------------------------------------

KEYS = {"file", "singular", "fig25", "translation", "rotation", "all", "singular_dof",
        "restraining"}  # fmt: skip
SPACE = {"maintaining", "detaching", "constraining"}
Infinity = float("inf")
ROTATION = SPACE | {"detaching_type1", "detaching_type2"}


def test_json_schema_is_exact_and_compact(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Square peg seated in a square hole (tests/test_dof.py CASES): bottom corners on the
    # floor and the four walls' corners: lift only (D), x and y held (C), all rotations C.
    walls = [((0, y, z), (1, 0, 0)) for y in (0, 1) for z in (0, 1)]
    walls += [((1, y, z), (-1, 0, 0)) for y in (0, 1) for z in (0, 1)]
    walls += [((x, 0, z), (0, 1, 0)) for x in (0, 1) for z in (0, 1)]
    walls += [((x, 1, z), (0, -1, 0)) for x in (0, 1) for z in (0, 1)]
    floor = [((x, y, 0), (0, 0, 1)) for x in (0, 1) for y in (0, 1)]
    peg = {"contacts": [{"point": p, "normals": [n]} for p, n in floor + walls]}
    files = [write(tmp_path, "peg.json", peg), write(tmp_path, "ve.json", VE)]
    assert main(["dof", "--json", *files]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    for line, path in zip(lines, files, strict=True):
        assert " " not in line  # compact: no spaces at all (file names have none)
        obj = json.loads(line)
        assert set(obj) == KEYS and obj["file"] == path
        assert set(obj["translation"]) == set(obj["all"]) == SPACE
        assert set(obj["rotation"]) == ROTATION
        assert set(obj["singular_dof"]) == {"translation", "rotation", "all"}
        assert set(obj["singular_dof"]["rotation"]) == ROTATION
        assert set(obj["restraining"]) == {"translation", "rotation", "all"}
        assert len(obj["fig25"]) == 8 and all(type(v) is int for v in obj["fig25"])
    seated, ve = (json.loads(line) for line in lines)
    assert seated["fig25"] == [0, 1, 2, 0, 0, 3, 3, 3]
    assert seated["all"] == {"maintaining": 0, "detaching": 1, "constraining": 5}
    assert seated["restraining"] == {"translation": 3, "rotation": 3, "all": 6}
    # VE alone: the regular numbers are 0; the singular ones are those of "no contact";
    # Fig. 25 prints the singular variants: SM = 3 in both spaces, r_t = 2, r_r = 0.
    assert ve["translation"] == {"maintaining": 0, "detaching": 0, "constraining": 0}
    assert ve["singular_dof"]["rotation"]["maintaining"] == 3
    assert ve["fig25"] == [3, 0, 0, 3, 0, 0, 2, 0]


def test_table_marks_singular_rows(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    files = [write(tmp_path, "block.json", BLOCK), write(tmp_path, "ve.json", VE)]
    assert main(["dof", *files]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[2].split() == [files[1], "yes", "3", "0", "0", "3", "0", "0", "2", "0", "0",
                              "0", "2"]  # fmt: skip
    assert out[3].startswith("singular rows: tM..rC, rD_I, rD_II are the singular variants")
    assert main(["dof", files[0]]) == 0
    assert "singular rows" not in capsys.readouterr().out


@pytest.mark.parametrize(
    ("content", "message"),
    [
        # strings and booleans are not numbers, although numpy would convert them
        (
            {"contacts": [{"point": ["0", "0", "1"], "normals": [[0, 0, 1]]}]},
            'contact 0: point: expected 3 numbers [x, y, z], got ["0", "0", "1"]',
        ),
        (
            {"contacts": [{"point": [0, 0, 0], "normals": [[0, True, 1]]}]},
            "contact 0: normal 0: expected 3 numbers [x, y, z], got [0, true, 1]",
        ),
        (
            {"contacts": [{"point": [0, 0, 0], "normals": []}]},
            "contact 0: normals must be a non-empty list of [nx, ny, nz], got []",
        ),
        (
            {"contacts": [{"point": [0, 0, 0], "normals": [[0, 0, 1], [1, 0]]}]},
            "contact 0: normal 1: expected 3 numbers",
        ),
        (
            {"contacts": [{"point": [0, 0, 0], "normals": [[0, 0, 1]]}, 7]},
            'contact 1: expected an object with "point" and "normals"',
        ),
        (
            {"contacts": [{"point": [0, 0, 0], "normals": [[0, 0, 1e-300]]}]},
            "contact 0: normal 0 is zero",
        ),
        (
            {"contacts": [{"point": [0, 0, 0], "normals": [[0, -Infinity, 1]]}]},
            "contact 0: normals are not finite",
        ),
        ("", "not valid JSON: Expecting value at line 1, column 1"),
        ("[]", 'expected an object with a "contacts" list'),
    ],
)
def test_more_bad_input(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: object, message: str
) -> None:
    bad = write(tmp_path, "bad.json", content)
    assert main(["dof", bad]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith(f"apo dof: error: {bad}: {message}")
    assert captured.err.count("\n") == 1 and "Traceback" not in captured.err


def test_unreadable_paths(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["dof", str(tmp_path)]) == 2  # a directory
    assert f"apo dof: error: {tmp_path}: cannot read" in capsys.readouterr().err
    latin = tmp_path / "latin1.json"
    latin.write_bytes(b'{"contacts": [], "note": "\xe9"}')
    assert main(["dof", str(latin)]) == 2
    assert f"apo dof: error: {latin}: cannot read" in capsys.readouterr().err


def test_only_the_direction_of_a_normal_matters(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Huge finite components (whose length would overflow), a scaled normal and a single
    # normal written without the outer brackets all mean the same direction: normals
    # (0, 1, 1)/sqrt2 at 0 and +z at (1, 0, 0) span y, z (m_t = 1, no opposing: c_t = 0);
    # moments 0 and (0, -1, 0): rank W = 2, m_a = 4, m_r = 3; r_t = 2, r_r = 0.
    def state(n: object, far: float = 1.0, m: object = ((0, 0, 1),)) -> dict[str, object]:
        return {"contacts": [{"point": [0, 0, 0], "normals": n},
                             {"point": [far, 0, 0], "normals": m}]}  # fmt: skip

    files = [
        write(tmp_path, "unit.json", state([[0, 1, 1]])),
        write(tmp_path, "huge.json", state([[0, 1e308, 1e308]])),
        write(tmp_path, "flat.json", state([0, 3, 3])),
        # huge coordinates are scaled away exactly: a box on an edge 1e200 long still
        # turns about the edge and about z (rotation M = 2), not as one point (M = 3)
        write(tmp_path, "far.json", state([[0, 0, 1]], 1e200)),
    ]
    assert main(["dof", "--json", *files]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    objs = [json.loads(line) for line in captured.out.splitlines()]
    assert [o["fig25"] for o in objs] == [[1, 2, 0, 3, 0, 0, 2, 0]] * 3 + [[2, 1, 0, 2, 1, 0, 1, 1]]
