"""report.html's plotly.js bundle copied from its file: the same page as the bytes joined."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from apo.cli import main
from apo.report import html
from apo.report.html import report_data, report_parts, write_report


@pytest.fixture(scope="module")
def doc(tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--out", str(out), "--no-plot", "--no-report", "--seed", "8"]) == 0
    return json.loads((out / "task.json").read_text())


def test_copied_bundle_is_the_page(doc: dict, tmp_path: Path, monkeypatch) -> None:
    data = report_data(doc)
    want = b"".join(report_parts(data))
    assert write_report(tmp_path / "a.html", data) == len(want)
    assert (tmp_path / "a.html").read_bytes() == want

    def no_sendfile(*args: object) -> int:
        raise OSError("not here")

    monkeypatch.setattr(os, "sendfile", no_sendfile)  # the bytes written instead
    assert write_report(tmp_path / "b.html", data) == len(want)
    assert (tmp_path / "b.html").read_bytes() == want


def test_a_bundle_that_needs_escaping_is_escaped(
    doc: dict, tmp_path: Path, monkeypatch, request
) -> None:
    bundle = tmp_path / "plotly.min.js"
    bundle.write_bytes(b"var a='</script>';" * 1000)
    monkeypatch.setattr(html, "_plotly_bundle", lambda: bundle)
    html.plotly_js.cache_clear()  # kept per process: the real bundle after this test
    request.addfinalizer(html.plotly_js.cache_clear)
    data = report_data(doc)
    write_report(tmp_path / "c.html", data)
    page = (tmp_path / "c.html").read_bytes()
    assert page == b"".join(report_parts(data))
    assert b"var a='<\\/script>';" in page and b"var a='</script>'" not in page


def test_bundle_scanned_a_window_at_a_time(tmp_path: Path, monkeypatch) -> None:
    """``</script`` is found wherever it lies, across the windows' edges too; the size is
    the file's (the windows map a part of the bundle at a time: less resident memory)."""
    import mmap

    from apo.report import html

    monkeypatch.setattr(html, "SCAN_WINDOW", mmap.ALLOCATIONGRANULARITY)
    w, needle = mmap.ALLOCATIONGRANULARITY, b"</script"
    for at in (None, 0, 5, w - 4, w - len(needle), w, 2 * w - 1, 3 * w + 17):
        body = bytearray(b"x" * (3 * w + 40))
        if at is not None:
            body[at : at + len(needle)] = needle
        path = tmp_path / f"b{at}.js"
        path.write_bytes(bytes(body[: 3 * w + 40]))
        assert html._file_lacks(path, needle) == (at is None, 3 * w + 40), at
    empty = tmp_path / "empty.js"
    empty.write_bytes(b"")
    assert html._file_lacks(empty, needle) == (True, 0)
