"""Benchmark of contact finding: per-frame time, fast (ContactFinder) vs naive (all pairs).

Scenes: the T-peg seated in the U-slot (16 + 16 vertices, 10 faces each; 20 elements), the
same pair 10 cm apart (broad phase only), a 20,480-triangle geodesic sphere resting on a
5,120-triangle one (1 element), and a 10,000-triangle cylinder (2,500-gon prism) standing on
a box (2,500 VF elements on the bottom cap). Times are the best of several repeats, per
frame, in a warm finder (per-model data built once).

Run ``.venv/bin/python benchmarks/contacts.py [--quick]``; prints a table and writes
``benchmarks/results/contacts.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from apo.contact import ContactFinder
from apo.geometry import polyhedron_from_triangles
from apo.shapes import box, cylinder, icosphere, t_peg, u_block

ROOT = Path(__file__).resolve().parents[1]


def _best_per_call(fn: Any, number: int, repeat: int = 5) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best


def _pose(t: tuple[float, float, float]) -> np.ndarray:
    X = np.eye(4)
    X[:3, 3] = t
    return X


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="fewer repeats, skip naive on big")
    args = ap.parse_args()
    n_small = 50 if args.quick else 300

    peg, slot = t_peg(), u_block(slot_depth=0.070)
    big_ball = icosphere(5, radius=0.05)
    plate_src = icosphere(4, radius=0.5)
    plate = polyhedron_from_triangles(
        plate_src.vertices + np.array([0.0, 0.0, -0.5]), np.concatenate(plate_src.face_triangles)
    )
    cyl = cylinder(0.01, 0.02, sections=2500)
    table = box([0.2, 0.2, 0.05], center=[0.0, 0.0, -0.025])
    scenes = [
        ("T-peg seated in U-slot", peg, slot, _pose((0, 0.018, 0)), None, n_small),
        ("T-peg 10 cm above (no contact)", peg, slot, _pose((0, 0.118, 0)), None, n_small),
        ("icosphere 20k tris on 5k tris", big_ball, plate, _pose((0, 0, 0.05)), 2e-4, 5),
        ("cylinder 10k tris on a box", cyl, table, _pose((0, 0, 0)), 2e-5, 3),
    ]
    rows = []
    for name, G, E, X, thr, number in scenes:
        t0 = time.perf_counter()
        finder = ContactFinder(G, E, threshold=thr)
        state = finder.find(X)  # builds per-model data and local cones
        setup = time.perf_counter() - t0
        fast = _best_per_call(lambda f=finder, x=X: f.find(x), number)
        big = len(G.vertices) > 1000
        naive = None
        # The naive search is all pairs: skip it where that is tens of seconds.
        too_big = len(G.edges) * len(E.edges) > 2e7 or len(G.vertices) * len(E.faces) > 2e6
        if not (args.quick and big) and not too_big:
            naive = _best_per_call(
                lambda f=finder, x=X: f.find_naive(x),
                1 if big else number // 10 + 1,
                1 if big else 3,
            )
            assert finder.find_naive(X).key == state.key
        rows.append(
            {
                "scene": name,
                "triangles": [int(sum(len(t) for t in P.face_triangles)) for P in (G, E)],
                "elements": len(state.elements),
                "touching": len(state.touching),
                "setup_s": setup,
                "fast_ms": fast * 1e3,
                "naive_ms": None if naive is None else naive * 1e3,
            }
        )
        nv = "-" if naive is None else f"{naive * 1e3:10.2f}"
        print(
            f"{name:34s} tris {rows[-1]['triangles']!s:16s} elements {len(state.elements):5d}  "
            f"fast {fast * 1e3:8.3f} ms  naive {nv} ms  (setup {setup:.2f} s)"
        )
    out = ROOT / "benchmarks" / "results" / "contacts.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            {"python": platform.python_version(), "machine": platform.machine(), "rows": rows},
            indent=2,
        )
        + "\n"
    )


if __name__ == "__main__":
    main()
