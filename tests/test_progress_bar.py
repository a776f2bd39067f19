"""The progress bar of ``apo analyze`` on long inputs: drawn as tqdm draws it, without tqdm."""

from __future__ import annotations

import io
import subprocess
import sys

import pytest

import apo.cli.analyze as analyze


def test_progress_bar_draws_throttles_and_wipes(monkeypatch) -> None:
    now = [100.0]
    out = io.StringIO()
    bar = analyze.ProgressBar(2000, "contacts", out, delay=0.5)
    bar.clock = lambda: now[0]
    bar.start = 100.0
    bar.update(100)  # before the delay: nothing
    assert out.getvalue() == ""
    now[0] = 101.0
    bar.update(1000)
    first = out.getvalue()
    assert first == "\rcontacts:  50%|█████     | 1000/2000 [00:01<00:01, 1000.00frame/s]"
    now[0] += analyze.PROGRESS_INTERVAL / 2
    bar.update(1500)  # too soon after the last drawing
    assert out.getvalue() == first
    now[0] = 102.5
    bar.update(1997)
    line = out.getvalue().split("\r")[-1]
    assert line == "contacts: 100%|█████████▉| 1997/2000 [00:02<00:00, 798.80frame/s] "  # padded
    bar.close()
    assert out.getvalue().endswith("\r" + " " * (len(line) - 1) + "\r")
    assert analyze.ProgressBar(10, "x", out).line(0, 0.0).endswith("[00:00<?, 0.00frame/s]")
    assert analyze._clock(3725.0) == "1:02:05"


@pytest.mark.parametrize("frames", [100, 5000])
def test_progress_bar_needs_no_tqdm(frames: int) -> None:
    """Its import took 5.5 MB of resident memory and 30 ms, paid by long inputs only."""
    code = (
        "import io, sys\n"
        "import apo.cli.analyze as a\n"
        "a.PROGRESS_DELAY = 0.0\n"
        "err, sys.stderr = sys.stderr, io.StringIO()\n"
        f"update, close = a.progress_bar({frames}, 'contacts')\n"
        f"_ = update and update({frames} // 2, {frames})\n"
        "close()\n"
        "text, sys.stderr = sys.stderr.getvalue(), err\n"
        "print(('tqdm' in sys.modules), repr(text))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    imported, text = out.stdout.split(" ", 1)
    assert imported == "False"
    assert ("50%|" in text) == (frames >= analyze.PROGRESS_MIN_FRAMES)
