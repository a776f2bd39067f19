"""Benchmark of the core: DOF analysis per state and contact finding per frame (issue 2, 7).

DOF analysis (``apo.dof.analyze``): time per state, median (target <= 1 ms), over a set of
realistic states: the canonical states of ``tests/test_dof.py``, the distinct states the
contact finder sees along the first author's demonstration (41 poses, at the recognition
threshold and at the finder's tight default) and along the synthetic demonstrations of
``apo.synthetic`` (exact poses at the default threshold, 1 mm / 1 deg noise at the
recognition threshold).

Contact finding: time per frame of ``ContactFinder`` on
- the first author's T-peg and U-hole (``peg.step``, ``hole.step``, in mm, read with
  ``apo.io``) at the 41 poses of ``peg_in_hole.pose.list`` (skipped, with the reason, when
  ``../shared`` is absent), at the recognition threshold and at the default one;
- the project's own ``apo.shapes.t_peg`` / ``u_block``: the synthetic peg-in-hole
  demonstration with 1 mm / 1 deg noise (60 frames), the peg seated, the peg 10 cm away;
- meshes of at least 10,000 triangles: a 20,480-triangle geodesic sphere on a 5,120-triangle
  one, a 10,000-triangle cylinder (2,500-gon prism) standing on a box (2,500 VF elements);
  three poses each (resting, turned about z, lifted by half the threshold).

Columns: ``batch`` is ``find_batch`` over all the frames (targets: <= 0.2 ms per frame for
the T-peg/U-hole, <= 20 ms for 10,000 triangles), ``labels`` ``find_labels`` over all the
frames (the state keys only, what recognition runs per frame), ``find`` one frame at a time,
``naive``
the all-pairs search (``find_naive``), ``before`` the per-frame ``find`` of the contact
finder at the revision ``--before`` (default: the last one before the search was
vectorised), loaded from git into this run; the ratios are ``naive / batch`` and
``before / batch``. ``same`` says that every variant found the same states (element keys and
touching pairs) at every frame, and ``find_labels`` the same grouping of the frames. Times
are the best of several repeats, warm per-model data.

Run ``.venv/bin/python benchmarks/core.py [--quick] [--before REV | --no-before]``; prints
two tables and writes ``benchmarks/results/core.json``. Timings on a shared machine are
noisy: compare the columns of one run.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from apo.contact import DEFAULT_THRESHOLD_FRACTION, ContactFinder, contact_points
from apo.dof import ContactPoint, analyze
from apo.geometry import Polyhedron, polyhedron_from_triangles
from apo.recognition import default_threshold as recognition_threshold
from apo.shapes import box, cylinder, icosphere, t_peg, u_block
from apo.synthetic import add_noise, all_demos, peg_in_hole_2d

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "apo-peg-in-hole"
BEFORE = "3cf4701~1"  # the last revision with the per-frame search


def _best(fn: Callable[[], Any], number: int, repeat: int) -> float:
    """Best time (s) of one call of ``fn`` over ``repeat`` rounds of ``number`` calls."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best


def _pose(t: Sequence[float], angle: float = 0.0) -> np.ndarray:
    """Pose translated by ``t`` and turned by ``angle`` about z."""
    X = np.eye(4)
    c, s = np.cos(angle), np.sin(angle)
    X[:2, :2] = [[c, -s], [s, c]]
    X[:3, 3] = t
    return X


def load_before(rev: str) -> tuple[ModuleType | None, str]:
    """``apo.contact`` as it was at ``rev`` (from git), or None and the reason."""
    try:
        src = subprocess.run(
            ["git", "show", f"{rev}:src/apo/contact.py"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        return None, f"git show {rev}:src/apo/contact.py failed ({exc})"
    spec = importlib.util.spec_from_loader("apo_contact_before", loader=None)
    assert spec is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["apo_contact_before"] = mod  # dataclasses look their module up
    exec(compile(src, f"{rev}:src/apo/contact.py", "exec"), mod.__dict__)
    return mod, rev


def _real_models() -> tuple[Polyhedron, Polyhedron, np.ndarray] | str:
    """The first author's models (metres) and 41 poses, or why they are missing."""
    if not DATA.is_dir():
        return f"first author's data not found at {DATA}: its rows are skipped"
    from apo.io.meshes import load_polyhedron
    from apo.io.poses import load_demonstration

    G = load_polyhedron(DATA / "peg.step")  # STEP in mm, read in metres
    E = load_polyhedron(DATA / "hole.step")
    X = load_demonstration(DATA / "peg_in_hole.pose.list", units="mm").X_EG
    return G, E, np.asarray(X)


# --------------------------------------------------------------------------------------------
# DOF analysis
# --------------------------------------------------------------------------------------------


def dof_states() -> tuple[list[tuple[str, list[ContactPoint]]], list[str]]:
    """(source, contact points) of every state of the benchmark set, and skip notes."""
    notes: list[str] = []
    out: list[tuple[str, list[ContactPoint]]] = []
    sys.path.insert(0, str(ROOT / "tests"))
    import test_dof

    out += [("canonical (tests/test_dof.py)", case[0]) for case in test_dof.CASES.values()]

    def along(source: str, G: Polyhedron, E: Polyhedron, X: np.ndarray, thr: float | None) -> None:
        seen: set[Any] = set()
        for s in ContactFinder(G, E, threshold=thr).find_batch(X):
            if s.elements and s.key not in seen:
                seen.add(s.key)
                out.append((source, contact_points(s)))

    real = _real_models()
    if isinstance(real, str):
        notes.append(real)
    else:
        G, E, X = real
        along("real demonstration", G, E, X, recognition_threshold(G, E))
        along("real demonstration", G, E, X, None)
    for demo in all_demos().values():
        G, E = demo.grasped, demo.environment
        along("synthetic demonstrations", G, E, demo.X_EG_true, None)
        noisy = add_noise(demo, sigma_mm=1.0, sigma_deg=1.0, seed=0)
        along("synthetic demonstrations", G, E, noisy.X_EG, recognition_threshold(G, E))
    return out, notes


def bench_dof(quick: bool) -> dict[str, Any]:
    states, notes = dof_states()
    number = 5 if quick else 20
    times = []
    for _, contacts in states:
        analyze(contacts)  # warm
        times.append(_best(lambda c=contacts: analyze(c), number, 3))
    t = np.array(times) * 1e3
    by_source: dict[str, list[float]] = {}
    for (src, _), ms in zip(states, t.tolist(), strict=True):
        by_source.setdefault(src, []).append(ms)
    return {
        "states": len(states),
        "median_ms": float(np.median(t)),
        "p90_ms": float(np.percentile(t, 90)),
        "max_ms": float(t.max()),
        "over_1ms": int(np.count_nonzero(t > 1.0)),
        "target_median_ms": 1.0,
        "by_source": {
            k: {"states": len(v), "median_ms": float(np.median(v))} for k, v in by_source.items()
        },
        "notes": notes,
    }


# --------------------------------------------------------------------------------------------
# Contact finding
# --------------------------------------------------------------------------------------------


def contact_scenes() -> tuple[list[dict[str, Any]], list[str]]:
    """Scenes: name, models, poses (N, 4, 4), threshold, target; and skip notes."""
    notes: list[str] = []
    scenes: list[dict[str, Any]] = []

    def add(
        name: str, G: Polyhedron, E: Polyhedron, X: np.ndarray, thr: float | None, target: float
    ) -> None:
        scenes.append(
            {"scene": name, "G": G, "E": E, "X": X, "threshold": thr, "target_ms": target}
        )

    real = _real_models()
    if isinstance(real, str):
        notes.append(real)
    else:
        G, E, X = real
        add("real T-peg/U-hole, recognition threshold", G, E, X, recognition_threshold(G, E), 0.2)
        add("real T-peg/U-hole, default threshold", G, E, X, None, 0.2)
    demo = add_noise(peg_in_hole_2d(), sigma_mm=1.0, sigma_deg=1.0, seed=0)
    G, E = demo.grasped, demo.environment
    add("apo.shapes T-peg/U-slot, noisy demo", G, E, demo.X_EG, recognition_threshold(G, E), 0.2)
    peg, slot = t_peg(), u_block(slot_depth=0.070)
    rng = np.random.default_rng(0)
    jitter = 0.2 * DEFAULT_THRESHOLD_FRACTION * min(peg.scale, slot.scale)
    for name, y in (("seated", 0.018), ("10 cm above", 0.118)):
        # 50 frames held still, jittered by 0.2 default thresholds: the same elements
        X = np.stack([_pose([0, y, 0] + jitter * rng.uniform(-1, 1, 3)) for _ in range(50)])
        add(f"apo.shapes T-peg {name}, held", peg, slot, X, None, 0.2)
    ball = icosphere(5, radius=0.05)
    src = icosphere(4, radius=0.5)
    plate = polyhedron_from_triangles(
        src.vertices + np.array([0.0, 0.0, -0.5]), np.concatenate(src.face_triangles)
    )
    cyl = cylinder(0.01, 0.02, sections=2500)
    table = box([0.2, 0.2, 0.05], center=[0.0, 0.0, -0.025])
    for name, G, E, z, thr in (
        ("icosphere 20k tris on 5k tris", ball, plate, 0.05, 2e-4),
        ("icosphere 20k tris on a box", ball, table, 0.05, 2e-4),
        ("cylinder 10k tris on a box", cyl, table, 0.0, 2e-5),
    ):
        X = np.stack([_pose((0, 0, z)), _pose((0, 0, z), 0.3), _pose((0, 0, z + 0.5 * thr))])
        add(name, G, E, X, thr, 20.0)
    return scenes, notes


def _same(a: Sequence[Any], b: Sequence[Any]) -> bool:
    return all(x.key == y.key and x.touching == y.touching for x, y in zip(a, b, strict=True))


def _same_labels(states: Sequence[Any], labels: Any) -> bool:
    """``find_labels``' labels group the frames as the keys of ``find_batch``'s states do."""
    index: dict[Any, int] = {}
    return [index.setdefault(s.key, len(index)) for s in states] == labels.tolist()


def bench_contacts(
    quick: bool, before: ModuleType | None
) -> tuple[list[dict[str, Any]], list[str]]:
    scenes, notes = contact_scenes()
    rows = []
    repeat = 2 if quick else 5
    for sc in scenes:
        G, E, X, thr = sc["G"], sc["E"], sc["X"], sc["threshold"]
        n = len(X)
        big = len(G.vertices) + len(E.vertices) > 2000
        reps = 1 if big else max(1, 400 // n)
        t0 = time.perf_counter()
        finder = ContactFinder(G, E, threshold=thr)
        states = finder.find_batch(X)  # builds the per-model data and local cones
        setup = time.perf_counter() - t0
        batch = _best(lambda f=finder, x=X: f.find_batch(x), reps, repeat) / n
        labels = _best(lambda f=finder, x=X: f.find_labels(x), reps, repeat) / n
        same = _same_labels(states, finder.find_labels(X)[0])
        single = _best(lambda f=finder, x=X: [f.find(p) for p in x], reps, repeat) / n
        same = same and _same(states, [finder.find(p) for p in X])
        # The naive search is all pairs: skip it where that takes minutes; once on big ones.
        pairs = max(len(G.edges) * len(E.edges), 10 * len(G.vertices) * len(E.faces))
        naive: float | None = None
        if pairs > 5e7:
            notes.append(f"{sc['scene']}: naive search skipped ({pairs:.1e} pairs)")
        elif big:
            naive = _best(lambda f=finder, x=X[0]: f.find_naive(x), 1, 1)
            same = same and _same(states[:1], [finder.find_naive(X[0])])
        else:
            naive = (
                _best(
                    lambda f=finder, x=X: [f.find_naive(p) for p in x], max(1, reps // 10), repeat
                )
                / n
            )
            same = same and _same(states, [finder.find_naive(p) for p in X])
        before_ms = None
        if before is not None:
            old = before.ContactFinder(G, E, threshold=thr)
            same = same and _same(states, old.find_batch(X))
            before_ms = 1e3 * _best(lambda f=old, x=X: [f.find(p) for p in x], reps, repeat) / n
        r = {
            "scene": sc["scene"],
            "frames": n,
            "triangles": [int(sum(len(t) for t in P.face_triangles)) for P in (G, E)],
            "threshold_m": finder.threshold,
            "elements_per_frame": float(np.mean([len(s.elements) for s in states])),
            "touching_per_frame": float(np.mean([len(s.touching) for s in states])),
            "setup_s": setup,
            "batch_ms": batch * 1e3,
            "labels_ms": labels * 1e3,
            "find_ms": single * 1e3,
            "naive_ms": None if naive is None else naive * 1e3,
            "before_ms": before_ms,
            "naive_over_batch": None if naive is None else naive / batch,
            "before_over_batch": None if before_ms is None else before_ms / (batch * 1e3),
            "target_ms": sc["target_ms"],
            "meets_target": batch * 1e3 <= sc["target_ms"],
            "same": same,
        }
        rows.append(r)
        b = "-" if before_ms is None else f"{before_ms:.3f}"
        nv = "-" if naive is None else f"{naive * 1e3:.3f}"
        rn = "-" if naive is None else f"{naive / batch:.1f}x"
        rb = "-" if r["before_over_batch"] is None else f"{r['before_over_batch']:.1f}x"
        print(
            f"{r['scene']:42s} {n:4d} {r['elements_per_frame']:6.1f} {r['batch_ms']:8.3f} "
            f"{r['labels_ms']:8.3f} "
            f"{r['find_ms']:8.3f} {nv:>9s} {b:>8s} {rn:>8s} "
            f"{rb:>6s} {sc['target_ms']:6.1f} {'yes' if r['meets_target'] else 'NO':>4s} "
            f"{'yes' if same else 'NO':>4s}",
            flush=True,
        )
    return rows, notes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats")
    ap.add_argument("--before", default=BEFORE, help=f"git revision of 'before' ({BEFORE})")
    ap.add_argument("--no-before", action="store_true", help="skip the 'before' column")
    args = ap.parse_args()

    print("DOF analysis per state (apo.dof.analyze), target: median <= 1 ms")
    dof = bench_dof(args.quick)
    print(
        f"  {dof['states']} states: median {dof['median_ms']:.3f} ms, 90th percentile "
        f"{dof['p90_ms']:.3f} ms, max {dof['max_ms']:.3f} ms, over 1 ms: {dof['over_1ms']}"
    )
    for src, v in dof["by_source"].items():
        print(f"    {src:32s} {v['states']:3d} states, median {v['median_ms']:.3f} ms")
    for note in dof["notes"]:
        print(f"  skipped: {note}")

    before, why = (None, "--no-before") if args.no_before else load_before(args.before)
    print("\nContact finding, ms per frame; ratios naive / batch and before / batch")
    print(f"  before: {'skipped, ' if before is None else ''}{why}")
    print(
        f"{'scene':42s} {'frms':>4s} {'elems':>6s} {'batch':>8s} {'labels':>8s} {'find':>8s} "
        f"{'naive':>9s} "
        f"{'before':>8s} {'naive/b':>8s} {'bef/b':>6s} {'target':>6s} {'met':>4s} {'same':>4s}"
    )
    contacts, notes = bench_contacts(args.quick, before)
    for note in notes:
        print(f"  skipped: {note}")
    out = ROOT / "benchmarks" / "results" / "core.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    result = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": platform.machine(),
        "before": None if before is None else why,
        "dof": dof,
        "contacts": contacts,
    }
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"\nwrote {out.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
