"""Read a JSON file with one clear error per problem: the one JSON-file reader of apo.

Every command and reader that takes a JSON file (``task.json``, ``motion.json``,
``replay.json``, camera calibrations, ``apo dof`` contact files) reads it with
:func:`read_json`, so a missing, unreadable, non-UTF-8 or malformed file gives the same
:class:`apo.errors.InputFormatError`, starting with the path. What the document must contain
is checked by the caller.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from apo.errors import InputFormatError

__all__ = ["read_json"]


def read_json(path: str | Path, *, what: str = "file") -> Any:
    """Return the parsed JSON document of ``path``.

    Parameters
    ----------
    path : str or Path
        The file.
    what : str
        What the file is, for the message of a missing file (``"{path}: {what} not found"``,
        e.g. ``"camera calibration file"``).

    Raises
    ------
    InputFormatError
        ``{path}: {what} not found``; ``{path}: cannot read (...)`` (a folder, no
        permission, not UTF-8 text); ``{path}: not valid JSON: {reason} at line L, column C``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> folder = tempfile.TemporaryDirectory()
    >>> p = pathlib.Path(folder.name) / "a.json"
    >>> _ = p.write_text('{"a": [1,, 2]}')
    >>> read_json(p)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    apo.errors.InputFormatError: .../a.json: not valid JSON: Expecting value at line 1, column 10
    >>> _ = p.write_text('{"a": [1, 2]}')
    >>> read_json(p)
    {'a': [1, 2]}
    >>> folder.cleanup()
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputFormatError(f"{p}: {what} not found") from None
    except UnicodeDecodeError as exc:
        raise InputFormatError(f"{p}: cannot read (not UTF-8 text: {exc.reason})") from None
    except OSError as exc:
        raise InputFormatError(f"{p}: cannot read ({exc.strerror or exc})") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputFormatError(
            f"{p}: not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}"
        ) from None
