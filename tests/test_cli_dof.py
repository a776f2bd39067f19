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
        ('{"contacts": [\n  {"point": [0, 0, 0],, }]}', "invalid JSON at line 2, column"),
        (
            {"contacts": [{"point": [0, 0, 0], "normals": [[0, 0, 0]]}]},
            "contact 0: normal 0 is zero",
        ),
        ({"contacts": [{"point": [0, 0, "x"], "normals": [[0, 0, 1]]}]}, "contact 0: not numeric"),
        ({"contacts": [{"point": [0, 0], "normals": [[0, 0, 1]]}]}, "contact 0: point must"),
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
    assert f"apo dof: error: {missing}: no such file" in capsys.readouterr().err
