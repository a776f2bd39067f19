"""``apo contacts GRASPED ENVIRONMENT --pose ...``: contact elements and DOF at one pose.

The pose ``"x y z qw qx qy qz"`` is ``X_EG``, the grasped object's pose in the environment's
frame (position in ``--units``). Points are printed in ``--units``, normals are unit vectors,
both in the environment frame; the DOF fields are those of ``apo dof`` (``docs/contacts.md``).
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

import numpy as np

from apo.cli import warnings_to_stderr
from apo.constants import UNITS
from apo.errors import InputFormatError

_UNITS = UNITS  # the one units table (apo.constants, a leaf module: cheap to import)


def register(subparsers: Any) -> None:
    """Add the ``contacts`` sub-command."""
    p = subparsers.add_parser(
        "contacts",
        help="contact elements and DOF of a grasped model posed in an environment model",
        description=(
            "Find the contact elements between the grasped object, at the given pose in the "
            "environment's frame, and the environment object; print them with the DOF "
            "indices of the contact state (as `apo dof`). Points and normals are in the "
            "environment frame; lengths in --units."
        ),
    )
    p.add_argument("grasped", metavar="GRASPED", help="grasped model (STEP, STL, OBJ, PLY)")
    p.add_argument("environment", metavar="ENVIRONMENT", help="environment model file")
    p.add_argument(
        "--pose",
        required=True,
        metavar="'x y z qw qx qy qz'",
        help=(
            "pose of the grasped object in the environment frame: position in --units, "
            "quaternion scalar first (normalised here)"
        ),
    )
    p.add_argument(
        "--units",
        default="mm",
        help=(
            "length unit of --pose, --threshold, the output and mesh files: mm (default), "
            "cm, m or in; STEP files use the unit they declare"
        ),
    )
    p.add_argument(
        "--threshold",
        metavar="D",
        help=(
            "contact distance threshold in --units (default: 1e-3 of the smaller model's "
            "bounding-box diagonal, for exact poses; observed poses need a few mm)"
        ),
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object: frame, units, threshold, elements and the DOF fields",
    )
    p.set_defaults(func=run)


def parse_pose(text: str, unit: float) -> np.ndarray:
    """Parse ``"x y z qw qx qy qz"`` (position in a unit of ``unit`` metres) into a 4x4 pose.

    Raises
    ------
    InputFormatError
        Not 7 finite numbers, or a zero quaternion.
    """
    from apo.spatial import pose_from_position_quaternion

    parts = text.replace(",", " ").split()
    if len(parts) != 7:
        raise InputFormatError(
            f"--pose: expected 7 numbers 'x y z qw qx qy qz', got {len(parts)}: {text!r}"
        )
    try:
        vals = [float(x) for x in parts]
    except ValueError as exc:
        raise InputFormatError(f"--pose: not a number in {text!r}") from exc
    if not all(math.isfinite(v) for v in vals):
        raise InputFormatError(f"--pose: non-finite value in {text!r}")
    q = np.asarray(vals[3:])
    if float(np.linalg.norm(q)) < 1e-9:
        raise InputFormatError(f"--pose: the quaternion has zero norm in {text!r}")
    return pose_from_position_quaternion(np.asarray(vals[:3]) * unit, q)


def run(args: argparse.Namespace) -> int:
    """Run ``apo contacts``; return the exit code.

    Warnings raised while reading the models (a mesh flipped inside-out, sliver triangles
    absorbed, a STEP file's own unit overriding ``--units``) are printed on stderr as
    ``apo contacts: warning: ...``.
    """
    from apo.contact import contact_points, default_threshold, find_contacts
    from apo.dof import analyze, dof_result_to_dict
    from apo.io.meshes import load_polyhedron

    if args.units not in _UNITS:
        raise InputFormatError(
            f"--units: unknown unit {args.units!r}; expected one of {', '.join(_UNITS)}"
        )
    unit = _UNITS[args.units]
    X_EG = parse_pose(args.pose, unit)
    threshold = None
    if args.threshold is not None:
        try:
            threshold = float(args.threshold) * unit
        except ValueError as exc:
            raise InputFormatError(f"--threshold: not a number: {args.threshold!r}") from exc
        if not (math.isfinite(threshold) and threshold > 0):
            raise InputFormatError(f"--threshold: must be positive, got {args.threshold!r}")
    with warnings_to_stderr("apo contacts"):
        grasped = load_polyhedron(args.grasped, units=args.units)
        environment = load_polyhedron(args.environment, units=args.units)
    if threshold is None:
        threshold = default_threshold(grasped, environment)
    state = find_contacts(grasped, environment, X_EG, threshold=threshold)
    dof = analyze(contact_points(state))
    elements: list[dict[str, Any]] = [
        {
            "kind": el.kind.value,
            "grasped": [el.grasped[0], el.grasped[1]],
            "environment": [el.environment[0], el.environment[1]],
            "point": [float(x) / unit for x in el.point],
            "normals": [[float(x) for x in n] for n in el.normals],
        }
        for el in state.elements
    ]
    dof_dict = dof_result_to_dict(dof)
    if args.json:
        out = {
            "frame": "environment",
            "units": args.units,
            "threshold": threshold / unit,
            "elements": elements,
        }
        out.update(dof_dict)
        print(json.dumps(out, indent=2))
        return 0
    print(f"frame: environment, units: {args.units}, threshold: {threshold / unit:.6g}")
    print(f"{len(elements)} contact element(s){' (singular state)' if state.singular else ''}")
    for el in elements:
        g = f"{el['grasped'][0]}{el['grasped'][1]}"
        e = f"{el['environment'][0]}{el['environment'][1]}"
        pt = " ".join(f"{x:.4g}" for x in el["point"])
        nr = "; ".join(" ".join(f"{x:+.3f}" for x in n) for n in el["normals"])
        print(f"  {el['kind']:2s} G:{g:5s} E:{e:5s} point ({pt})  normals [{nr}]")
    f = dof.fig25
    label = "singular M D C" if dof.singular else "M D C"
    print(
        f"translation {label}: {f[0]} {f[1]} {f[2]}   rotation {label}: {f[3]} {f[4]} {f[5]}   "
        f"restraining t r: {f[6]} {f[7]}"
    )
    for key in ("singular", "translation", "rotation", "all", "singular_dof", "restraining"):
        print(f"{key}: {json.dumps(dof_dict[key])}")
    return 0
