"""DOF analysis: hand-derived canonical states and property tests (docs/theory.md, paper 2.2/3.5).

Conventions: contact constraint ``(P x F) . S0 + F . S1 >= 0``; F points from the environment
to the grasped object. Unit block [0,1]^3 unless said otherwise.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog

from apo.constants import Tolerances
from apo.dof import (
    ContactPoint,
    DofResult,
    Restraining,
    RotationDof,
    SpaceDof,
    analyze,
    analyze_arrays,
    check_contacts,
    dof_result_to_dict,
    maximal_support,
    numerical_rank,
)
from apo.errors import InputFormatError

S2 = 1 / math.sqrt(2)
X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)
MX, MY = (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0)


def cp(point: tuple[float, ...], *normals: tuple[float, ...]) -> ContactPoint:
    return ContactPoint(np.array(point, dtype=float), np.array(normals, dtype=float))


def bottom(z: float = 0.0) -> list[ContactPoint]:
    return [cp((x, y, z), Z) for x in (0, 1) for y in (0, 1)]


def wall_x0() -> list[ContactPoint]:
    return [cp((0, y, z), X) for y in (0, 1) for z in (0, 1)]


def hole_walls() -> list[ContactPoint]:
    return (
        wall_x0()
        + [cp((1, y, z), MX) for y in (0, 1) for z in (0, 1)]
        + [cp((x, 0, z), Y) for x in (0, 1) for z in (0, 1)]
        + [cp((x, 1, z), MY) for x in (0, 1) for z in (0, 1)]
    )


# --- hand-derived canonical states ----------------------------------------------------------
# fig25 = (tM, tD, tC, rM, rD, rC, r_t, r_r); all = (m_a, d_a, c_a); rot12 = (d_r1, d_r2).
CASES = {
    # nothing touches: every motion maintains; nothing restrains.
    "no contact": ([], (3, 0, 0, 3, 0, 0, 0, 0), (6, 0, 0), (0, 0)),
    # one VF point: slide in the plane (2), lift (1); any rotation about an axis through the
    # point keeps it (m_a = 6 - 1 = 5, m_r = 5 - 2 = 3).
    "point on plane": ([cp((0, 0, 0), Z)], (2, 1, 0, 3, 0, 0, 1, 0), (5, 1, 0), (0, 0)),
    # EE crossing edges: one point, normal e_A x e_B: same numbers as a point on a plane.
    "crossing edges": (
        [cp((0.3, -0.2, 0.5), (0, 0, -1))],
        (2, 1, 0, 3, 0, 0, 1, 0),
        (5, 1, 0),
        (0, 0),
    ),
    # block face on table: slide x, y and spin about z maintain (m_a = 6 - rank 3 = 3,
    # m_r = 1); no opposing normals so V_r* = {0}, V_r = R^3: tipping about x or y is
    # possible both ways (about opposite bottom edges, with a lift): type I, d_r1 = 3 - 0 - 1.
    "block on table": (bottom(), (2, 1, 0, 1, 2, 0, 1, 2), (3, 3, 0), (2, 0)),
    # + wall x = 0: only sliding along y maintains (m_a = 1, m_r = 0); normals +x, +z never
    # cancel, so V_r = R^3 and all three rotation DOF are type I detaching.
    "block on table against wall": (
        bottom() + wall_x0(),
        (1, 2, 0, 0, 3, 0, 2, 3),
        (1, 5, 0),
        (3, 0),
    ),
    # corner of three walls: nothing maintains, nothing cancels: everything detaches.
    "block in corner": (
        bottom() + wall_x0() + [cp((x, 0, z), Y) for x in (0, 1) for z in (0, 1)],
        (0, 3, 0, 0, 3, 0, 3, 3),
        (0, 6, 0),
        (3, 0),
    ),
    # square peg in square hole on the bottom: lift only (d_t = 1), x, y blocked by opposite
    # walls (c_t = 2); wall pairs force v_y = x w_z - z w_x and v_x = y w_z - z w_y at the
    # corners, so w = 0: c_r = 3. V_a = {w = 0, v_x = v_y = 0, v_z >= 0}: d_a = 1, c_a = 5.
    "peg in hole, bottom": (bottom() + hole_walls(), (0, 1, 2, 0, 0, 3, 3, 3), (0, 1, 5), (0, 0)),
    # without the bottom: z slides (m_t = 1), everything else constrained; m_a = 1, m_r = 0.
    "peg in hole, no bottom": (hole_walls(), (1, 0, 2, 0, 0, 3, 2, 3), (1, 0, 5), (0, 0)),
    # box standing on one edge (along x): rotation about the edge and about z maintain
    # (m_a = 6 - 2 = 4, m_r = 2); tipping about y either way with a lift: type I.
    "box on an edge": (
        [cp((0, 0, 0), Z), cp((1, 0, 0), Z)],
        (2, 1, 0, 2, 1, 0, 1, 1),
        (4, 2, 0),
        (1, 0),
    ),
    # tilted peg jammed between walls x = 0 (touching at the top, z = 1) and x = 1 (at the
    # bottom): +-x cancel (c_t = 1); V_r* = cone{Mo_1 + Mo_2} = cone{(0, 1, 0)}, so
    # V_r = {w_y >= 0}: c_r = 0, d_r = 3 - 2 - 0 = 1, lin(V_r) = {w_y = 0} has dim 2 = m_r:
    # d_r1 = 0, d_r2 = 1 (the peg can only un-jam). V_a is full (S_a empty): c_a = 0.
    "jammed peg": (
        [cp((0, 0, 1), X), cp((1, 0, 0), MX)],
        (2, 0, 1, 2, 1, 0, 1, 1),
        (4, 2, 0),
        (0, 1),
    ),
    # mixed types: +-x at (0,0,0), (0,0,1) cancel (c_t = 1), V_r* = cone{Mo_1 + Mo_2} =
    # cone{(0, -1, 0)}: lin(V_r) = {w_y = 0}; the floor z at the origin and the slanted face
    # at (0,1,0) leave m_a = 2 (slide y; turn about (1,0,1) through the origin), m_r = 1; S_a is
    # empty so V_r spans R^3: d_r = 2, d_r1 = 2 - 1 = 1 (the axis in w_y = 0), d_r2 = 1 (w_y).
    "mixed type I and II": (
        [cp((0, 0, 0), X), cp((0, 0, 1), MX), cp((0, 1, 0), (S2, 0, S2)), cp((0, 0, 0), Z)],
        (1, 1, 1, 1, 2, 0, 2, 2),
        (2, 4, 0),
        (1, 1),
    ),
}


@pytest.mark.parametrize("name", list(CASES))
def test_canonical_states(name: str) -> None:
    contacts, fig25, all_, rot12 = CASES[name]
    r = analyze(contacts)
    assert not r.singular
    assert r.fig25 == fig25
    a = r.all
    assert (a.maintaining, a.detaching, a.constraining) == all_
    assert (r.rotation.detaching_type1, r.rotation.detaching_type2) == rot12
    assert r.six("translation")[3:] == (0, 0, 0)
    assert r.six("rotation")[3:] == (0, 0, 0)


def test_block_on_table_geometry() -> None:
    g = analyze(bottom()).geometry
    assert g.translation_maintaining.shape == (2, 3)
    np.testing.assert_allclose(np.abs(g.translation_detaching), [[0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(g.translation_detaching_direction, [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(g.rotation_maintaining, [[0, 0, 1]], atol=1e-12)
    assert g.rotation_detaching.shape == g.rotation_detaching_type1.shape == (2, 3)
    assert g.rotation_detaching_type2.shape == (0, 3)
    # canonical maintaining twists: 2 translations, then a spin about z through the block
    assert g.maintaining_twists.shape == (3, 6)
    np.testing.assert_allclose(g.maintaining_twists[:2, :3], 0, atol=1e-12)
    spin = g.maintaining_twists[2]
    np.testing.assert_allclose(spin[:3], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(spin[3:], 0, atol=1e-12)  # S1 orthogonal to x, y; no pitch


def test_maintaining_twist_in_input_frame() -> None:
    # box on an edge along x at height 2, offset y = 5: the edge rotation is the screw with
    # S0 = x through (0, 5, 2): S1 = C x S0 = (0, 2, -5); minus its x-y parts (maintaining
    # translations are x and y): (0, 0, -5).
    r = analyze([cp((0, 5, 2), Z), cp((3, 5, 2), Z)])
    tw = r.geometry.maintaining_twists
    assert tw.shape == (4, 6)
    for row in tw:  # each is admissible with equality at both contacts
        for p in ((0, 5, 2), (3, 5, 2)):
            assert abs(np.cross(p, Z) @ row[:3] + np.array(Z) @ row[3:]) < 1e-9
    rot = tw[2:]
    assert np.linalg.matrix_rank(rot[:, :3]) == 2


def test_corner_detaching_direction() -> None:
    # three walls at the origin: min sum F.u with F.u >= 1 is u = (1, 1, 1)
    r = analyze([cp((0, 0, 0), X), cp((0, 0, 0), Y), cp((0, 0, 0), Z)])
    np.testing.assert_allclose(
        r.geometry.translation_detaching_direction, np.ones(3) / math.sqrt(3), atol=1e-9
    )


def test_jammed_peg_geometry_and_cpp_pitfall() -> None:
    r = analyze(CASES["jammed peg"][0])
    g = r.geometry
    np.testing.assert_allclose(np.abs(g.translation_constraining), [[1, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(np.abs(g.rotation_detaching_type2), [[0, 1, 0]], atol=1e-12)
    # the C++ shortcut c_r = c_a - c_t gives -1 here; the paper's definition gives 0
    assert r.all.constraining - r.translation.constraining == -1
    assert r.rotation.constraining == 0


def test_vr_is_projection_not_s1_zero() -> None:
    # Pitfall: with S1 = 0 the block on the table could only turn about axes with
    # w_x >= 0, w_y <= 0 (origin at a corner); V_r (some S1 exists) is all of R^3, and the
    # excess of lin(V_r) (dim 3) over the projection of lin(V_a) (dim 1, spin) is d_r1 = 2.
    r = analyze(bottom())
    assert r.rotation == RotationDof(1, 2, 0, 2, 0)
    assert r.geometry.rotation_maintaining.shape[0] == 1


def test_singular_ve_point_alone() -> None:
    # vertex on a convex edge along x: normals (0, +-1, 1)/sqrt2; no regular element left:
    # singular M = 3 in both spaces; r_t = 2 (y, z), r_a = 2 (moments 0), r_r = 0.
    r = analyze([cp((0, 0, 0), (0, S2, S2), (0, -S2, S2))])
    assert r.singular
    assert r.translation == SpaceDof(0, 0, 0)
    assert r.rotation == RotationDof(0, 0, 0)
    assert r.fig25 == (3, 0, 0, 3, 0, 0, 2, 0)
    assert r.six("translation") == (0, 0, 0, 3, 0, 0)


def test_singular_with_regular_rest() -> None:
    # VE point plus a VF point: the singular variant is the lone VF point's (2,1,0 / 3,0,0);
    # restraining: normals span y, z (r_t = 2); the VF moment (0, -1, 0) adds one: r_a = 3.
    r = analyze([cp((0, 0, 0), (0, S2, S2), (0, -S2, S2)), cp((1, 0, 0), Z)])
    assert r.singular
    assert r.fig25 == (2, 1, 0, 3, 0, 0, 2, 1)
    assert r.singular_dof_all == SpaceDof(5, 1, 0)
    assert r.all == SpaceDof(0, 0, 0)


def test_parallel_convex_edges_fig18() -> None:
    # Fig. 18: two VE/EV points on parallel convex edges along x; nothing regular: SM = 3.
    # Restraining: normals span y, z (r_t = 2); moments of the x = 1 point add w_y, w_z
    # (r_a = 4), so r_r = 2 (rotation about the common edge keeps contact).
    n = ((0, S2, S2), (0, -S2, S2))
    r = analyze([cp((0, 0, 0), *n), cp((1, 0, 0), *n)])
    assert r.singular
    assert r.fig25 == (3, 0, 0, 3, 0, 0, 2, 2)
    assert r.restraining.all == 4


def test_concave_corner_is_not_singular() -> None:
    # a vertex in a concave corner: two single-normal elements at the same point
    r = analyze([cp((0, 0, 0), Z), cp((0, 0, 0), X)])
    assert not r.singular
    assert r.fig25[:3] == (1, 2, 0)


def test_maximal_support_non_pair_cancellation() -> None:
    # three coplanar normals positively spanning the plane + z and a tilted one: no opposite
    # pair and no pointedness certificate: S = the three planar ones.
    g = np.array([X, Y, (-S2, -S2, 0), Z, (S2, 0, S2)]).T
    assert maximal_support(g).tolist() == [True, True, True, False, False]
    # with -z added everything cancels
    g2 = np.hstack([g, np.array([[0, 0, -1.0]]).T])
    assert maximal_support(g2).all()
    assert maximal_support(np.zeros((3, 0))).shape == (0,)
    with pytest.raises(ValueError, match="non-zero"):
        maximal_support(np.zeros((3, 2)))


def test_tiny_tilt_snaps_and_large_tilt_does_not() -> None:
    # opposite walls, one tilted by eps: below the tolerance they still cancel
    def state(eps: float) -> DofResult:
        return analyze([cp((0, 0, 0), X), cp((1, 0, 0), (-math.cos(eps), 0, math.sin(eps)))])

    for eps in (1e-10, -1e-10, 1e-6, -1e-6):  # below sqrt(2) tol.rank: merged, either sign
        assert state(eps).translation == SpaceDof(2, 0, 1)
    for eps in (3e-6, -3e-6):
        assert state(eps).translation == SpaceDof(1, 2, 0)
    assert state(1e-2).translation == SpaceDof(1, 2, 0)  # a thin wedge: both detach
    assert state(-1e-2).translation == SpaceDof(1, 2, 0)


def _slot(rng: np.random.Generator, tilt: float, offset: float) -> list[ContactPoint]:
    """A block between two parallel walls, touching each at four corners facing each other.

    The second wall's normal is turned by ``tilt`` rad about a random axis in the wall, and
    its four points are moved by about ``offset`` m along it: what a pose correction to
    1e-7 m and models rounded to float32 (an STL) leave of exact geometry.
    """
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    u = np.cross(n, rng.normal(size=3))
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    half = rng.uniform(0.005, 0.04, 2)
    corners = [a * u + b * v for a in (-half[0], half[0]) for b in (-half[1], half[1])]
    angle = rng.uniform(0.0, 2.0 * np.pi)
    axis = math.cos(angle) * u + math.sin(angle) * v
    m = -n * math.cos(tilt) + np.cross(axis, -n) * math.sin(tilt)
    origin = rng.normal(size=3) * 0.3
    width = rng.uniform(0.005, 0.05)
    moved = offset * rng.normal(size=(4, 2)) @ np.array([u, v])
    walls = [cp(origin + c, n) for c in corners]
    walls += [cp(origin + c + width * n + moved[i], m) for i, c in enumerate(corners)]
    return walls


def test_walls_opposite_within_the_rank_rule_are_opposite_for_the_cones_too() -> None:
    # A slot's walls tilted by less than tol.rank are opposite for the rank rule (one
    # constraining translation); the cone tests on the null vectors must agree (both
    # rotations across the slot constrained), not find a one-way rotation from a tilt of
    # 1e-7 rad: an STL's float32 coordinates did that to a peg in a slot (state G).
    rng = np.random.default_rng(7)
    expected = (SpaceDof(2, 0, 1), RotationDof(1, 0, 2, 0, 0))
    for _ in range(60):
        exact = analyze(_slot(rng, 0.0, 0.0))
        assert (exact.translation, exact.rotation) == expected
        near = analyze(_slot(rng, rng.uniform(0.05, 0.5) * 1e-6, 5e-8))
        assert (near.translation, near.rotation) == expected


def test_analyze_arrays_and_dict() -> None:
    r = analyze_arrays([(0, 0, 0)], [[(0, 0, 2.0)]])
    assert r.fig25 == (2, 1, 0, 3, 0, 0, 1, 0)
    d = dof_result_to_dict(analyze(CASES["jammed peg"][0]))
    assert d["fig25"] == [2, 0, 1, 2, 1, 0, 1, 1]
    assert d["rotation"]["detaching_type2"] == 1
    assert set(d["singular_dof"]) == {"translation", "rotation", "all"}
    assert d["restraining"] == {"translation": 1, "rotation": 1, "all": 2}


def test_numerical_rank_rule() -> None:
    a = np.array([[1.0, 0.0], [0.0, 1e-8]])
    assert numerical_rank(a) == 1
    assert numerical_rank(a, tolerances=Tolerances(rank=1e-9)) == 2
    assert numerical_rank(np.zeros((3, 0))) == 0


@pytest.mark.parametrize(
    ("point", "normals", "match"),
    [
        ((0, 0), [Z], r"contact 1: point must have shape \(3,\), got \(2,\)"),
        ((0, 0, math.nan), [Z], "contact 1: point is not finite"),
        ((0, 0, 0), [(0, 0, 0)], "contact 1: normal 0 is zero"),
        ((0, 0, 0), [(0, math.nan, 1)], "contact 1: normals are not finite"),
        ((0, 0, 0), [(0, 1)], r"contact 1: normals must have shape \(M, 3\)"),
        ((0, 0, 0), np.zeros((0, 3)), r"M >= 1, got \(0, 3\)"),
    ],
)
def test_check_contacts_errors(point: object, normals: object, match: str) -> None:
    good = ContactPoint(np.zeros(3), np.array([Z]))
    bad = ContactPoint(np.asarray(point, dtype=float), np.asarray(normals, dtype=float))
    with pytest.raises(InputFormatError, match=match):
        check_contacts([good, bad])
    with pytest.raises(ValueError, match=match):
        analyze([good, bad])


def test_check_contacts_normalises() -> None:
    _, ns = check_contacts([cp((1, 2, 3), (0, 0, 5), (3, 4, 0))])
    np.testing.assert_allclose(ns[0], [[0, 0, 1], [0.6, 0.8, 0]])
    with pytest.raises(InputFormatError, match="2 points but 1"):
        analyze_arrays([(0, 0, 0), (1, 0, 0)], [[Z]])


# --- cross-check of the maximal support against a per-index LP -------------------------------


def _support_brute(g: np.ndarray) -> list[bool]:
    """i in S iff -g_i in cone(G): feasibility of G mu = -g_i, mu >= 0 (scipy HiGHS)."""
    out = []
    for i in range(g.shape[1]):
        res = linprog(np.zeros(g.shape[1]), A_eq=g, b_eq=-g[:, i], bounds=(0, None), method="highs")
        out.append(res.status == 0)
    return out


small_int_vectors = st.lists(
    st.tuples(*[st.integers(-1, 1)] * 3).filter(lambda v: v != (0, 0, 0)), min_size=1, max_size=7
)


@settings(max_examples=50, deadline=None, derandomize=True)
@given(small_int_vectors)
def test_maximal_support_matches_brute_force(vectors: list[tuple[int, int, int]]) -> None:
    g = np.array(vectors, dtype=float).T
    g = g / np.linalg.norm(g, axis=0)
    assert maximal_support(g).tolist() == _support_brute(g)


# --- properties ------------------------------------------------------------------------------

_DIRS = [X, Y, Z, MX, MY, (0, 0, -1), (S2, 0, S2), (0, -S2, S2), (1, 2, 2)]


@st.composite
def states(draw: st.DrawFn, max_normals: int = 2) -> list[ContactPoint]:
    n = draw(st.integers(0, 6))
    out = []
    for _ in range(n):
        p = tuple(float(v) for v in draw(st.tuples(*[st.integers(-2, 2)] * 3)))
        m = draw(st.integers(1, max_normals))
        ns = draw(st.lists(st.sampled_from(_DIRS), min_size=m, max_size=m, unique=True))
        out.append(cp(p, *ns))
    return out


def _rotation(q: tuple[float, float, float, float]) -> np.ndarray:
    w, x, y, z = np.array(q) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _numbers(r: DofResult) -> tuple[object, ...]:
    return (r.singular, r.translation, r.rotation, r.all, r.singular_dof_translation,
            r.singular_dof_rotation, r.singular_dof_all, r.restraining)  # fmt: skip


quaternions = st.tuples(*[st.floats(-1, 1)] * 4).filter(lambda q: sum(v * v for v in q) > 0.1)


@settings(max_examples=50, deadline=None, derandomize=True)
@given(
    states(),
    quaternions,
    st.tuples(*[st.floats(-10, 10)] * 3),
    st.floats(1e-3, 1e3),
    st.randoms(use_true_random=False),
)
def test_invariance(
    contacts: list[ContactPoint],
    q: tuple[float, float, float, float],
    t: tuple[float, float, float],
    scale: float,
    rnd: object,
) -> None:
    base = analyze(contacts)
    rot = _rotation(q)
    moved = [
        ContactPoint(scale * (rot @ c.point) + np.array(t), c.normals @ rot.T) for c in contacts
    ]
    assert _numbers(analyze(moved)) == _numbers(base)
    shuffled = list(contacts)
    rnd.shuffle(shuffled)  # type: ignore[attr-defined]
    assert _numbers(analyze(shuffled)) == _numbers(base)


@settings(max_examples=50, deadline=None, derandomize=True)
@given(states())
def test_sum_rules(contacts: list[ContactPoint]) -> None:
    r = analyze(contacts)
    assert sum(r.six("translation")) == 3
    assert sum(r.six("rotation")) == 3
    a, sa = r.all, r.singular_dof_all
    assert (
        a.maintaining
        + a.detaching
        + a.constraining
        + sum((sa.maintaining, sa.detaching, sa.constraining))
        == 6
    )
    used_t = r.singular_dof_translation if r.singular else r.translation
    used_r = r.singular_dof_rotation if r.singular else r.rotation
    used_a = r.singular_dof_all if r.singular else r.all
    assert used_r.maintaining == used_a.maintaining - used_t.maintaining  # proposition 3
    assert used_r.detaching_type1 + used_r.detaching_type2 == used_r.detaching
    assert min(used_r.detaching_type1, used_r.detaching_type2) >= 0
    rs = r.restraining
    assert rs.rotation == rs.all - rs.translation
    # restraining >= detaching + constraining (equality when non-singular)
    assert rs.translation >= used_t.detaching + used_t.constraining
    assert rs.all >= used_a.detaching + used_a.constraining
    # also rotation: span(W')/span(W) maps onto span(F')/span(F) when normals are added
    assert rs.rotation >= used_r.detaching + used_r.constraining
    if not r.singular:
        assert rs.translation == used_t.detaching + used_t.constraining
        assert rs.all == used_a.detaching + used_a.constraining
        assert rs.rotation == used_r.detaching + used_r.constraining
    # geometry matches the numbers and partitions R^3
    g = r.geometry
    assert g.translation_maintaining.shape[0] == used_t.maintaining
    assert g.translation_detaching.shape[0] == used_t.detaching
    assert g.translation_constraining.shape[0] == used_t.constraining
    assert g.rotation_maintaining.shape[0] == used_r.maintaining
    assert g.rotation_detaching.shape[0] == used_r.detaching
    assert g.rotation_detaching_type1.shape[0] == used_r.detaching_type1
    assert g.rotation_detaching_type2.shape[0] == used_r.detaching_type2
    assert g.rotation_constraining.shape[0] == used_r.constraining
    for parts in (
        (g.translation_maintaining, g.translation_detaching, g.translation_constraining),
        (g.rotation_maintaining, g.rotation_detaching, g.rotation_constraining),
    ):
        basis = np.vstack(parts)
        np.testing.assert_allclose(basis @ basis.T, np.eye(3), atol=1e-8)
    assert g.maintaining_twists.shape == (used_a.maintaining, 6)


def _in_vr(contacts: list[ContactPoint], s: np.ndarray) -> bool:
    """Brute force: is the rotation axis s in V_r, i.e. some S1 makes [s; S1] admissible?"""
    rows = [(n, np.cross(c.point, n) @ s) for c in contacts for n in c.normals]
    if not rows:
        return True
    a = np.array([n for n, _ in rows])
    b = np.array([m for _, m in rows])
    res = linprog(np.zeros(3), A_ub=-a, b_ub=b, bounds=(None, None), method="highs")
    return bool(res.status == 0)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(states(max_normals=1))
def test_rotation_subspaces_brute_force(contacts: list[ContactPoint]) -> None:
    r = analyze(contacts)
    g = r.geometry
    for s in np.vstack([g.rotation_maintaining, g.rotation_detaching_type1]):
        assert _in_vr(contacts, s) and _in_vr(contacts, -s)  # in lin(V_r): both ways
    for s in g.rotation_detaching_type2:
        assert not (_in_vr(contacts, s) and _in_vr(contacts, -s))
    for s in g.rotation_constraining:
        assert not _in_vr(contacts, s) and not _in_vr(contacts, -s)
    # the detaching direction breaks every breakable contact and keeps the others
    u = g.translation_detaching_direction
    if r.translation.detaching:
        dots = np.array([c.normals[0] @ u for c in contacts])
        assert dots.min() > -1e-9
        assert dots.max() > 1e-6
    else:
        np.testing.assert_array_equal(u, 0)


small_int_6vectors = st.lists(
    st.tuples(*[st.integers(-1, 1)] * 6).filter(any), min_size=1, max_size=9
)


@settings(max_examples=50, deadline=None, derandomize=True)
@given(small_int_6vectors)
def test_maximal_support_6d_matches_brute_force(vectors: list[tuple[int, ...]]) -> None:
    g = np.array(vectors, dtype=float).T
    assert maximal_support(g).tolist() == _support_brute(g / np.linalg.norm(g, axis=0))


def test_support_lp_fallback_directly() -> None:
    from apo.dof import _support_lp

    # null space of [x, y, -(x+y)/sqrt2, z, (x+z)/sqrt2]: support = first three
    g = np.array([X, Y, (-S2, -S2, 0), Z, (S2, 0, S2)]).T
    vt = np.linalg.svd(g)[2]
    assert _support_lp(vt[3:].T, 1e-7).tolist() == [True, True, True, False, False]


def test_lp_fallback_is_used(monkeypatch: pytest.MonkeyPatch) -> None:
    import apo.dof as dof

    calls = []
    original = dof._support_lp

    def counting(z: np.ndarray, eta: float) -> np.ndarray:
        calls.append(z.shape)
        return original(z, eta)

    monkeypatch.setattr(dof, "_support_lp", counting)
    rng = np.random.default_rng(0)
    for _ in range(30):
        g = rng.integers(-1, 2, size=(3, 7)).astype(float)
        g = g[:, np.linalg.norm(g, axis=0) > 0]
        assert maximal_support(g).tolist() == _support_brute(g / np.linalg.norm(g, axis=0))
    assert calls, "no random case reached the LP"


# --- every index against an independent LP computation ----------------------------------------


def _implicit_equalities(a: np.ndarray) -> np.ndarray:
    """Rows i with ``a_i . x = 0`` on all of ``{x : a x >= 0}``: one LP per row (scipy)."""
    m, n = a.shape
    out = np.zeros(m, dtype=bool)
    for i in range(m):
        res = linprog(
            -a[i],
            A_ub=np.vstack([-a, a[i : i + 1]]),
            b_ub=np.r_[np.zeros(m), 1.0],
            bounds=[(None, None)] * n,
            method="highs",
        )
        assert res.status == 0
        out[i] = -res.fun < 1e-9
    return out


def _rank(a: np.ndarray) -> int:
    return int(np.linalg.matrix_rank(a, tol=1e-9)) if a.size else 0


def _span_dim(a: np.ndarray, n: int, keep: int) -> int:
    """Dimension of the projection on the first ``keep`` coordinates of ``{x : a x >= 0}``."""
    eq = _implicit_equalities(a) if len(a) else np.zeros(0, dtype=bool)
    if eq.any():
        vt = np.linalg.svd(a[eq])[2]
        basis = vt[_rank(a[eq]) :].T  # span of the cone = null space of its equalities
    else:
        basis = np.eye(n)
    return _rank(basis[:keep])


def _brute_indices(contacts: list[ContactPoint]) -> tuple[tuple[int, ...], ...]:
    """(fig25 of the regular analysis, (m_a, d_a, c_a), (d_r1, d_r2)) straight from the
    definitions: ranks of R_t, R_a; dim V_t, V_a; V_r = projection of V_a; lin(V_r) as the
    projection of {(s, v1, v2) : [s; v1] and [-s; v2] admissible}."""
    if not contacts:
        return (3, 0, 0, 3, 0, 0), (6, 0, 0), (0, 0)
    f = np.array([c.normals[0] / np.linalg.norm(c.normals[0]) for c in contacts])
    mo = np.cross(np.array([c.point for c in contacts]), f)
    w = np.hstack([mo, f])  # rows act on [S0; S1]
    m_t, m_a = 3 - _rank(f), 6 - _rank(w)
    c_t = 3 - _span_dim(f, 3, 3)
    c_a = 6 - _span_dim(w, 6, 6)
    c_r = 3 - _span_dim(w, 6, 3)
    z = np.zeros_like(f)
    lin_vr = _span_dim(np.vstack([np.hstack([mo, f, z]), np.hstack([-mo, z, f])]), 9, 3)
    m_r = m_a - m_t
    d_r = 3 - m_r - c_r
    d_r1 = lin_vr - m_r
    return (m_t, 3 - m_t - c_t, c_t, m_r, d_r, c_r), (m_a, 6 - m_a - c_a, c_a), (d_r1, d_r - d_r1)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(states())
def test_every_index_matches_the_definitions(contacts: list[ContactPoint]) -> None:
    # Independent of apo.dof's maximal-support shortcuts: per-row LPs for the implicit
    # equalities, and the type I space lin(V_r) = {s : s and -s in V_r} lifted to (s, v1, v2).
    r = analyze(contacts)
    regular = [c for c in contacts if not c.singular]
    six, all_, rot12 = _brute_indices(regular)
    t = r.singular_dof_translation if r.singular else r.translation
    rot = r.singular_dof_rotation if r.singular else r.rotation
    a = r.singular_dof_all if r.singular else r.all
    got_six = (t.maintaining, t.detaching, t.constraining,
               rot.maintaining, rot.detaching, rot.constraining)  # fmt: skip
    assert got_six == six
    assert (a.maintaining, a.detaching, a.constraining) == all_
    assert (rot.detaching_type1, rot.detaching_type2) == rot12
    # restraining over every normal of every point (section 3.5)
    rows = [(c.point, n / np.linalg.norm(n)) for c in contacts for n in c.normals]
    f = np.array([n for _, n in rows]).reshape(-1, 3)
    w = np.array([np.r_[np.cross(p, n), n] for p, n in rows]).reshape(-1, 6)
    assert r.restraining == Restraining(_rank(f), _rank(w) - _rank(f), _rank(w))


def test_huge_finite_normal_is_only_a_direction() -> None:
    huge = analyze([cp((0, 0, 0), (1e308, 1e308, 0)), cp((1, 0, 0), Z)])
    assert _numbers(huge) == _numbers(analyze([cp((0, 0, 0), (1, 1, 0)), cp((1, 0, 0), Z)]))


def test_huge_coordinates_scale_away() -> None:
    s = 1e200
    big = analyze([cp((0, 0, 0), Z), cp((s, 0, 0), Z)])
    assert big.fig25 == (2, 1, 0, 2, 1, 0, 1, 1)  # box on an edge, as CASES


def _twists_scale(got: DofResult, ref: DofResult, s: float, *, exact: bool) -> None:
    """Maintaining twists of ``got`` are those of ``ref`` with the moments S1 of the
    rotation rows times ``s`` (the first m_t rows, pure translations, unchanged)."""
    m_t = ref.translation.maintaining
    tw, tw_ref = got.geometry.maintaining_twists, ref.geometry.maintaining_twists
    expected = tw_ref.copy()
    expected[m_t:, 3:] *= s
    if exact:
        assert np.array_equal(tw, expected)
    else:
        np.testing.assert_allclose(tw[:, :3], expected[:, :3], atol=1e-12)
        np.testing.assert_allclose(tw[m_t:, 3:] / s, tw_ref[m_t:, 3:], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(tw[:m_t, 3:], tw_ref[:m_t, 3:], atol=1e-12)


@pytest.mark.parametrize("s", [1e-200, 1e-5, 1e200, 1e300])
def test_scaled_coordinates_give_the_same_answer_and_scaled_twists(s: float) -> None:
    # The box on an edge of test_maintaining_twist_in_input_frame with every coordinate
    # times s: the same numbers and subspaces; the moment parts S1 (metres per rad) of the
    # rotational maintaining twists scale by s.
    pts = [(0, 5, 2), (3, 5, 2)]
    ref = analyze([cp(p, Z) for p in pts])
    got = analyze([cp(tuple(s * c for c in p), Z) for p in pts])
    assert _numbers(got) == _numbers(ref)
    _twists_scale(got, ref, s, exact=False)


def test_power_of_two_scaling_of_coordinates_and_normals_is_exact() -> None:
    # Points and normals are rescaled by powers of two only, so scaling the input by one
    # changes no bit of the unit normals and subspaces, and scales S1 exactly.
    contacts = [cp((0.3, 5.1, 2.7), (0.1, 0.2, 3.0)), cp((3.3, 4.9, 2.2), (0.3, -0.1, 1.7))]
    ref = analyze(contacts)
    k = 2.0**700
    got = analyze([cp(tuple(k * p for p in c.point), *(k * c.normals)) for c in contacts])
    assert _numbers(got) == _numbers(ref)
    _twists_scale(got, ref, k, exact=True)
    for name in ("rotation_maintaining", "rotation_detaching", "translation_detaching_direction"):
        assert np.array_equal(getattr(got.geometry, name), getattr(ref.geometry, name)), name
    _, ns = check_contacts(contacts)
    _, ns_k = check_contacts([cp(c.point, *(k * c.normals)) for c in contacts])
    for a, b in zip(ns, ns_k, strict=True):
        assert np.array_equal(a, b)


@pytest.mark.parametrize(
    ("normal", "zero"),
    [
        ((1e-13, 0, 0), True),
        ((0, 5e-13, 5e-13), True),
        ((1e-11, 0, 0), False),
        ((1e-300, 0, 0), True),
    ],
)
def test_tiny_normals_are_zero_below_1e_12_only(normal: tuple[float, ...], zero: bool) -> None:
    # A normal is zero when its length is at most 1e-12, however it is scaled internally.
    contacts = [cp((0, 0, 0), Z), cp((1, 0, 0), normal)]
    if zero:
        with pytest.raises(InputFormatError, match="contact 1: normal 0 is zero"):
            check_contacts(contacts)
    else:
        np.testing.assert_allclose(check_contacts(contacts)[1][1], [[1, 0, 0]])


def test_a_bad_contact_after_a_huge_normal_is_named() -> None:
    # The culprit search does not overflow on the huge, valid normal of contact 0.
    with pytest.raises(InputFormatError, match="contact 1: normal 0 is zero"):
        check_contacts([cp((0, 0, 0), (1e308, -1e308, 1e308)), cp((1, 0, 0), (0, 0, 0))])


@pytest.mark.parametrize("name", list(CASES))
def test_the_lp_oracle_agrees_with_the_hand_derivations(name: str) -> None:
    # The oracle above is itself checked on the hand-derived states.
    contacts, fig25, all_, rot12 = CASES[name]
    assert _brute_indices(contacts) == (fig25[:6], all_, rot12)


@pytest.mark.parametrize(
    ("z", "support"),
    [
        ([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]], [False, False, True]),
        ([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], [True, True, True]),
        ([[1.0, 1.0], [-1.0, -1.0], [0.0, 0.0]], [False, False, False]),
    ],
)
def test_support_rescue_keeps_what_a_verified_point_certifies(z, support):
    # HiGHS's unproven points are verified here: each t_i > 1/2 with Z y >= t certifies
    # z_i . y > 0; the union over settings is in the maximal support.
    from apo import dof

    z = np.asarray(z)
    got = dof._support_rescue(dof._support_lp_model(z), z, 1e-9)
    np.testing.assert_array_equal(got, support)
    np.testing.assert_array_equal(dof._support_lp(z, 1e-9), support)


def test_recognition_survives_a_cone_highs_cannot_prove():
    # Random T-peg variant 3, 0.03 mm / 0.05 deg of noise and a constant 0.75 mm offset:
    # HiGHS stopped with status "unknown" on one state's cone and recognition raised a
    # bare RuntimeError("maximal-support LP failed").
    from apo import synthetic
    from apo.recognition import recognize
    from apo.recognition.inputs import default_threshold

    d = synthetic.random_variant(3)
    base = default_threshold(d.grasped, d.environment)
    nd = synthetic.add_noise(d, sigma_mm=0.05 * base * 1e3 / 4, sigma_deg=0.05, seed=3)
    rng = np.random.default_rng(3)
    u = rng.normal(size=3)
    X = nd.X_EG.copy()
    X[:, :3, 3] += 0.3 * base * u / np.linalg.norm(u)
    task = recognize(d.grasped, d.environment, nd.times, X)
    assert task.states
