"""Write a command's whole output set into a folder: checked first, atomic, one writer at a time.

Every command that writes a folder of results (``apo analyze``, ``apo demo``, later
``apo plan`` / ``apo replay``) goes through :class:`OutputSet`::

    with OutputSet("results", label="--out") as outs:    # checks, locks: before the work
        ...                                              # the analysis
        outs.write_json("task.json", data)
        outs.write_text("frames.csv", text)
        render_into(outs.path("frames"))                 # any writer, into the set
    # here results/ holds the new set, whole; an exception left the old one untouched

Semantics (the full story is in ``docs/outputs.md``):

- The destination is checked when the set is opened, before any work: an existing file,
  a path under a file, a folder that is not writable, the current folder (or one of its
  ancestors) or a mount point are refused with :class:`~apo.errors.OutputError`.
- The files are written into a private folder beside the destination
  (``.<name>.apo-new-*``), then swapped in with one atomic ``renameat2(RENAME_EXCHANGE)``
  (Linux; elsewhere two renames, with recovery at the next opening). A process killed at
  any moment leaves either the old set or the new one, whole, at the destination.
- A manifest, ``.apo-outputs.json``, is written last into the set: it names every file of
  the set with its size and SHA-256. Entries of the destination that the previous manifest
  does not name (the user's own files) are carried over into the new set (hard links).
- A second writer on the same destination is refused with a message naming the process
  that holds it (a ``flock`` on ``.<name>.apo-lock`` beside the destination).
- Files and folders are created with the process's umask (a destination that exists keeps
  its mode).

:func:`atomic_file` is the single-file version (``apo report --out F``, ``apo track``).
"""

from __future__ import annotations

import ctypes
import errno
import hashlib
import json
import os
import shutil
import sys
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from contextlib import ExitStack, contextmanager, suppress
from pathlib import Path
from types import TracebackType
from typing import Any

from apo.errors import OutputError
from apo.jsonform import JSON_TEXT_DEPTH, JsonItems, json_chunks

__all__ = [
    "MANIFEST",
    "MANIFEST_FORMAT",
    "JsonItems",
    "OutputSet",
    "atomic_file",
    "check_file_destination",
    "json_chunks",
    "json_text",
    "output_files",
    "read_manifest",
    "sha256_file",
]

MANIFEST = ".apo-outputs.json"
"""Name of the manifest inside an output folder: the files of the set, written last."""
MANIFEST_FORMAT = "apo.outputs/1"
"""Value of the manifest's ``format`` key."""

_NEW, _OLD, _LOCK = ".apo-new-", ".apo-old-", ".apo-lock"
_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def umask() -> int:
    """Return the process's umask (without changing it for longer than a system call)."""
    try:  # Linux >= 4.7: no window in which another thread sees a changed umask
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    old = os.umask(0o022)
    os.umask(old)
    return old


def _why(exc: OSError) -> str:
    return exc.strerror or str(exc)


def _nearest_existing(path: Path) -> Path:
    """Return ``path`` or its nearest existing ancestor (following symbolic links)."""
    p = path
    while not os.path.lexists(p) and p != p.parent:
        p = p.parent
    return p


def _check_creatable(path: Path, label: str, shown: Path | None = None) -> None:
    """Raise :class:`OutputError` if ``path`` (which does not exist) cannot be created."""
    anc = _nearest_existing(path.parent)
    where = f"{label} {shown or path}: cannot be created"
    if not anc.is_dir():
        raise OutputError(
            f"{where}: {anc} is a file, not a folder"
            if anc.exists()
            else f"{where}: {anc} is a broken link"
        )
    if not os.access(anc, os.W_OK | os.X_OK):
        raise OutputError(f"{where}: folder {anc} is not writable")


def check_file_destination(path: str | Path, *, label: str = "output file") -> Path:
    """Check that the file ``path`` can be written; return it. Raises :class:`OutputError`."""
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{label} {p}: is a folder; give a file name")
    if p.exists():
        if not os.access(p.parent if str(p.parent) else Path("."), os.W_OK | os.X_OK):
            raise OutputError(f"{label} {p}: folder {p.parent} is not writable")
    else:
        _check_creatable(p, label)
    return p


@contextmanager
def atomic_file(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it over ``path`` on success.

    The file gets the mode of the file it replaces, or ``0666 & ~umask`` for a new one (not
    the ``0600`` of :func:`tempfile.mkstemp`). On an exception the temporary file is removed
    and ``path`` is untouched.
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".apo-tmp", dir=target.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        try:
            mode = target.stat().st_mode & 0o7777
        except OSError:
            mode = 0o666 & ~umask()
        os.chmod(tmp, mode)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@contextmanager
def output_files(
    paths: Sequence[str | Path], *, label: str = "output file"
) -> Iterator[list[Path]]:
    """Check, lock and write a few loose files; yield their temporary paths, in order.

    For outputs that live beside other files (``apo track --out poses.csv`` and its
    ``poses.environment.json``): every destination is checked on entry (before the work),
    the first one is locked against a second writer, and on success each temporary file is
    renamed over its destination (mode as in :func:`atomic_file`). The renames follow one
    another: unlike :class:`OutputSet`, a kill between them can pair a new file with an old one.
    """
    finals = [check_file_destination(p, label=label) for p in paths]
    first = Path(os.path.abspath(finals[0]))
    first.parent.mkdir(parents=True, exist_ok=True)
    lock = _Lock(first.parent / f".{first.name}{_LOCK}", finals[0], label, "file")
    try:
        lock.acquire()
    except OutputError:
        raise
    except OSError as exc:
        raise OutputError(f"{label} {finals[0]}: cannot write: {_why(exc)}") from None
    try:
        with ExitStack() as stack:
            yield [stack.enter_context(atomic_file(p)) for p in finals]
    finally:
        lock.release()


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap the paths ``a`` and ``b``; False if the system cannot."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    rc = fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def sha256_file(path: str | Path) -> str:
    """Return the hex SHA-256 of a file's content."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_manifest(folder: str | Path) -> dict[str, Any] | None:
    """Return the manifest of an output folder, or None if it has none (or an unreadable one).

    ``{"format": "apo.outputs/1", "files": {relative path: {"bytes": n, "sha256": hex}}}``;
    only the files of the set are named (not the entries carried over from the user).
    """
    try:
        doc = json.loads((Path(folder) / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or not isinstance(doc.get("files"), dict):
        return None
    return doc


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst, follow_symlinks=False)
    except OSError:
        shutil.copy2(src, dst, follow_symlinks=False)


class _Lock:
    """An exclusive, non-blocking lock on ``path`` (``flock``), naming its holder in the file."""

    def __init__(self, path: Path, dest: Path, label: str, what: str = "output folder") -> None:
        self.path = path
        self.fd: int | None = None
        self.dest, self.label, self.what = dest, label, what

    def acquire(self) -> None:
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not POSIX: no lock
            return
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666 & ~umask())
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                holder = os.pread(fd, 4096, 0).decode("utf-8", "replace").strip()
                os.close(fd)
                raise OutputError(
                    f"{self.label} {self.dest}: another apo process is writing this "
                    f"{self.what} ({holder or 'unknown process'}); wait for it to finish or choose "
                    f"another {self.label}"
                ) from None
            # the holder before us may have unlinked the file between our open and our lock
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        prog = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python"
        if prog in ("__main__.py", "-c", "-m"):
            prog = "apo"
        cmd = " ".join([prog, *sys.argv[1:]])
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}: {cmd[:200]}\n".encode(), 0)
        self.fd = fd

    def release(self) -> None:
        if self.fd is None:
            return
        with suppress(OSError):
            os.unlink(self.path)  # while still holding it: a waiter re-checks the inode
        os.close(self.fd)
        self.fd = None


class OutputSet:
    """The whole set of files a command writes into the folder ``dest``, committed atomically.

    Parameters
    ----------
    dest : str or Path
        The output folder. It may exist (its set is replaced as a whole) or not (it is
        created, with its missing parents).
    label : str
        How error messages name the destination (e.g. ``"--out"``).

    Use it as a context manager: entering checks the destination, takes the lock and
    creates the private staging folder (so open it *before* the work); leaving without an
    exception commits the set; leaving with one discards it. See the module docstring.
    """

    def __init__(self, dest: str | Path, *, label: str = "output folder") -> None:
        self.given = Path(dest)
        self.label = label
        self.dest = Path(os.path.realpath(self.given))
        self.staging: Path | None = None
        self._lock = _Lock(self.dest.parent / f".{self.dest.name}{_LOCK}", self.given, self.label)
        self._made: list[Path] = []
        self.committed = False

    # -- opening ---------------------------------------------------------------------------
    def __enter__(self) -> OutputSet:
        self.check()
        self._make_parents()
        try:
            self._lock.acquire()
            self._recover()
            staging = tempfile.mkdtemp(prefix=f".{self.dest.name}{_NEW}", dir=self.dest.parent)
        except OutputError:
            self._abandon()
            raise
        except OSError as exc:
            self._abandon()
            raise OutputError(
                f"{self.label} {self.given}: cannot write here: {_why(exc)}"
            ) from None
        except BaseException:
            self._abandon()
            raise
        self.staging = Path(staging)
        try:
            mode = self.dest.stat().st_mode & 0o7777
        except OSError:
            mode = 0o777 & ~umask()
        os.chmod(staging, mode)
        return self

    def check(self) -> None:
        """Raise :class:`OutputError` if the destination cannot take an output set."""
        d, label = self.dest, f"{self.label} {self.given}"
        if d.exists() and not d.is_dir():
            raise OutputError(f"{label}: is an existing file, not a folder")
        if not d.exists():
            _check_creatable(d, self.label, self.given)
            return
        if os.path.ismount(d) or d == d.parent:
            raise OutputError(f"{label}: is a mount point; choose a folder inside it")
        cwd = Path(os.path.realpath(Path.cwd()))
        if cwd == d or d in cwd.parents:
            raise OutputError(
                f"{label}: is the current folder (or contains it); the output folder is "
                "replaced as a whole: choose a sub-folder, e.g. ./results"
            )
        for p, what in ((d, "folder"), (d.parent, "its parent folder")):
            if not os.access(p, os.W_OK | os.X_OK):
                raise OutputError(f"{label}: {what} {p} is not writable")

    def _make_parents(self) -> None:
        missing = []
        p = self.dest.parent
        while not p.exists():
            missing.append(p)
            p = p.parent
        try:
            for m in reversed(missing):
                m.mkdir()
                self._made.append(m)
        except OSError as exc:
            self._abandon()
            raise OutputError(
                f"{self.label} {self.given}: cannot create {m}: {_why(exc)}"
            ) from None

    def _siblings(self, marker: str) -> list[Path]:
        prefix = f".{self.dest.name}{marker}"
        return sorted(p for p in self.dest.parent.iterdir() if p.name.startswith(prefix))

    def _recover(self) -> None:
        """Under the lock: finish what a killed writer left (restore, then remove its folders)."""
        olds = self._siblings(_OLD)
        if not os.path.lexists(self.dest) and olds:
            os.rename(olds[-1], self.dest)  # killed between the two renames of the fallback
            olds = olds[:-1]
        for p in olds + self._siblings(_NEW):
            shutil.rmtree(p, ignore_errors=True)

    # -- filling ---------------------------------------------------------------------------
    def _staged(self) -> Path:
        if self.staging is None:
            raise RuntimeError("OutputSet used outside its `with` block")
        return self.staging

    def path(self, name: str) -> Path:
        """Return where to write the entry ``name`` (a relative path) of the set now.

        The parent folders are created. The file appears at :meth:`final` after the commit.
        """
        rel = Path(name)
        if rel.is_absolute() or ".." in rel.parts or not rel.parts or name == MANIFEST:
            raise ValueError(f"output name must be a plain relative path, got {name!r}")
        p = self._staged() / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def final(self, name: str) -> Path:
        """Return where the entry ``name`` will be once the set is committed."""
        return self.given / name

    def write_text(self, name: str, text: str) -> Path:
        """Write ``text`` (UTF-8, Unix line ends) as ``name``; return its final path."""
        with open(self.path(name), "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
        return self.final(name)

    def write_chunks(self, name: str, chunks: Iterable[str]) -> Path:
        """Write the text ``chunks`` one after another as ``name`` (UTF-8, Unix line ends).

        For large files made block by block: only one chunk is in memory at a time.
        """
        with open(self.path(name), "w", encoding="utf-8", newline="\n") as fh:
            for chunk in chunks:
                fh.write(chunk)
        return self.final(name)

    def write_bytes(self, name: str, data: bytes) -> Path:
        """Write ``data`` as ``name``; return its final path."""
        self.path(name).write_bytes(data)
        return self.final(name)

    def write_json(self, name: str, data: Any, *, indent: int | None = 2) -> Path:
        """Write ``data`` as JSON (with a final newline) as ``name``; return its final path."""
        return self.write_text(name, json.dumps(data, indent=indent) + "\n")

    def add_file(self, name: str, source: str | Path) -> Path:
        """Copy the file ``source`` into the set as ``name``; return its final path."""
        shutil.copyfile(source, self.path(name))
        return self.final(name)

    def names(self) -> list[str]:
        """Relative paths of the files in the set so far (sorted, ``/`` separated)."""
        root = self._staged()
        return sorted(
            p.relative_to(root).as_posix()
            for p in root.rglob("*")
            if (p.is_file() or p.is_symlink()) and p.name != MANIFEST
        )

    # -- committing ------------------------------------------------------------------------
    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            if exc_type is None:
                self.commit()
        finally:
            self._abandon()

    def commit(self) -> None:
        """Write the manifest, carry the user's files over, swap the set in."""
        staging = self._staged()
        names = self.names()
        files = {
            n: {"bytes": (staging / n).stat().st_size, "sha256": sha256_file(staging / n)}
            for n in names
        }
        top = {n.split("/")[0] for n in names}
        if self.dest.is_dir():
            self._carry_over(staging, top)
        manifest = {"format": MANIFEST_FORMAT, "files": files}
        (staging / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")
        try:
            self._swap(staging)
        except OSError as exc:
            raise OutputError(
                f"{self.label} {self.given}: cannot put the outputs in place: {_why(exc)}"
            ) from None
        self.staging = None
        self.committed = True

    def _carry_over(self, staging: Path, new_top: set[str]) -> None:
        """Link the destination's entries that are not apo's previous set into ``staging``."""
        old = read_manifest(self.dest)
        ours = {n.split("/")[0] for n in old["files"]} if old else set()
        for entry in os.scandir(self.dest):
            if entry.name in new_top or entry.name in ours or entry.name == MANIFEST:
                continue
            target = staging / entry.name
            if entry.is_dir(follow_symlinks=False):
                shutil.copytree(entry.path, target, symlinks=True, copy_function=_link_or_copy)
            else:
                _link_or_copy(entry.path, str(target))

    def _swap(self, staging: Path) -> None:
        if not os.path.lexists(self.dest):
            os.rename(staging, self.dest)
            return
        if _exchange(staging, self.dest):
            shutil.rmtree(staging, ignore_errors=True)  # it now holds the old set
            return
        old = Path(tempfile.mkdtemp(prefix=f".{self.dest.name}{_OLD}", dir=self.dest.parent))
        os.replace(self.dest, old)  # an empty folder is replaced
        os.rename(staging, self.dest)  # a kill between the two: restored at the next opening
        shutil.rmtree(old, ignore_errors=True)

    def _abandon(self) -> None:
        """Remove the staging folder (if not committed), the lock and parents we created."""
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging = None
        self._lock.release()
        if not self.committed:
            for m in reversed(self._made):
                with suppress(OSError):
                    m.rmdir()
        self._made = []


def json_text(data: Any, *, depth: int = JSON_TEXT_DEPTH) -> str:
    """Return ``data`` as JSON text, indented by two spaces, with a final newline.

    Objects and arrays are laid out as ``json.dumps(data, indent=2)`` lays them out, except
    that one holding no object or array (``[0, 5]``, a position) and any nested ``depth``
    levels deep are written on one line (``", "`` and ``": "`` separators). ``json.dumps``
    with an indent runs the pure-Python encoder (about 3 s for the 27 MB task of 30,000
    frames); this way the C encoder writes every one-line part (ten times faster), and a
    long task stays readable: one line per contact element or sub-skill. ``json.loads``
    reads back the same document as from ``json.dumps(data)``.

    Examples
    --------
    >>> print(json_text({"a": [1, {"b": [2, 3]}], "c": {}, "d": {"e": [[1]]}}, depth=2), end="")
    {
      "a": [
        1,
        {"b": [2, 3]}
      ],
      "c": {},
      "d": {
        "e": [[1]]
      }
    }
    """
    return "".join(json_chunks(data, depth=depth))
