"""Read a ``task.json`` file and find the model files it names.

:func:`read_task` is :func:`apo.task.task_from_dict` on a file, with the file's problems
(missing, unreadable, not JSON) reported as :class:`apo.errors.InputFormatError` naming it;
:func:`model_paths` resolves the models' recorded paths against the folder of ``task.json``
(``docs/task-json.md``) and checks that they exist.
"""

from __future__ import annotations

from pathlib import Path

from apo.errors import InputFormatError
from apo.io.jsonfile import read_json
from apo.outputs import sha256_file
from apo.task import ModelRef, TaskModel, task_from_dict

__all__ = ["model_paths", "read_task", "task_ref"]


def read_task(path: str | Path) -> TaskModel:
    """Read and validate a ``task.json``; return the :class:`~apo.task.TaskModel` (SI).

    Raises
    ------
    InputFormatError
        Missing or unreadable file, not UTF-8, malformed JSON (with line and column), or any
        field :func:`apo.task.task_from_dict` rejects. Every message starts with the path.
    """
    p = Path(path)
    return task_from_dict(read_json(p), source=str(p))


def model_paths(task: TaskModel, path: str | Path) -> tuple[Path, Path]:
    """Return the grasped and environment model files of ``task`` read from ``path``.

    Relative paths are resolved against the folder of ``path`` (the ``task.json``).

    Raises
    ------
    InputFormatError
        A model file that does not exist (naming ``task.json``, the field and the path).
    """
    base = Path(path).parent
    out: list[Path] = []
    for role, ref in (("grasped", task.grasped), ("environment", task.environment)):
        if not ref.path:
            raise InputFormatError(f"{path}: models.{role}.path: empty (a built-in model?)")
        p = Path(ref.path)
        p = p if p.is_absolute() else base / p
        if not p.is_file():
            raise InputFormatError(
                f"{path}: models.{role}.path: model file not found: {p} "
                f"(paths are relative to the folder of task.json)"
            )
        out.append(p)
    return out[0], out[1]


def task_ref(path: str | Path) -> ModelRef:
    """Return the reference (path as given, SHA-256 of the content, name) of a task file."""
    p = Path(path)
    return ModelRef(path=str(p), sha256=sha256_file(p), name=p.name)
