"""``apo dof FILE...``: DOF indices of contact states given as JSON files.

Each FILE holds ``{"contacts": [{"point": [x, y, z], "normals": [[nx, ny, nz], ...]}, ...]}``
in the environment frame; normals point from the environment towards the grasped object and
a point with more than one normal is singular. Good files are reported even when others fail;
the exit code is then 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from apo.errors import InputFormatError

_HEADERS = ("tM", "tD", "tC", "rM", "rD", "rC", "r_t", "r_r")


def register(subparsers: Any) -> None:
    """Add the ``dof`` sub-command."""
    p = subparsers.add_parser(
        "dof",
        help="DOF indices of contact states (JSON files of points and normals)",
        description=(
            "Print the DOF indices (paper section 2.2, Fig. 25) of each contact state. FILE is "
            'JSON: {"contacts": [{"point": [x, y, z], "normals": [[nx, ny, nz], ...]}]}, '
            "environment frame, normals from the environment towards the grasped object."
        ),
    )
    p.add_argument("files", nargs="+", metavar="FILE", help="contact-state JSON file(s)")
    p.add_argument(
        "--json", action="store_true", help="one compact JSON object per file, one per line"
    )
    p.set_defaults(func=run)


def load_contacts(path: str) -> list[Any]:
    """Read a contact-state JSON file into a list of :class:`apo.dof.ContactPoint`.

    Raises
    ------
    InputFormatError
        Missing or unreadable file, malformed JSON (with line and column), wrong structure or
        bad numbers (naming the contact). Every message starts with the file name.
    """
    import numpy as np

    from apo.dof import ContactPoint, check_arrays

    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputFormatError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFormatError(f"{path}: cannot read: {exc}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFormatError(
            f"{path}: invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None
    if not isinstance(data, dict) or not isinstance(data.get("contacts"), list):
        raise InputFormatError(f'{path}: expected an object with a "contacts" list')
    points: list[Any] = []
    normals: list[Any] = []
    for i, c in enumerate(data["contacts"]):
        if not isinstance(c, dict) or "point" not in c or "normals" not in c:
            raise InputFormatError(
                f'{path}: contact {i}: expected an object with "point" and "normals"'
            )
        points.append(c["point"])
        normals.append(c["normals"])
    try:
        pts, unit = check_arrays(points, normals)
    except InputFormatError as exc:
        raise InputFormatError(f"{path}: {exc}") from None
    return [
        ContactPoint(point=np.array(p, dtype=np.float64), normals=n)
        for p, n in zip(pts, unit, strict=True)
    ]


def _row(name: str, result: Any) -> list[str]:
    r = result.singular_dof_rotation if result.singular else result.rotation
    return [
        name,
        "yes" if result.singular else "no",
        *(str(v) for v in result.fig25),
        str(r.detaching_type1),
        str(r.detaching_type2),
        str(result.restraining.all),
    ]


def _print_table(rows: list[list[str]]) -> None:
    header = ["file", "singular", *_HEADERS, "rD_I", "rD_II", "r_a"]
    widths = [max(len(r[k]) for r in [header, *rows]) for k in range(len(header))]
    for r in [header, *rows]:
        print(
            "  ".join(
                c.ljust(w) if k < 2 else c.rjust(w)
                for k, (c, w) in enumerate(zip(r, widths, strict=True))
            )
        )


def run(args: argparse.Namespace) -> int:
    """Run ``apo dof``; return 0, or 2 if any file failed (the others are still reported)."""
    from apo.dof import analyze, dof_result_to_dict

    failed = 0
    rows: list[list[str]] = []
    for path in args.files:
        try:
            result = analyze(load_contacts(path))
        except InputFormatError as exc:
            failed += 1
            print(f"apo dof: error: {exc}", file=sys.stderr)
            continue
        if args.json:
            print(json.dumps({"file": path, **dof_result_to_dict(result)}, separators=(",", ":")))
        else:
            rows.append(_row(path, result))
    if rows:
        _print_table(rows)
    return 2 if failed else 0
