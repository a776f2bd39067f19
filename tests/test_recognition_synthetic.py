"""Recognition of the scripted demonstrations against their ground truth (issue 3, section 6).

Each demonstration of :mod:`apo.synthetic` knows its true contact states (element keys at
the exact poses) and the sub-skills and critical transitions derived by hand from the
paper's rules. Recognition must reproduce them exactly: without noise, and with Gaussian pose
noise of 1 mm / 1 deg for fixed seeds.
"""

from __future__ import annotations

import pytest

from apo import synthetic
from apo.recognition import recognize_frames

DEMOS = synthetic.all_demos()


def _recognise(demo, sigma: float, seed: int):
    noisy = synthetic.add_noise(demo, sigma_mm=sigma, sigma_deg=sigma, seed=seed) if sigma else demo
    return recognize_frames(demo.grasped, demo.environment, noisy.times, noisy.X_EG)


def _check(demo, rec) -> None:
    task = rec.task
    # states: the same sequence of contact states (element keys of each visited state)
    got_keys = [
        frozenset((e.kind, e.grasped, e.environment) for e in s.elements) for s in task.states
    ]
    want_keys = [demo.true_states[s].key for s, _, _ in demo.segments()]
    assert len(got_keys) == len(want_keys), [s.id for s in task.states]
    assert got_keys == want_keys
    # their DOF numbers as the paper's Fig. 25 prints them, derived by hand
    want_fig25 = [demo.true_states[s].fig25 for s, _, _ in demo.segments()]
    assert [s.fig25 for s in task.states] == [tuple(f) for f in want_fig25]
    # sub-skills and critical transitions, transition by transition
    got = [[(k.kind, k.space, k.type) for k in t.subskills] for t in task.transitions]
    want = [list(et.subskills) for et in demo.expected_subskills]
    assert got == want
    assert [t.critical for t in task.transitions] == [et.critical for et in demo.expected_subskills]
    assert all(t.direct for t in task.transitions)


@pytest.mark.parametrize("name", sorted(DEMOS))
def test_exact_without_noise(name: str) -> None:
    demo = DEMOS[name]
    _check(demo, _recognise(demo, 0.0, 0))


@pytest.mark.parametrize("name", sorted(DEMOS))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_exact_with_1mm_1deg_noise(name: str, seed: int) -> None:
    demo = DEMOS[name]
    _check(demo, _recognise(demo, 1.0, seed))


@pytest.mark.parametrize("name", sorted(DEMOS))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_subskills_exact_with_1mm_1deg_noise(name: str, seed: int) -> None:
    demo = DEMOS[name]
    rec = _recognise(demo, 1.0, seed)
    want = [k for et in demo.expected_subskills for k in et.subskills]
    assert rec.task.subskill_sequence() == want
    assert sum(t.critical for t in rec.task.transitions) == sum(
        et.critical for et in demo.expected_subskills
    )


def _true_motion(demo, i: int, space: str, direction) -> float:
    """True motion along ``direction`` between the middle frames of segments i and i + 1."""
    import numpy as np

    from apo.transitions import _relative_twist

    segs = demo.segments()
    (_s, a0, b0), (_t, a1, b1) = segs[i], segs[i + 1]
    xa, xb = demo.X_EG_true[(a0 + b0 - 1) // 2], demo.X_EG_true[(a1 + b1 - 1) // 2]
    xi = _relative_twist(xa, xb)
    d = np.asarray(direction, dtype=float)
    if space == "rotation":
        return float(xi[:3] @ d)
    return float(xi[3:] @ d)


@pytest.mark.parametrize("seed", range(8))
def test_slide_directions_have_the_sign_of_the_demonstrated_motion(seed: int) -> None:
    # Issue 9 / sim's finding: the E->F rotational slide of the T-peg turned +z on one noise
    # seed and -z on another while the peg turns -z. A slide's direction follows the motion.
    demo = (
        synthetic.random_variant(seed, name="peg_in_hole_2d")
        if seed % 2
        else DEMOS["peg_in_hole_2d"]
    )
    noisy = synthetic.add_noise(demo, sigma_mm=0.5 + seed % 3 * 0.5, sigma_deg=1.0, seed=seed)
    task = recognize_frames(noisy.grasped, noisy.environment, noisy.times, noisy.X_EG).task
    assert len(task.transitions) == len(demo.expected_subskills)
    checked = 0
    for i, tr in enumerate(task.transitions):
        for sub in tr.subskills:
            if sub.kind != "slide" or sub.direction is None:
                continue
            moved = _true_motion(noisy, i, sub.space, sub.direction)
            least = 0.09 if sub.space == "rotation" else 0.005  # 5 deg, 5 mm
            if abs(moved) >= least:
                assert moved > 0, (i, sub.space, sub.direction, moved)
                checked += 1
    assert checked >= 1  # the E->F turn (30 degrees and more) is always checked
