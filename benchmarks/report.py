"""Benchmark of the HTML report: size, cost of writing it, time to interactive.

Cases:

- ``real-41``: the first author's 41-frame demonstration (skipped when ``../shared`` is
  absent): the cost ``apo analyze`` pays to write ``report.html`` (render + write), cold
  (first call in the process: reads the plotly.js bundle) and warm, against the analysis.
- ``synthetic-3000``: the built-in T-peg / U-slot example scripted over 3,000 frames
  (``apo.synthetic.peg_in_hole_2d``, 0.5 mm / 0.5 deg noise), recognised, its report
  written: file size, write cost, time to interactive in headless Chromium (navigation start
  to every plot drawn and the controls live: ``window.apoReady``), and the time one slider
  step takes to redraw (``apo.seek``, promise resolved).

Prints a table and writes ``benchmarks/results/report.json``. Targets (issue 10): the
3,000-frame page under 10 MB and interactive in under 3 s.

    python benchmarks/report.py [--frames 3000] [--runs 3]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

RESULTS = Path(__file__).parent / "results" / "report.json"


def _write_cost(rec: Any, G: Any, E: Any, X: Any, out: Path, repeat: int) -> dict[str, float]:
    from apo.report import html as html_mod
    from apo.report.sources import recognition_report

    html_mod.plotly_js.cache_clear()
    html_mod._asset.cache_clear()
    times = []
    size = 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        doc = recognition_report(rec, grasped=G, environment=E, X_observed=X)
        size = html_mod.write_report(out, doc)
        times.append(time.perf_counter() - t0)
    return {
        "write_cold_ms": 1e3 * times[0],
        "write_warm_ms": 1e3 * min(times[1:] or times),
        "bytes": float(size),
    }


def bench_real(tmp: Path, repeat: int) -> dict[str, Any] | None:
    from apo.io import load_polyhedron
    from apo.io.poses import load_demonstration
    from apo.recognition import recognize_frames

    data = Path(__file__).resolve().parents[2] / "shared" / "data" / "apo-peg-in-hole"
    if not data.is_dir():
        return None
    dem = load_demonstration(data / "peg_in_hole.pose.list")
    G = load_polyhedron(dem.grasped_path)
    E = load_polyhedron(dem.environment_path)
    t0 = time.perf_counter()
    rec = recognize_frames(G, E, dem.times, dem.X_EG, units="mm")
    t_rec = time.perf_counter() - t0
    cost = _write_cost(rec, G, E, dem.X_EG, tmp / "real.html", repeat)
    return {
        "case": "real-41",
        "frames": len(dem.times),
        "recognition_s": t_rec,
        **cost,
        "path": str(tmp / "real.html"),
    }


def bench_synthetic(tmp: Path, n_frames: int, repeat: int) -> dict[str, Any]:
    from apo import synthetic
    from apo.recognition import recognize_frames

    demo = synthetic.peg_in_hole_2d(n_frames)
    noisy = synthetic.add_noise(demo, sigma_mm=0.5, sigma_deg=0.5, seed=0)
    t0 = time.perf_counter()
    rec = recognize_frames(demo.grasped, demo.environment, noisy.times, noisy.X_EG, units="mm")
    t_rec = time.perf_counter() - t0
    cost = _write_cost(rec, demo.grasped, demo.environment, noisy.X_EG, tmp / "s.html", repeat)
    return {
        "case": f"synthetic-{n_frames}",
        "frames": n_frames,
        "states": len(rec.task.states),
        "rejected": len(rec.task.rejected),
        "recognition_s": t_rec,
        **cost,
        "path": str(tmp / "s.html"),
    }


def browser_times(path: str, runs: int) -> dict[str, Any]:
    """Time to interactive (ms) over ``runs`` fresh loads, and one slider step (ms)."""
    from apo.errors import ApoError
    from apo.report.browser import headless_chromium, open_report

    try:
        tti = []
        with headless_chromium() as drv:
            for _ in range(runs):
                tti.append(open_report(drv, path))
                drv.get("about:blank")
            open_report(drv, path)
            steps = drv.execute_async_script(
                """
                var done = arguments[arguments.length - 1];
                var n = window.apo.data.frames.frame.shape[0], out = [], k = 0;
                function next() {
                  if (k >= 20) { done(out); return; }
                  var t0 = performance.now();
                  window.apo.seek(Math.floor((k + 1) * n / 21)).then(function () {
                    out.push(performance.now() - t0); k++; next();
                  });
                }
                next();
                """
            )
            severe = [e["message"] for e in drv.get_log("browser") if e["level"] == "SEVERE"]
    except ApoError as exc:
        return {"browser": f"not run: {exc}"}
    return {
        "tti_ms": tti,
        "tti_median_ms": statistics.median(tti),
        "seek_median_ms": statistics.median(steps),
        "seek_max_ms": max(steps),
        "console_errors": severe,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--runs", type=int, default=3, help="browser loads (median reported)")
    ap.add_argument("--repeat", type=int, default=5, help="report writes per case")
    args = ap.parse_args()
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="apo-bench-report-") as d:
        tmp = Path(d)
        real = bench_real(tmp, args.repeat)
        if real is not None:
            real.update(browser_times(real.pop("path"), args.runs))
            rows.append(real)
        syn = bench_synthetic(tmp, args.frames, args.repeat)
        syn.update(browser_times(syn.pop("path"), args.runs))
        rows.append(syn)
    head = (
        f"{'case':<16} {'frames':>6} {'size MB':>8} {'write cold ms':>13} {'warm ms':>8} "
        f"{'recog s':>8} {'TTI ms':>7} {'seek ms':>8}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        tti = r.get("tti_median_ms", float("nan"))
        seek = r.get("seek_median_ms", float("nan"))
        print(
            f"{r['case']:<16} {r['frames']:>6} {r['bytes'] / 1e6:>8.2f} "
            f"{r['write_cold_ms']:>13.1f} {r['write_warm_ms']:>8.1f} {r['recognition_s']:>8.2f} "
            f"{tti:>7.0f} {seek:>8.0f}"
        )
        if "browser" in r:
            print(f"  {r['browser']}")
    print(
        "TTI: navigation start to every plot drawn (headless Chromium, SwiftShader WebGL), "
        f"median of {args.runs}; seek: one slider step redrawn, median of 20"
    )
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    info = {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "numpy": np.__version__,
        "targets": {"size_mb_max": 10, "tti_s_max": 3},
    }
    RESULTS.write_text(json.dumps({"info": info, "cases": rows}, indent=2) + "\n")
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
