"""Tests of apo.transitions: DOF transitions, sub-skills, critical and direct transitions."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from apo.contact import ContactElement, ContactKind, ContactState
from apo.dof import (
    ContactPoint,
    DofGeometry,
    DofResult,
    Restraining,
    RotationDof,
    SpaceDof,
    analyze,
)
from apo.errors import InputFormatError
from apo.transitions import (
    CRITICAL,
    IMPRACTICAL,
    PRACTICAL,
    DirectCheck,
    DofKind,
    SubskillKind,
    analyze_transition,
    check_six,
    decompose,
    direct_transition_possible,
    is_practical,
    kind_subspaces,
    transition_pairs,
)

K = DofKind

# ---------------------------------------------------------------------------------------------
# Helpers: DOF results from numbers (empty geometry) and from hand-made bases
# ---------------------------------------------------------------------------------------------


def empty_geometry() -> DofGeometry:
    z = np.zeros((0, 3))
    return DofGeometry(z, z, z, z, z, z, z, np.zeros((0, 6)))


def make_dof(
    fig25: tuple[int, ...],
    *,
    singular: bool = False,
    d_r1: int | None = None,
    geometry: DofGeometry | None = None,
) -> DofResult:
    """A DofResult from the paper's eight numbers (singular variants when ``singular``)."""
    tm, td, tc, rm, rd, rc, rt, rr = fig25
    d1 = rd if d_r1 is None else d_r1
    t = SpaceDof(tm, td, tc)
    r = RotationDof(rm, rd, rc, d1, rd - d1)
    zero, zero_r = SpaceDof(0, 0, 0), RotationDof(0, 0, 0, 0, 0)
    a = SpaceDof(tm + rm, 0, 0)  # not used by apo.transitions
    return DofResult(
        singular=singular,
        translation=zero if singular else t,
        rotation=zero_r if singular else r,
        all=zero if singular else a,
        singular_dof_translation=t if singular else zero,
        singular_dof_rotation=r if singular else zero_r,
        singular_dof_all=a if singular else zero,
        restraining=Restraining(rt, rr, rt + rr),
        geometry=geometry if geometry is not None else empty_geometry(),
    )


def element(i: int, point, normals, kind=ContactKind.VF, env=("f", 0)) -> ContactElement:
    return ContactElement(
        kind, ("v", i), env, np.asarray(point, float), np.atleast_2d(np.asarray(normals, float))
    )


def state(*elements: ContactElement, extra=()) -> ContactState:
    touching = frozenset((e.grasped, e.environment) for e in elements) | frozenset(extra)
    return ContactState(tuple(sorted(elements, key=lambda e: e.key)), touching)


def dof_of(st: ContactState) -> DofResult:
    return analyze([ContactPoint(e.point, e.normals) for e in st.elements])


# The states of the paper's worked example (section 5.1.1, Fig. 25), as in apo.synthetic's
# T-peg demonstration: A free, B edge on the top face, C (singular) edge on the rim edge,
# D rim edge on the peg's face, E wedged, F (singular) both edges on both rims, G upright in
# the slot, H seated.
PAPER = {
    "A": make_dof((3, 0, 0, 3, 0, 0, 0, 0)),
    "B": make_dof((2, 1, 0, 2, 1, 0, 1, 1), d_r1=1),
    "C": make_dof((3, 0, 0, 3, 0, 0, 2, 2), singular=True),
    "D": make_dof((2, 1, 0, 2, 1, 0, 1, 1), d_r1=1),
    "E": make_dof((1, 2, 0, 1, 2, 0, 2, 2), d_r1=2),
    "F": make_dof((3, 0, 0, 3, 0, 0, 2, 3), singular=True),
    "G": make_dof((2, 0, 1, 1, 0, 2, 1, 2)),
    "H": make_dof((1, 1, 1, 0, 1, 2, 2, 3), d_r1=1),
}


def kinds(tr, space=None):
    return [(str(s.kind), s.space, s.type) for s in tr.subskills if space in (None, s.space)]


# ---------------------------------------------------------------------------------------------
# The practical table
# ---------------------------------------------------------------------------------------------


def test_practical_table_has_the_papers_20_pairs():
    listed = {
        ("M", "D"), ("M", "SM"), ("M", "SD"), ("D", "C"), ("D", "SM"), ("D", "SD"),
        ("D", "SC"), ("C", "SM"), ("C", "SD"), ("C", "SC"),
    }  # fmt: skip
    expected = listed | {(y, x) for x, y in listed}
    assert {(str(x), str(y)) for x, y in PRACTICAL} == expected
    assert len(PRACTICAL) == 20 and len(IMPRACTICAL) == 10
    assert PRACTICAL.isdisjoint(IMPRACTICAL) and len(PRACTICAL | IMPRACTICAL) == 30
    assert CRITICAL <= PRACTICAL


@pytest.mark.parametrize(
    ("pair", "ok"),
    [(("M", "D"), True), (("SM", "C"), True), (("M", "C"), False), (("SC", "M"), False),
     (("SM", "SD"), False), (("SD", "SC"), False), (("D", "M"), True)],
)  # fmt: skip
def test_is_practical(pair, ok):
    assert is_practical(*pair) is ok


def test_dof_kind_is_a_string_enum():
    assert (K.M, K.D) == ("M", "D") and str(SubskillKind.PUSH_TO) == "push_to"


# ---------------------------------------------------------------------------------------------
# decompose
# ---------------------------------------------------------------------------------------------


def test_decompose_unique_push():
    decs = decompose((3, 0, 0, 0, 0, 0), (2, 1, 0, 0, 0, 0), space="translation")
    assert [d.pairs for d in decs] == [((K.M, K.D),)]


def test_decompose_no_change_is_one_empty_decomposition():
    decs = decompose((2, 1, 0, 0, 0, 0), (2, 1, 0, 0, 0, 0), space="rotation")
    assert len(decs) == 1 and decs[0].pairs == ()


@pytest.mark.parametrize(
    ("before", "after"),
    [
        ((3, 0, 0, 0, 0, 0), (2, 0, 1, 0, 0, 0)),  # M -> C only
        ((3, 0, 0, 0, 0, 0), (0, 0, 0, 2, 0, 1)),  # one M must go to SC
        ((0, 0, 0, 3, 0, 0), (0, 0, 0, 2, 1, 0)),  # SM -> SD (singular to singular)
    ],
)
def test_decompose_impractical_change_is_empty(before, after):
    assert decompose(before, after, space="translation") == []


def test_decompose_matches_units_only_through_practical_pairs():
    # M must not go to SC: the only plans give SC to D
    decs = decompose((1, 2, 0, 0, 0, 0), (0, 0, 0, 0, 2, 1), space="translation")
    assert [d.pairs for d in decs] == [((K.M, K.SD), (K.D, K.SD), (K.D, K.SC))]


def test_decompose_enumerates_every_plan():
    # (1, 1, 1) regular -> (1, 1, 1) singular: 3! = 6 bijections minus those with M -> SC
    # (2 of them): 4 plans
    decs = decompose((1, 1, 1, 0, 0, 0), (0, 0, 0, 1, 1, 1), space="translation")
    plans = {d.pairs for d in decs}
    assert len(plans) == 4 and len(decs) == 4
    assert all((K.M, K.SC) not in p for p in plans)
    assert all(len(p) == 3 for p in plans)


def test_decompose_without_geometry_ties_in_north_west_order():
    decs = decompose((1, 1, 1, 0, 0, 0), (0, 0, 0, 1, 1, 1), space="translation")
    assert decs[0].pairs == ((K.M, K.SM), (K.D, K.SD), (K.C, K.SC))
    assert all(d.score == 0.0 for d in decs)


def geometry_t(m, d, c) -> DofGeometry:
    """Translation-only geometry from three lists of basis rows (rotation empty)."""
    arr = [np.asarray(x, float).reshape(-1, 3) for x in (m, d, c)]
    z = np.zeros((0, 3))
    return DofGeometry(arr[0], arr[1], arr[2], z, z, z, z, np.zeros((0, 6)))


X, Y, Z = [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]


def test_decompose_geometry_prefers_overlapping_subspaces():
    # before: M along x, D along y, C along z; after (singular): SM along y, SD along x,
    # SC along z. The x direction went M -> SD, y went D -> SM.
    gb = geometry_t([X], [Y], [Z])
    ga = geometry_t([Y], [X], [Z])
    decs = decompose(
        (1, 1, 1, 0, 0, 0), (0, 0, 0, 1, 1, 1), before_geom=gb, after_geom=ga,
        space="translation",
    )  # fmt: skip
    assert decs[0].pairs == ((K.M, K.SD), (K.D, K.SM), (K.C, K.SC))
    assert decs[0].score == pytest.approx(3.0)
    assert all(d.score < decs[0].score for d in decs[1:])


def test_decompose_mismatched_geometry_is_ignored():
    # geometry whose dimensions disagree with the numbers counts as absent
    gb = geometry_t([X, Y], [Z], [])
    assert kind_subspaces((1, 1, 1, 0, 0, 0), gb, "translation") == {}
    subs = kind_subspaces((2, 1, 0, 0, 0, 0), gb, "translation")
    assert subs[K.M].shape == (2, 3) and subs[K.SM].shape == (0, 3)


def test_kind_subspaces_singular_state_maps_geometry_to_singular_kinds():
    g = geometry_t([X, Y], [Z], [])
    subs = kind_subspaces((0, 0, 0, 2, 1, 0), g, "translation")
    assert subs[K.SM].shape == (2, 3) and subs[K.SD].shape == (1, 3)
    assert subs[K.M].shape == (0, 3) and subs[K.D].shape == (0, 3)


@pytest.mark.parametrize(
    ("six", "match"),
    [
        ((3, 0, 0, 0, 0), "6 numbers"),
        ((2, 0, 0, 0, 0, 0), "sum to 3"),
        ((4, -1, 0, 0, 0, 0), "non-negative"),
        ((1, 0, 0, 2, 0, 0), "mixed"),
        ((1.5, 1.5, 0, 0, 0, 0), "integers"),
    ],
)
def test_check_six_rejects(six, match):
    with pytest.raises(InputFormatError, match=match):
        check_six(six)


def test_decompose_rejects_bad_space():
    with pytest.raises(InputFormatError, match="space"):
        decompose((3, 0, 0, 0, 0, 0), (3, 0, 0, 0, 0, 0), space="both")


# ---------------------------------------------------------------------------------------------
# The paper's worked example (section 5.1.1)
# ---------------------------------------------------------------------------------------------


def test_paper_transition_1_push_to_translation_and_type_I_rotation():
    # t, r: M -1, D +1; the new rotation detaching DOF is type I
    tr = analyze_transition(PAPER["A"], PAPER["B"])
    assert transition_pairs(tr) == {"translation": [("M", "D")], "rotation": [("M", "D")]}
    assert kinds(tr) == [("push_to", "translation", None), ("push_to", "rotation", "I")]
    assert not tr.critical and tr.feasible and tr.dof_changed


def test_paper_transition_2_slide_in_both_spaces():
    # M -2, D -1, SM +3 in both; restraining +1 in both: slide in both (D -> SM comes with it)
    tr = analyze_transition(PAPER["B"], PAPER["C"])
    for sp in ("translation", "rotation"):
        assert tr.dof_transitions[sp] == ((K.M, K.SM), (K.M, K.SM), (K.D, K.SM))
    assert kinds(tr) == [("slide", "translation", None), ("slide", "rotation", None)]
    assert not tr.critical


def test_paper_transition_3_no_subskill_not_critical():
    # SM -> M twice and SM -> D: no sub-skill of its own; no SM -> C
    tr = analyze_transition(PAPER["C"], PAPER["D"])
    for sp in ("translation", "rotation"):
        assert tr.dof_transitions[sp] == ((K.SM, K.M), (K.SM, K.M), (K.SM, K.D))
    assert tr.subskills == () and not tr.critical and tr.feasible


def test_paper_transition_4_push_to_again():
    tr = analyze_transition(PAPER["D"], PAPER["E"])
    assert kinds(tr) == [("push_to", "translation", None), ("push_to", "rotation", "I")]


def test_paper_transition_5_rotation_slide_only():
    # M -> SM in both spaces, but only the rotation restraining DOF grows (2 -> 3)
    tr = analyze_transition(PAPER["E"], PAPER["F"])
    assert (K.M, K.SM) in tr.dof_transitions["translation"]
    assert (K.M, K.SM) in tr.dof_transitions["rotation"]
    assert kinds(tr) == [("slide", "rotation", None)]


def test_paper_transition_6_is_critical():
    # t: SM -> C once; r: SM -> C twice
    tr = analyze_transition(PAPER["F"], PAPER["G"])
    assert tr.dof_transitions["translation"].count((K.SM, K.C)) == 1
    assert tr.dof_transitions["rotation"].count((K.SM, K.C)) == 2
    assert tr.critical and tr.subskills == () and tr.feasible


def test_paper_transition_7_push_to():
    tr = analyze_transition(PAPER["G"], PAPER["H"])
    assert kinds(tr) == [("push_to", "translation", None), ("push_to", "rotation", "I")]


def test_paper_sequence_every_transition_is_direct_by_the_numbers():
    ids = "ABCDEFGH"
    for a, b in itertools.pairwise(ids):
        ok, why = direct_transition_possible(set(), set(), PAPER[a], PAPER[b])
        assert ok, (a, b, why)


# ---------------------------------------------------------------------------------------------
# Other sub-skill rules
# ---------------------------------------------------------------------------------------------


def test_release_is_the_reverse_of_push_to():
    tr = analyze_transition(PAPER["B"], PAPER["A"])
    assert kinds(tr) == [("release", "translation", None), ("release", "rotation", None)]


def test_sd_to_m_is_a_release_and_m_to_sd_a_push_to():
    free = make_dof((3, 0, 0, 3, 0, 0, 0, 0))
    sing = make_dof((2, 1, 0, 3, 0, 0, 2, 2), singular=True)
    push = analyze_transition(free, sing)
    assert push.dof_transitions["translation"] == ((K.M, K.SM), (K.M, K.SM), (K.M, K.SD))
    assert ("push_to", "translation", None) in kinds(push)
    assert ("slide", "translation", None) in kinds(push)  # r_t grew 0 -> 2
    rel = analyze_transition(sing, free)
    assert ("release", "translation", None) in kinds(rel)


def test_slide_needs_the_restraining_dof_to_grow():
    b = make_dof((2, 1, 0, 2, 1, 0, 1, 1))
    a = make_dof((3, 0, 0, 3, 0, 0, 1, 1), singular=True)  # restraining unchanged
    tr = analyze_transition(b, a)
    assert (K.M, K.SM) in tr.dof_transitions["translation"]
    assert tr.subskills == ()


def test_rotation_push_to_type_II_when_d_r2_grows():
    b = make_dof((1, 1, 1, 1, 1, 1, 2, 2), d_r1=1)
    a = make_dof((1, 1, 1, 0, 2, 1, 2, 3), d_r1=1)  # d_r1 stays 1, d_r2 0 -> 1
    tr = analyze_transition(b, a)
    assert kinds(tr) == [("push_to", "rotation", "II")]


def test_sm_to_m_alone_has_no_subskill():
    b = make_dof((3, 0, 0, 3, 0, 0, 2, 2), singular=True)
    a = make_dof((3, 0, 0, 3, 0, 0, 0, 0))
    tr = analyze_transition(b, a)
    assert tr.dof_transitions["translation"] == ((K.SM, K.M),) * 3
    assert tr.subskills == () and not tr.critical


def test_sd_to_c_is_critical_and_sm_to_d_is_not():
    b = make_dof((1, 1, 1, 3, 0, 0, 2, 2), singular=True)
    a = make_dof((1, 1, 1, 3, 0, 0, 2, 2))
    tr = analyze_transition(b, a)
    assert tr.dof_transitions["translation"] == ((K.SM, K.M), (K.SD, K.D), (K.SC, K.C))
    assert not tr.critical  # the north-west plan pairs SD with D
    assert any(d.critical for d in tr.alternatives["translation"])  # SD -> C was considered
    assert tr.choice["translation"] == "tie"


def test_impractical_change_is_not_feasible():
    b = make_dof((3, 0, 0, 3, 0, 0, 0, 0))
    a = make_dof((2, 0, 1, 3, 0, 0, 1, 0))  # M -> C
    tr = analyze_transition(b, a)
    assert not tr.feasible and "translation" in tr.reason
    assert tr.dof_transitions["translation"] == () and tr.choice["translation"] == "none"
    ok, why = direct_transition_possible(set(), set(), b, a)
    assert not ok and "practical" in why


# ---------------------------------------------------------------------------------------------
# Direct-transition test
# ---------------------------------------------------------------------------------------------

FA, FB, FC = (("v", 0), ("f", 1)), (("v", 1), ("f", 1)), (("e", 2), ("e", 5))


def test_direct_transition_needs_nested_touching_sets():
    d = PAPER["B"]
    check = direct_transition_possible({FA, FB}, {FA}, d, d)
    assert isinstance(check, DirectCheck) and check and check.reason == ""
    ok, why = direct_transition_possible({FA, FB}, {FA, FC}, d, d)
    assert not ok and "nested" in why and not direct_transition_possible({FA}, {FC}, d, d)


def test_direct_transition_accepts_contact_states_and_is_symmetric():
    sa = state(element(0, (0, 0, 0), Z), element(1, (1, 0, 0), Z))
    sb = state(element(0, (0, 0, 0), Z))
    da, db = dof_of(sa), dof_of(sb)
    assert bool(direct_transition_possible(sa, sb, da, db))
    assert bool(direct_transition_possible(sb, sa, db, da))


def test_direct_transition_uses_the_full_touching_sets():
    # same elements, but a touching pair (not an element) differs on both sides
    sa = state(element(0, (0, 0, 0), Z), extra=[FB])
    sb = state(element(0, (0, 0, 0), Z), extra=[FC])
    d = dof_of(sa)
    assert not direct_transition_possible(sa, sb, d, d)


def test_direct_transition_rejects_bad_state_type():
    with pytest.raises(InputFormatError, match="touching"):
        direct_transition_possible([FA], {FA}, PAPER["A"], PAPER["A"])


def test_element_change_without_dof_change():
    # one vertex-face contact replaced by another at a different point with the same normal:
    # a state change with no DOF change, no sub-skill, not critical
    sa = state(element(0, (0, 0, 0), Z))
    sb = state(element(0, (0, 0, 0), Z), element(1, (0, 0, 0), Z, env=("f", 2)))
    tr = analyze_transition(dof_of(sa), dof_of(sb), before_state=sa, after_state=sb)
    assert not tr.dof_changed and tr.subskills == () and not tr.critical and tr.feasible
    assert all(c == "no change" for c in tr.choice.values())


def test_analyze_transition_reports_donald_failure():
    sa = state(element(0, (0, 0, 0), Z), extra=[FB])
    sb = state(element(0, (0, 0, 0), Z), extra=[FC])
    d = dof_of(sa)
    tr = analyze_transition(d, d, before_state=sa, after_state=sb)
    assert not tr.feasible and "Donald" in tr.reason


# ---------------------------------------------------------------------------------------------
# Directions, from real DOF analyses
# ---------------------------------------------------------------------------------------------

# A unit block standing on a table (z up): bottom corners at z = 0.
BOTTOM = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]


def on_table() -> ContactState:
    return state(*(element(i, p, Z) for i, p in enumerate(BOTTOM)))


def against_wall(points) -> ContactState:
    """On the table and touching a wall at x = 1 (wall normal -x towards the block)."""
    wall = [element(10 + i, p, [-1, 0, 0], env=("f", 3)) for i, p in enumerate(points)]
    return state(*(element(i, p, Z) for i, p in enumerate(BOTTOM)), *wall)


def test_translation_push_to_points_into_the_new_contact():
    before, after = on_table(), against_wall([(1, 0, 0.5)])
    db, da = dof_of(before), dof_of(after)
    tr = analyze_transition(db, da, before_state=before, after_state=after)
    (push,) = [s for s in tr.subskills if s.space == "translation"]
    assert push.kind is SubskillKind.PUSH_TO and push.source == "contacts"
    np.testing.assert_allclose(push.direction, X, atol=1e-9)  # moved +x into the wall
    assert push.subspace.shape == (1, 3) and abs(push.subspace[0] @ X) == pytest.approx(1)
    # without the contacts the after-state's detaching direction (-x) gives the same
    tr2 = analyze_transition(db, da)
    (push2,) = [s for s in tr2.subskills if s.space == "translation"]
    assert push2.source == "detaching_direction"
    np.testing.assert_allclose(push2.direction, X, atol=1e-9)


def test_translation_release_points_away_from_the_lost_contact():
    before, after = against_wall([(1, 0, 0.5)]), on_table()
    tr = analyze_transition(dof_of(before), dof_of(after), before_state=before, after_state=after)
    (rel,) = [s for s in tr.subskills if s.space == "translation"]
    assert rel.kind is SubskillKind.RELEASE
    np.testing.assert_allclose(rel.direction, [-1, 0, 0], atol=1e-9)


def test_rotation_push_to_axis_turns_into_the_wall():
    # face flush with the wall at x = 1: rotation about z is lost (M -> D)
    before, after = on_table(), against_wall([(1, 0, 0.5), (1, 1, 0.5)])
    db, da = dof_of(before), dof_of(after)
    tr = analyze_transition(db, da, before_state=before, after_state=after)
    assert (K.M, K.D) in tr.dof_transitions["rotation"]
    (rot,) = [s for s in tr.subskills if s.space == "rotation"]
    assert rot.kind is SubskillKind.PUSH_TO and rot.source == "contacts"
    assert abs(rot.direction @ Z) == pytest.approx(1.0)
    # the twist about the axis through the point drives the wall contacts in (net)
    s0 = rot.direction
    s1 = np.cross(rot.point, s0)
    pairing = sum(
        np.cross(p, n) @ s0 + n @ s1
        for p, n in [((1, 0, 0.5), -np.array(X)), ((1, 1, 0.5), -np.array(X))]
    )
    assert pairing < 0
    # it keeps the table contacts: the axis is vertical, so every bottom point moves in-plane
    assert rot.point[2] == pytest.approx(0.0, abs=1e-9)


def test_translation_slide_points_to_where_the_support_ends():
    # the block slid +x until its back bottom edge sits on the table's edge at x = 1
    # (table top +z, table side +x): singular vertex-edge contacts with normals {+z, +x}
    before = on_table()
    edge = [
        element(i, p, [Z, X], kind=ContactKind.VE, env=("e", 7))
        for i, p in enumerate([(1, 0, 0), (1, 1, 0)])
    ]
    after = state(*edge)
    db, da = dof_of(before), dof_of(after)
    assert da.singular and da.restraining.translation > db.restraining.translation
    tr = analyze_transition(db, da, before_state=before, after_state=after)
    (slide,) = [s for s in tr.subskills if s.space == "translation"]
    assert slide.kind is SubskillKind.SLIDE
    np.testing.assert_allclose(slide.direction, X, atol=1e-9)


def test_direction_from_poses_when_nothing_else_tells():
    # slide between hand-made geometries with no contacts: the displacement decides the sign
    gb = geometry_t([X, Y], [Z], [])
    ga = geometry_t([X, Y, Z], [], [])
    b = make_dof((2, 1, 0, 3, 0, 0, 1, 0), geometry=None)
    b = DofResult(**{**b.__dict__, "geometry": gb})
    a = make_dof((3, 0, 0, 3, 0, 0, 2, 0), singular=True)
    a = DofResult(**{**a.__dict__, "geometry": ga})
    x_b, x_a = np.eye(4), np.eye(4)
    x_a[:3, 3] = [-0.01, 0.0, 0.0]
    tr = analyze_transition(b, a, X_EG_before=x_b, X_EG_after=x_a)
    (slide,) = tr.subskills
    assert slide.source == "poses"
    np.testing.assert_allclose(slide.direction, [-1, 0, 0], atol=1e-9)
    tr0 = analyze_transition(b, a)
    assert tr0.subskills[0].direction is None and tr0.subskills[0].source == "none"


def test_bad_pose_is_rejected():
    with pytest.raises(InputFormatError, match=r"X_EG_before must have shape \(4, 4\)"):
        analyze_transition(PAPER["A"], PAPER["B"], X_EG_before=np.eye(3))
    with pytest.raises(InputFormatError, match="X_EG_after rotation part is not a rotation"):
        analyze_transition(PAPER["A"], PAPER["B"], X_EG_after=np.diag([1.0, 1.0, 2.0, 1.0]))


def _moved(st: ContactState, R: np.ndarray, t: np.ndarray) -> ContactState:
    """The same state after a rigid motion (R, t) of the whole scene."""
    return state(
        *(
            ContactElement(e.kind, e.grasped, e.environment, R @ e.point + t, e.normals @ R.T)
            for e in st.elements
        )
    )


def _pose(R: np.ndarray, t) -> np.ndarray:
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R, t
    return X


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_rotation_push_to_axis_passes_through_the_pivot_seen_in_the_poses():
    # The block turned about the vertical line through its corner (1, 1) until its face
    # landed flush on the wall x = 1: that corner moved least, so the axis passes through it.
    before, after = on_table(), against_wall([(1, 0, 0.5), (1, 1, 0.5)])
    X_after = np.eye(4)
    c = np.array([1.0, 1.0, 0.0])
    X_before = _pose(_rz(0.1), c - _rz(0.1) @ c)  # turned by 0.1 rad about the corner
    tr = analyze_transition(
        dof_of(before),
        dof_of(after),
        before_state=before,
        after_state=after,
        X_EG_before=X_before,
        X_EG_after=X_after,
    )
    (rot,) = [s for s in tr.subskills if s.space == "rotation"]
    # the axis is the vertical through (1, 1): its point closest to the origin is (1, 1, 0)
    assert abs(rot.direction @ Z) == pytest.approx(1.0)
    np.testing.assert_allclose(rot.point, [1.0, 1.0, 0.0], atol=1e-9)
    # and it turns the block into the wall: the other end of the face moves in +x
    v = np.cross(rot.direction, np.array([1.0, 0.0, 0.5]) - rot.point)
    assert v[0] > 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rotation_sub_skill_axis_moves_with_the_scene(seed: int):
    # The reported axis is a property of the contacts, not of where the origin of E is.
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=rng).as_matrix()
    t = rng.normal(size=3) * 5
    before, after = on_table(), against_wall([(1, 0, 0.5), (1, 1, 0.5)])
    tr0 = analyze_transition(dof_of(before), dof_of(after), before_state=before, after_state=after)
    b1, a1 = _moved(before, R, t), _moved(after, R, t)
    tr1 = analyze_transition(dof_of(b1), dof_of(a1), before_state=b1, after_state=a1)
    (r0,) = [s for s in tr0.subskills if s.space == "rotation"]
    (r1,) = [s for s in tr1.subskills if s.space == "rotation"]
    np.testing.assert_allclose(r1.direction, R @ r0.direction, atol=1e-7)
    # the moved point of axis 0 lies on axis 1
    q = R @ r0.point + t - r1.point
    np.testing.assert_allclose(np.cross(q, r1.direction), 0.0, atol=1e-7)
