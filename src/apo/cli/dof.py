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
import warnings
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


def _json(value: Any) -> str:
    """``value`` as JSON text, cut to 60 characters (for messages)."""
    text = json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _numbers(value: Any, where: str, path: str) -> list[float]:
    """Return ``value`` as a list of 3 JSON numbers, or raise naming ``where``.

    JSON ``true``/``false`` and strings are rejected, although numpy would convert them.
    """
    if not (
        isinstance(value, list)
        and len(value) == 3
        and all(isinstance(x, int | float) and not isinstance(x, bool) for x in value)
    ):
        raise InputFormatError(f"{path}: {where}: expected 3 numbers [x, y, z], got {_json(value)}")
    return [float(x) for x in value]


def load_contacts(path: str) -> list[Any]:
    """Read a contact-state JSON file into a list of :class:`apo.dof.ContactPoint`.

    Points and normals must be JSON numbers (not strings or booleans); ``"normals"`` is a list
    of ``[nx, ny, nz]`` (a single ``[nx, ny, nz]`` is accepted as one normal). Only the
    direction of a normal matters; huge but finite normals and coordinates are scaled
    exactly by :mod:`apo.dof` (the DOF indices do not change under uniform scaling).

    Raises
    ------
    InputFormatError
        Missing or unreadable file, malformed JSON (with line and column), wrong structure or
        bad numbers (naming the contact). Every message starts with the file name.
    """
    import numpy as np

    from apo.dof import ContactPoint, check_arrays
    from apo.io.jsonfile import read_json

    data = read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("contacts"), list):
        raise InputFormatError(f'{path}: expected an object with a "contacts" list')
    points: list[list[float]] = []
    normals: list[list[list[float]]] = []
    for i, c in enumerate(data["contacts"]):
        if not isinstance(c, dict) or "point" not in c or "normals" not in c:
            raise InputFormatError(
                f'{path}: contact {i}: expected an object with "point" and "normals"'
            )
        points.append(_numbers(c["point"], f"contact {i}: point", path))
        ns = c["normals"]
        if isinstance(ns, list) and len(ns) == 3 and not any(isinstance(x, list) for x in ns):
            ns = [ns]  # one normal written without the outer brackets
        if not isinstance(ns, list) or not ns:
            raise InputFormatError(
                f"{path}: contact {i}: normals must be a non-empty list of [nx, ny, nz], "
                f"got {_json(ns)}"
            )
        normals.append([_numbers(n, f"contact {i}: normal {j}", path) for j, n in enumerate(ns)])
    pts = np.array(points, dtype=np.float64).reshape(-1, 3)
    # apo.dof scales huge normals and coordinates itself (exact powers of two)
    try:
        checked, unit = check_arrays(pts, [np.array(n, dtype=np.float64) for n in normals])
    except InputFormatError as exc:
        raise InputFormatError(f"{path}: {exc}") from None
    return [ContactPoint(point=p.copy(), normals=n) for p, n in zip(checked, unit, strict=True)]


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
    if any(r[1] == "yes" for r in rows):
        print(
            "singular rows: tM..rC, rD_I, rD_II are the singular variants (SM, SD, SC), "
            "as in the paper's Fig. 25"
        )


def run(args: argparse.Namespace) -> int:
    """Run ``apo dof``; return 0, or 2 if any file failed (the others are still reported)."""
    from apo.dof import analyze, dof_result_to_dict

    failed = 0
    rows: list[list[str]] = []
    for path in args.files:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                result = analyze(load_contacts(path))
            except InputFormatError as exc:
                failed += 1
                print(f"apo dof: error: {exc}", file=sys.stderr)
                continue
        for w in caught:
            print(f"apo dof: warning: {path}: {w.message}", file=sys.stderr)
        if args.json:
            print(json.dumps({"file": path, **dof_result_to_dict(result)}, separators=(",", ":")))
        else:
            rows.append(_row(path, result))
    if rows:
        _print_table(rows)
    return 2 if failed else 0
