"""task.json's states and transitions made as text: the same bytes as their dictionaries."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

from apo import task as task_mod
from apo.jsonform import rounded_texts
from apo.outputs import json_text
from apo.recognition import recognize_frames
from apo.synthetic import add_noise, random_variant


def _values(rng: np.random.Generator, n: int) -> list[float]:
    """Finite floats of every magnitude that task.json holds, with the edge cases of rounding."""
    exps = rng.choice([-13, -12, -10, -9, -8, -6, -5, -4, -3, -2, 0, 1, 2, 3, 5, 6, 7], n)
    vals = (rng.uniform(-1.0, 1.0, n) * 10.0**exps).tolist()
    edges = [0.0, -0.0, 1.0, -1.0, 5e-10, -5e-10, 4.99999999e-10, 5.000000001e-10, 1e-9,
             1e-4, -1e-4, 0.0001 - 1e-13, 0.00009999999995, 10.00001, -20.00005,
             100.0000123, 99999.9999999999, 999999.9999999999, 1e6, -1e6, 123456.123456789,
             0.5e-9 * 3, 2.5e-9, 0.0000123, -0.00001]  # fmt: skip
    halves = (rng.integers(-(10**6), 10**6, 200) / 2.0 ** rng.integers(0, 40, 200)).tolist()
    rounded = [round(v, int(d)) for v, d in zip(vals[:300], rng.integers(0, 11, 300), strict=True)]
    return vals + edges + halves + rounded


@pytest.mark.parametrize("seed", [5, 61])
def test_rounded_texts_are_the_json_numbers(seed: int) -> None:
    rng = np.random.default_rng(seed)
    vals = _values(rng, 20_000)
    assert rounded_texts(vals) == [repr(round(v, 9)) for v in vals]
    for _ in range(300):  # short runs of small values (no value for the slow path)
        some = list(rng.choice(vals, int(rng.integers(1, 12))))
        assert rounded_texts(some) == [repr(round(float(v), 9)) for v in some]
    assert rounded_texts([]) == []


def _task(seed: int, units: str) -> Any:
    demo = add_noise(random_variant(seed), sigma_mm=1.5, sigma_deg=1.5, seed=seed)
    rec = recognize_frames(demo.grasped, demo.environment, demo.times, demo.X_EG, units=units)
    return rec.task


def _same_text(task: Any) -> None:
    want = json_text(task_mod.task_to_dict(task), depth=2)
    assert "".join(task_mod.task_json_chunks(task, depth=2)) == want


@pytest.mark.parametrize(("seed", "units"), [(8, "mm"), (44, "m"), (73, "in"), (90, "cm")])
def test_state_and_transition_lines_are_their_dicts_encoded(monkeypatch, seed: int, units: str):
    task = _task(seed, units)
    assert task.states and task.transitions
    for block in (1, 3, 256):
        monkeypatch.setattr(task_mod, "JSON_BLOCK_STATES", block)
        _same_text(task)


def test_lines_of_unusual_values_are_their_dicts_encoded(monkeypatch) -> None:
    """Escaped ids, tiny and large numbers, and numbers that are not finite (the dicts)."""
    monkeypatch.setattr(task_mod, "JSON_BLOCK_STATES", 2)
    task = _task(19, "mm")
    states = list(task.states)
    with_elements = next(i for i, s in enumerate(states) if s.elements)
    s = states[with_elements]
    e = s.elements[0]
    tiny = dataclasses.replace(e, point=np.array([1e-12, -3e-7, 2e5]), normals=-e.normals)
    X = s.X_EG.copy()
    X[:3, 3] = [4e-8, -0.0, 1234.5]
    states[with_elements] = dataclasses.replace(s, X_EG=X, elements=(tiny, *s.elements[1:]))

    def odd_id(i: str | None) -> str | None:
        return None if i is None else f'{i}"\u00e9\\\n'

    odd = dataclasses.replace(
        task,
        states=tuple(dataclasses.replace(s, id=odd_id(s.id), same_as=odd_id(s.same_as))
                     for s in states),
        transitions=tuple(dataclasses.replace(t, from_id=odd_id(t.from_id), to_id=odd_id(t.to_id))
                          for t in task.transitions),
    )  # fmt: skip
    _same_text(odd)
    for bad in ("pose", "normal", "direction"):
        st = list(odd.states)
        tr = list(odd.transitions)
        if bad == "pose":
            X = st[0].X_EG.copy()
            X[0, 3] = math.nan
            st[0] = dataclasses.replace(st[0], X_EG=X)
        elif bad == "normal":
            e = st[with_elements].elements[0]
            nan = dataclasses.replace(e, normals=np.full_like(np.asarray(e.normals), math.inf))
            st[with_elements] = dataclasses.replace(st[with_elements], elements=(nan,))
        else:
            i = next(i for i, t in enumerate(tr) if t.subskills)
            v = dataclasses.replace(tr[i].subskills[0], direction=np.array([math.nan, 0.0, 1.0]))
            tr[i] = dataclasses.replace(tr[i], subskills=(v,))
        _same_text(dataclasses.replace(odd, states=tuple(st), transitions=tuple(tr)))
