"""Cold-start paths of `apo <command>`: one command's parser, a STEP file's unit read once."""

from __future__ import annotations

import subprocess
import sys

import pytest

from apo.cli import COMMANDS, build_parser

LINES = [
    ["analyze", "demo.pose.list", "--out", "o", "--json", "--threshold", "3", "--noise", "1,2"],
    ["analyze", "frames", "--grasped", "g.stl", "--environment", "e.stl", "--no-report"],
    ["report", "task.json"],
    ["figures", "task.json", "--out", "f"],
    ["analyze", "x.csv", "--plot", "--units", "m"],
    ["track", "f", "--grasped", "g.stl", "--environment", "e.stl", "--units", "m", "--out", "p"],
    ["track", "f", "--grasped", "g", "--environment", "e", "--colour", "none", "--out", "p.csv"],
]


@pytest.mark.parametrize("line", LINES)
def test_one_command_parser_gives_the_full_parsers_namespace(line: list[str]) -> None:
    full = vars(build_parser().parse_args(line))
    one = vars(build_parser(line[0]).parse_args(line))
    assert one == full


def test_every_command_is_registered_by_its_module() -> None:
    full = build_parser()
    (sub,) = (a for a in full._actions if a.dest == "command")
    assert tuple(sub.choices) == COMMANDS
    for name in COMMANDS:
        one = build_parser(name)
        (s,) = (a for a in one._actions if a.dest == "command")
        assert list(s.choices) == ([name] if name in ("analyze", "track") else list(COMMANDS))


@pytest.mark.parametrize("command", ["analyze", "track"])
def test_analyze_and_track_import_no_other_command_module(command: str) -> None:
    # (`apo analyze FRAMES` runs the tracker: apo.cli.analyze imports apo.cli.track)
    code = (
        "import sys\n"
        "from apo.cli import main\n"
        "try:\n"
        f"    main(['{command}', '--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "print(sorted(m for m in sys.modules if m.startswith('apo.cli.')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    loaded = out.stdout.strip().splitlines()[-1]
    assert f"apo.cli.{command}" in loaded
    assert command == "analyze" or "apo.cli.analyze" not in loaded
    assert "apo.cli.demo" not in loaded and "apo.cli.replay" not in loaded


def test_step_length_unit_reads_a_changed_file_again(tmp_path: object) -> None:
    import os
    from pathlib import Path

    from apo.io.meshes import step_length_unit

    # the unit entities of a minimal STEP file, in mm, then in m
    body = (
        "ISO-10303-21;\nDATA;\n#1=(LENGTH_UNIT()NAMED_UNIT(*)SI_UNIT({p},.METRE.));\n"
        "#2=(GEOMETRIC_REPRESENTATION_CONTEXT(3)GLOBAL_UNIT_ASSIGNED_CONTEXT((#1)));\n"
        "ENDSEC;\nEND-ISO-10303-21;\n"
    )
    f = Path(str(tmp_path)) / "part.step"
    f.write_text(body.format(p=".MILLI."))
    assert step_length_unit(f) == "mm"
    assert step_length_unit(str(f)) == "mm"
    f.write_text(body.format(p="$") + "\n")  # another size
    os.utime(f, ns=(1, 1))
    assert step_length_unit(f) == "m"
    missing = Path(str(tmp_path)) / "missing.step"
    try:
        step_length_unit(missing)
    except OSError:
        pass
    else:  # pragma: no cover
        raise AssertionError("a missing file reads as an OSError")
