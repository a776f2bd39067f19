"""Typed reading and rounded writing of apo's JSON documents (``task.json``, ``motion.json``).

Pure: dictionaries and lists in, numbers and arrays out; no file I/O (the readers of files
are in :mod:`apo.io`). Every document reader of apo (:func:`apo.task.task_from_dict`,
:func:`apo.motion.program_from_dict`) reads its fields through one :class:`JsonReader`, so a
wrong field always gives the same kind of message: an :class:`apo.errors.InputFormatError`
``"<source>: <field path>: <problem>"``, e.g. ``motion.json: primitives[2].stop.force:
expected a positive number, got 0.0``. Writers round numbers with :func:`rounded` (9
decimals: repeated runs write identical files, and 1e-9 of a millimetre or radian is far
below any tolerance of the method).

>>> rd = JsonReader("task.json")
>>> rd.vector([1, 2, 3], "states[0].pose.position", 3)
array([1., 2., 3.])
>>> rd.positive(0, "parameters.standoff")
Traceback (most recent call last):
...
apo.errors.InputFormatError: task.json: parameters.standoff: expected a positive number, got 0.0
>>> rounded_list([0.1 + 0.2, 1 / 3], 1000.0)
[300.0, 333.333333333]
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from itertools import repeat
from typing import Any

import numpy as np
import numpy.typing as npt

from apo.constants import tol
from apo.errors import InputFormatError
from apo.spatial import pose_from_position_quaternion, position_quaternion_from_pose
from apo.typing import FloatArray

_ESCAPE: Callable[[str], str] = json.encoder.encode_basestring_ascii

__all__ = [
    "JSON_TEXT_DEPTH",
    "JsonItems",
    "JsonReader",
    "RawJson",
    "json_chunks",
    "json_str",
    "one_line_encoder",
    "pose_to_dict",
    "rounded",
    "rounded_list",
    "rounded_rows",
    "rounded_texts",
]

_UNIT_TOLERANCE = tol.json_unit_norm  # why these two differ: apo.constants
_QUATERNION_TOLERANCE = tol.json_quaternion_norm


def rounded(x: float, nd: int = 9) -> float:
    """Return ``x`` as a float rounded to ``nd`` decimals (for JSON output)."""
    return float(round(float(x), nd))


#: ``"%.9f"`` texts of numbers below this size (in magnitude) have at most 15 significant
#: digits: :func:`rounded_texts` takes them as they are (trailing zeros dropped).
_FIXED_BELOW = 1e6
_BELOW_1E4 = re.compile(r",-?0\.0000[0-9]*(?=,)")


def rounded_texts(values: Sequence[float]) -> list[str]:
    """Return ``[repr(rounded(v)) for v in values]`` (JSON numbers) for finite floats.

    Made at once: one ``"%.9f"`` format of all the values, trailing zeros cut by regular
    expressions (twice as fast as ``round`` and ``repr`` per value; task.json has tens of
    thousands). The same text: ``round(v, 9)`` is the double nearest to the correctly
    rounded decimal that ``"%.9f"`` prints, and below 1e6 that decimal has at most 15
    significant digits, so it is the shortest text of that double, i.e. ``repr``'s, except
    that ``repr`` writes magnitudes below 1e-4 with an exponent (done for those only). Larger
    or non-finite values are converted one by one (``repr``: ``nan``, ``inf``).
    """
    if not len(values):
        return []
    if not all(-_FIXED_BELOW < v < _FIXED_BELOW for v in (min(values), max(values))):
        return [repr(round(float(v), 9)) for v in values]
    text = ("%.9f," * len(values)) % tuple(values)  # each "%.9f" ends with a comma
    text = "," + ",".join(map(str.rstrip, text.split(","), repeat("0"))).replace(".,", ".0,")
    if "0.0000" in text:
        text = _BELOW_1E4.sub(_exponent_form, text)
    return text.split(",")[1:-1]


def _exponent_form(m: re.Match[str]) -> str:
    """``,`` and the ``repr`` of a number written ``0.0000...`` (an exponent unless zero)."""
    v = float(m.group()[1:])
    return f",{v!r}" if v else m.group()


def json_str(s: str) -> str:
    """Return ``s`` as a JSON string, as :func:`json.dumps` writes it (ASCII, escaped)."""
    return _ESCAPE(s)


class RawJson(str):
    """JSON text that :func:`json_chunks` writes as it is (an item made as text already)."""

    __slots__ = ()


def rounded_list(a: npt.ArrayLike, scale: float = 1.0) -> list[float]:
    """Return the entries of ``a`` (flattened) times ``scale``, each :func:`rounded`.

    On plain floats (numpy scalars cost ten times more; task.json holds many).
    """
    arr = np.asarray(a, dtype=float).ravel()
    return [round(v, 9) for v in (arr if scale == 1.0 else arr * scale).tolist()]


def rounded_rows(a: npt.ArrayLike) -> list[list[float]]:
    """Return the 3-vectors of ``a`` (reshaped to (k, 3)) as rounded lists."""
    rows = np.asarray(a, dtype=float).reshape(-1, 3).tolist()  # one conversion: plain floats
    return [[round(v, 9) for v in row] for row in rows]


def pose_to_dict(X: FloatArray, scale: float = 1.0) -> dict[str, list[float]]:
    """Return ``{"position": p * scale, "quaternion": [qw, qx, qy, qz]}`` of a 4x4 pose."""
    p, q = position_quaternion_from_pose(X)
    return {"position": rounded_list(p, scale), "quaternion": rounded_list(q)}


class JsonReader:
    """Typed accessors that raise :class:`InputFormatError` naming the source and the field.

    Every accessor takes the value and ``where``, the field's path in the document
    (``"primitives[2].stop.force"``), and returns the value converted (floats, numpy
    arrays) or raises ``InputFormatError("<source>: <where>: <problem>")``.

    Parameters
    ----------
    source : str
        The document's name in messages (a file name), ``"document"`` if empty.
    """

    def __init__(self, source: str) -> None:
        self.source = source or "document"

    def fail(self, where: str, what: str) -> InputFormatError:
        """Return (not raise) the error for field ``where``."""
        return InputFormatError(f"{self.source}: {where}: {what}")

    # ---------------------------------------------------------------- structure
    def obj(self, d: Any, where: str) -> Mapping[str, Any]:
        """Return ``d``, which must be a JSON object."""
        if not isinstance(d, Mapping):
            raise self.fail(where, f"expected an object, got {type(d).__name__}")
        return d

    def get(self, d: Mapping[str, Any], key: str, where: str) -> Any:
        """Return the required field ``key`` of object ``d`` (``where`` names ``d``)."""
        if key not in d:
            raise self.fail(where, f"missing field {key!r}")
        return d[key]

    def lst(self, v: Any, where: str, n: int | None = None) -> Sequence[Any]:
        """Return ``v``, which must be a JSON list (of exactly ``n`` entries if given)."""
        if not isinstance(v, list | tuple):
            raise self.fail(where, f"expected a list, got {type(v).__name__}")
        if n is not None and len(v) != n:
            raise self.fail(where, f"expected {n} entries, got {len(v)}")
        return v

    # ---------------------------------------------------------------- scalars
    def string(self, v: Any, where: str, choices: Sequence[str] | None = None) -> str:
        """Return ``v``, which must be a string (one of ``choices`` if given)."""
        if not isinstance(v, str):
            raise self.fail(where, f"expected a string, got {type(v).__name__}")
        if choices is not None and v not in choices:
            raise self.fail(where, f"expected one of {list(choices)}, got {v!r}")
        return v

    def integer(self, v: Any, where: str) -> int:
        """Return ``v``, which must be an integer (not a boolean)."""
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(where, f"expected an integer, got {v!r}")
        return v

    def optional_int(self, v: Any, where: str) -> int | None:
        """Return ``v``, which must be an integer or null."""
        return None if v is None else self.integer(v, where)

    def boolean(self, v: Any, where: str) -> bool:
        """Return ``v``, which must be ``true`` or ``false``."""
        if not isinstance(v, bool):
            raise self.fail(where, f"expected true or false, got {v!r}")
        return v

    def number(self, v: Any, where: str) -> float:
        """Return ``v`` as a float; it must be a finite number (not a boolean)."""
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise self.fail(where, f"expected a finite number, got {v!r}")
        return float(v)

    def positive(self, v: Any, where: str) -> float:
        """Return ``v`` as a float; it must be a finite number > 0."""
        x = self.number(v, where)
        if x <= 0:
            raise self.fail(where, f"expected a positive number, got {x!r}")
        return x

    def non_negative(self, v: Any, where: str) -> float:
        """Return ``v`` as a float; it must be a finite number >= 0."""
        x = self.number(v, where)
        if x < 0:
            raise self.fail(where, f"expected a non-negative number, got {x!r}")
        return x

    # ---------------------------------------------------------------- arrays
    def vector(self, v: Any, where: str, n: int) -> FloatArray:
        """Return a list of ``n`` finite numbers as a float array."""
        items = self.lst(v, where, n)
        return np.array([self.number(x, f"{where}[{i}]") for i, x in enumerate(items)])

    def unit(self, v: Any, where: str, *, allow_zero: bool = False) -> FloatArray:
        """Return a unit 3-vector (or, with ``allow_zero``, an exact zero vector)."""
        a = self.vector(v, where, 3)
        n = float(np.linalg.norm(a))
        if abs(n - 1.0) > _UNIT_TOLERANCE and not (allow_zero and n < tol.zero_norm):
            raise self.fail(where, f"expected a unit vector, got {a.tolist()}")
        return a

    def rows(self, v: Any, where: str, *, orthonormal: bool = True) -> FloatArray:
        """At most 3 rows of 3 numbers, shape (k, 3); orthonormal unless told otherwise."""
        items = self.lst(v, where)
        if len(items) > 3:
            raise self.fail(where, f"expected at most 3 rows, got {len(items)}")
        a = np.array(
            [self.vector(r, f"{where}[{i}]", 3) for i, r in enumerate(items)], dtype=float
        ).reshape(-1, 3)
        eye = np.eye(len(a))
        if orthonormal and a.size and not np.allclose(a @ a.T, eye, atol=_UNIT_TOLERANCE):
            raise self.fail(where, "rows must be orthonormal unit vectors")
        return a

    def pose(self, v: Any, where: str, scale: float = 1.0) -> FloatArray:
        """``{"position", "quaternion"}`` as a 4x4 pose, the position times ``scale``."""
        d = self.obj(v, where)
        p = self.vector(self.get(d, "position", where), f"{where}.position", 3) * scale
        q = self.vector(self.get(d, "quaternion", where), f"{where}.quaternion", 4)
        if abs(float(np.linalg.norm(q)) - 1.0) > _QUATERNION_TOLERANCE:
            raise self.fail(f"{where}.quaternion", f"not a unit quaternion: {q.tolist()}")
        return pose_from_position_quaternion(p, q)

    def feature(self, v: Any, where: str) -> tuple[str, int]:
        """Return a model feature id ``["v" | "e" | "f", index >= 0]`` as a tuple."""
        items = self.lst(v, where, 2)
        kind = self.string(items[0], f"{where}[0]", ("v", "e", "f"))
        idx = self.integer(items[1], f"{where}[1]")
        if idx < 0:
            raise self.fail(where, f"negative feature index {idx}")
        return (kind, idx)


# --------------------------------------------------------------------------------------------
# Writing: JSON text laid out by depth, in chunks
# --------------------------------------------------------------------------------------------

#: Containers nested this deep are written on one line by :func:`apo.outputs.json_text`.
JSON_TEXT_DEPTH = 4


class JsonItems:
    """A JSON array whose items are made while it is written (:func:`json_chunks`).

    ``items()`` returns a fresh iterable of the items each time; ``n`` is their number and
    ``nested`` says whether they are objects or arrays (laid out one per line) or plain
    values. A long array (the states of a long task) is then never held whole: only the
    items of the block being written.
    """

    def __init__(self, n: int, items: Callable[[], Iterable[Any]], *, nested: bool = True):
        self.n = n
        self.items = items
        self.nested = nested

    def __len__(self) -> int:
        return self.n

    def __iter__(self) -> Iterator[Any]:
        return iter(self.items())


#: Pieces of text gathered into one chunk by :func:`json_chunks`.
JSON_CHUNK_PIECES = 2048


def json_chunks(data: Any, *, depth: int = JSON_TEXT_DEPTH) -> Iterator[str]:
    """Yield the text of :func:`json_text` in chunks (joined, the same text).

    ``data`` may hold :class:`JsonItems` arrays, written item by item: the text and the
    items of a long array are never in memory whole, only one chunk of
    ``JSON_CHUNK_PIECES`` pieces.
    """
    flat = one_line_encoder()
    out: list[str] = []
    nested = (dict, list, tuple, JsonItems)

    def plain(v: Any, level: int) -> bool:
        if isinstance(v, JsonItems):
            return level >= depth or not (v.n and v.nested)
        return (
            level >= depth
            or not isinstance(v, nested)
            or not any(isinstance(x, nested) for x in (v.values() if isinstance(v, dict) else v))
        )

    def put(v: Any, level: int) -> Iterator[str]:
        if type(v) is RawJson:
            out.append(v)
            return
        if plain(v, level):
            out.append(flat(list(v) if isinstance(v, JsonItems) else v))
            return
        pad = "\n" + "  " * (level + 1)
        if isinstance(v, dict):
            out.append("{")
            for i, (k, x) in enumerate(v.items()):
                out.append(("," if i else "") + pad + flat(str(k)) + ": ")
                yield from put(x, level + 1)
        else:
            out.append("[")
            for i, x in enumerate(v):
                out.append(("," if i else "") + pad)
                yield from put(x, level + 1)
                if len(out) >= JSON_CHUNK_PIECES:
                    yield "".join(out)
                    out.clear()
        out.append("\n" + "  " * level + ("}" if isinstance(v, dict) else "]"))

    yield from put(data, 0)
    out.append("\n")
    yield "".join(out)


def one_line_encoder() -> Callable[[Any], str]:
    """Return ``json.dumps(v, separators=(", ", ": "))`` as a function, made once.

    ``JSONEncoder.encode`` builds a new C encoder at every call (a few microseconds: most
    of the cost of a short list); this builds it once (``json.encoder.c_make_encoder``, with
    the arguments ``JSONEncoder.iterencode`` gives it), or falls back to ``encode``.
    """
    from json import encoder as std

    enc = json.JSONEncoder(separators=(", ", ": "))
    make = getattr(std, "c_make_encoder", None)
    if make is None:
        return enc.encode
    try:
        c = make(
            None, enc.default, std.encode_basestring_ascii, None, ": ", ", ", False, False, True
        )
        if "".join(c([1.5, {"a": None}], 0)) != '[1.5, {"a": null}]':
            return enc.encode
    except Exception:  # another Python's private signature
        return enc.encode
    esc = std.encode_basestring_ascii

    def one_line(v: Any) -> str:
        return esc(v) if isinstance(v, str) else "".join(c(v, 0))

    return one_line
