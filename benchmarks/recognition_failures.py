"""List the accuracy benchmark's failing runs: (kind, level, demo, seed), expected vs got.

The runs are those of ``benchmarks/recognition.py``'s accuracy section (same demonstrations,
noise and seeds: seed ``s`` is the noise seed of every demonstration and the random variant
``random_variant(10000 + s)``), spread over ``--jobs`` processes. For each failure it prints
the expected and recognised state sequences (Fig. 25 numbers), and the sub-skills where they
differ; a summary line per (kind, level) gives the share of exact runs.

Run ``.venv/bin/python benchmarks/recognition_failures.py --levels 'white=0,0.5;drift=1'
[--seeds 50] [--first 0] [--demos 'random variant,T-peg'] [--jobs 2]``.
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from recognition import _demos, _noisy, exact_result


def _letters(fig: list[tuple[int, ...]]) -> str:
    return " | ".join("".join(str(v) for v in f) for f in fig)


def _run(job: tuple[str, float, int, tuple[str, ...]]) -> list[dict[str, Any]]:
    """Recognise every demonstration of one (kind, level, seed); return one row per run."""
    from apo.recognition import recognize_frames

    kind, sigma, seed, only = job
    rows = []
    for name, demo in _demos(seed).items():
        if only and name not in only:
            continue
        noisy = _noisy(demo, kind, sigma, seed)
        rec = recognize_frames(noisy.grasped, noisy.environment, noisy.times, noisy.X_EG)
        task = rec.task
        segs = noisy.segments()
        want = [tuple(noisy.true_states[int(noisy.labels[a])].fig25) for _s, a, _b in segs]
        row: dict[str, Any] = {
            "kind": kind, "sigma": sigma, "seed": seed, "demo": name,
            "ok": exact_result(noisy, task),
            "want": want, "got": [tuple(s.fig25) for s in task.states],
            "want_sub": [k for et in noisy.expected_subskills for k in et.subskills],
            "got_sub": task.subskill_sequence(),
            "variant": noisy.meta.get("variant", {}).get("name", ""),
            "fps": round(float(noisy.meta["fps"]), 1),
            "threshold_mm": round(task.threshold * 1e3, 2),
            "noise_mm": round(rec.noise.distance * 1e3, 2) if rec.noise else None,
        }  # fmt: skip
        rows.append(row)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--levels", default="white=0,0.5,1,2")
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--demos", default="", help="comma list of demonstration names")
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    only = tuple(d for d in args.demos.split(",") if d)
    jobs = [
        (kind, float(v), seed, only)
        for kind, vals in (item.split("=") for item in args.levels.split(";") if item)
        for v in vals.split(",")
        for seed in range(args.first, args.first + args.seeds)
    ]
    tally: dict[tuple[str, float], list[int]] = {}
    with multiprocessing.Pool(args.jobs) as pool:
        for rows in pool.imap(_run, jobs):
            for r in rows:
                t = tally.setdefault((r["kind"], r["sigma"]), [0, 0])
                t[0] += r["ok"]
                t[1] += 1
                if r["ok"]:
                    continue
                print(
                    f"FAIL {r['kind']} {r['sigma']} seed {r['seed']} {r['demo']}"
                    f" ({r['variant']} {r['fps']} fps, threshold {r['threshold_mm']} mm,"
                    f" noise {r['noise_mm']} mm)\n  want {_letters(r['want'])}\n"
                    f"  got  {_letters(r['got'])}",
                    flush=True,
                )
                if r["want_sub"] != r["got_sub"]:
                    print(f"  sub want {r['want_sub']}\n  sub got  {r['got_sub']}", flush=True)
    for (kind, sigma), (ok, n) in tally.items():
        print(f"{kind} {sigma}: {ok}/{n} exact ({ok / n:.1%})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
