"""Tests of apo.synthetic: exact scripted contacts, no penetration, hand-derived DOF, noise."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

import numpy as np
import pytest

from apo.contact import ContactFinder, contact_points, element_residuals
from apo.dof import DofResult, analyze
from apo.geometry import Polyhedron, point_face_distance
from apo.synthetic import (
    VARIANTS,
    SyntheticDemo,
    add_noise,
    block_on_table_to_corner,
    block_tipping,
    corner_tray,
    peg_in_hole_2d,
    random_variant,
    square_peg_in_hole,
)

BUILDERS: dict[str, Callable[[], SyntheticDemo]] = {
    "peg_in_hole_2d": peg_in_hole_2d,
    "square_peg_in_hole": square_peg_in_hole,
    "block_on_table_to_corner": block_on_table_to_corner,
    "block_tipping": block_tipping,
}
# Random variants: sizes, proportions, shapes (random prisms), speeds, placements.
BUILDERS.update(
    {
        f"{key}#{seed}": (lambda key=key, seed=seed: random_variant(seed, name=key))
        for key in VARIANTS
        for seed in (0, 1)
    }
)
_CACHE: dict[str, SyntheticDemo] = {}


def demo(name: str) -> SyntheticDemo:
    if name not in _CACHE:
        _CACHE[name] = BUILDERS[name]()
    return _CACHE[name]


# --------------------------------------------------------------------------------------------
# Penetration check: sampled surface points of one model strictly inside the other
# --------------------------------------------------------------------------------------------


def surface_samples(poly: Polyhedron, k: int = 6) -> np.ndarray:
    """Vertices, points along edges and a barycentric grid on every face triangle."""
    pts = [poly.vertices]
    s = np.linspace(0.0, 1.0, 4 * k)[1:-1, None]
    E0, E1 = poly.vertices[poly.edges[:, 0]], poly.vertices[poly.edges[:, 1]]
    pts.append((E0[:, None] + s[None] * (E1 - E0)[:, None]).reshape(-1, 3))
    ij = [(i, j) for i in range(1, k) for j in range(1, k - i)]
    bary = np.array([(i / k, j / k, 1 - (i + j) / k) for i, j in ij])
    for tris in poly.face_triangles:
        P = poly.vertices[tris]  # (T, 3, 3)
        pts.append(np.einsum("bk,tkd->tbd", bary, P).reshape(-1, 3))
    return np.concatenate(pts)


def winding(poly: Polyhedron, points: np.ndarray) -> np.ndarray:
    """Generalised winding number of points w.r.t. the closed surface (1 inside, 0 out)."""
    tris = np.concatenate(poly.face_triangles)
    A, B, C = (poly.vertices[tris[:, i]][None] - points[:, None] for i in range(3))
    la, lb, lc = (np.linalg.norm(v, axis=2) for v in (A, B, C))
    num = np.einsum("pti,pti->pt", A, np.cross(B, C))
    den = (
        la * lb * lc
        + np.einsum("pti,pti->pt", A, B) * lc
        + np.einsum("pti,pti->pt", A, C) * lb
        + np.einsum("pti,pti->pt", B, C) * la
    )
    return np.asarray(2.0 * np.arctan2(num, den).sum(axis=1) / (4 * np.pi))


def depth_inside(poly: Polyhedron, points: np.ndarray) -> np.ndarray:
    """Distance to the surface for points inside ``poly`` (0 for points outside)."""
    inside = winding(poly, points) > 0.5
    if not inside.any():
        return np.zeros(len(points))
    q = points[inside]
    d = np.min([point_face_distance(poly, f, q)[0] for f in range(len(poly.faces))], axis=0)
    out = np.zeros(len(points))
    out[inside] = d
    return out


def test_penetration_check_detects_a_penetrating_pose() -> None:
    d = demo("block_tipping")
    X = d.X_EG_true[-1].copy()
    X[2, 3] -= 0.001  # 1 mm into the table
    P = surface_samples(d.grasped) @ X[:3, :3].T + X[:3, 3]
    assert depth_inside(d.environment, P).max() == pytest.approx(0.001, rel=1e-6)


@pytest.mark.parametrize("name", list(BUILDERS))
def test_true_poses_do_not_penetrate(name: str) -> None:
    d = demo(name)
    PG, PE = surface_samples(d.grasped), surface_samples(d.environment)
    for X in d.X_EG_true[::2]:
        R, t = X[:3, :3], X[:3, 3]
        assert depth_inside(d.environment, PG @ R.T + t).max() < 1e-9
        assert depth_inside(d.grasped, (PE - t) @ R).max() < 1e-9


# --------------------------------------------------------------------------------------------
# Scripted contacts hold, states as derived by hand
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(BUILDERS))
def test_every_frame_is_in_its_true_state(name: str) -> None:
    d = demo(name)
    finder = ContactFinder(d.grasped, d.environment)
    for k, X in enumerate(d.X_EG_true):
        st = d.true_states[int(d.labels[k])]
        state = finder.find(X)
        assert state.key == st.key, (name, st.name, k)
        assert Counter(e.kind.value for e in state.elements) == Counter(st.kinds), st.name
        assert state.singular == st.singular, st.name
        r, _ = element_residuals(d.grasped, d.environment, X, state.elements)
        assert np.abs(r).max(initial=0.0) < 1e-12, (st.name, k)


@pytest.mark.parametrize("name", list(BUILDERS))
def test_states_are_clear_of_unscripted_contacts(name: str) -> None:
    # Features not scripted to touch stay more than the margin apart: a threshold just
    # below the margin finds the same states.
    d = demo(name)
    finder = ContactFinder(d.grasped, d.environment, threshold=0.95 * d.meta["margin"])
    for k, X in enumerate(d.X_EG_true):
        assert finder.find(X).key == d.true_states[int(d.labels[k])].key, (name, k)


def dof(d: SyntheticDemo, state: int) -> DofResult:
    k = int(np.flatnonzero(d.labels == state)[0])
    found = ContactFinder(d.grasped, d.environment).find(d.X_EG_true[k])
    return analyze(contact_points(found))


@pytest.mark.parametrize("name", list(BUILDERS))
def test_fig25_of_every_true_state_matches_the_hand_derivation(name: str) -> None:
    # The expected numbers and their one-line reasoning are in TrueState.fig25 / .reason.
    d = demo(name)
    for i, st in enumerate(d.true_states):
        assert dof(d, i).fig25 == st.fig25, (name, st.name, st.reason)


# Key states of the paper's Fig. 25, restated here with one line of reasoning each.
PEG_2D_FIG25 = {
    # B: one line contact (normal +y): slide x, z, spin about y and the edge; tip about x.
    "B": (2, 1, 0, 2, 1, 0, 1, 1),
    # C: edge on parallel edge, singular: nothing regular remains, 2 normals x 2 points.
    "C": (3, 0, 0, 3, 0, 0, 2, 2),
    # E: two line contacts with different in-plane normals: z slides, 2D rotation kept.
    "E": (1, 2, 0, 1, 2, 0, 2, 2),
    # F: four VV at both rims, normals span the xy-plane; moments add the z-spread: r_r = 3.
    "F": (3, 0, 0, 3, 0, 0, 2, 3),
    # G: +-x at four points: x and rotations about y, z constrained.
    "G": (2, 0, 1, 1, 0, 2, 1, 2),
    # H: seated (as the first author's final frame): lift only, tip about x.
    "H": (1, 1, 1, 0, 1, 2, 2, 3),
}


def test_peg_2d_follows_the_papers_fig25() -> None:
    d = demo("peg_in_hole_2d")
    assert d.state_sequence == list("ABCDEFGH")
    names = [s.name for s in d.true_states]
    for n, fig in PEG_2D_FIG25.items():
        assert dof(d, names.index(n)).fig25 == fig, n
    # The paper's push-to (1), (4), (7) are type I: the two-way rotation DOF grows.
    for a, b in (("A", "B"), ("D", "E"), ("G", "H")):
        r0 = dof(d, names.index(a)).rotation.detaching_type1
        r1 = dof(d, names.index(b)).rotation.detaching_type1
        assert r1 == r0 + 1, (a, b)


def test_short_singular_states() -> None:
    d = demo("peg_in_hole_2d")
    runs = {d.true_states[s].name: b - a for s, a, b in d.segments()}
    assert runs["C"] == 2 and runs["F"] == 1  # the paper's F was seen in a single frame
    assert d.true_states[2].singular and d.true_states[5].singular
    sq = demo("square_peg_in_hole")
    assert sq.state_sequence == ["A", "B", "A", "F", "G", "H"]
    assert [b - a for s, a, b in sq.segments() if sq.true_states[s].name == "F"] == [1]


def six(r: DofResult, space: str) -> np.ndarray:
    return np.array(r.six(space))


def test_expected_subskills_agree_with_the_rules() -> None:
    # Cross-check of the hand-written sub-skills against the paper's rules applied to the
    # DOF numbers of the true states (a check of the data, not how it was written).
    for name in BUILDERS:
        d = demo(name)
        segs = d.segments()
        assert len(d.expected_subskills) == len(segs) - 1
        for tr, (s0, _, _), (s1, _, _) in zip(d.expected_subskills, segs, segs[1:], strict=False):
            assert (tr.source, tr.target) == (s0, s1)
            a, b = dof(d, s0), dof(d, s1)
            got: list[tuple[str, str, str | None]] = []
            critical = False
            restr = {
                "translation": b.restraining.translation - a.restraining.translation,
                "rotation": b.restraining.rotation - a.restraining.rotation,
            }
            for space in ("translation", "rotation"):
                dM, dD, dC, dSM, dSD, _dSC = six(b, space) - six(a, space)
                if dM < 0 and (dD > 0 or dSD > 0):
                    kind = None
                    if space == "rotation":
                        ra = a.singular_dof_rotation if a.singular else a.rotation
                        rb = b.singular_dof_rotation if b.singular else b.rotation
                        kind = "I" if rb.detaching_type1 > ra.detaching_type1 else "II"
                    got.append(("push_to", space, kind))
                if dM > 0 and (dD < 0 or dSD < 0):
                    got.append(("release", space, None))
                if dM < 0 and dSM > 0 and restr[space] > 0:
                    got.append(("slide", space, None))
                critical |= bool((dSM < 0 or dSD < 0) and dC > 0)
            assert tuple(got) == tr.subskills, (name, tr.reason)
            assert critical == tr.critical, (name, tr.reason)


def test_corner_tray_geometry() -> None:
    tray = corner_tray()
    assert (len(tray.faces), len(tray.vertices), len(tray.edges)) == (9, 14, 21)
    assert tray.n_concave_edges == 3  # the two wall feet and the corner between the walls
    assert tray.volume == pytest.approx(0.3 * 0.3 * 0.02 + (0.3 + 0.28) * 0.02 * 0.06)


def test_frames_times_and_meta() -> None:
    for name in BUILDERS:
        d = demo(name)
        n = len(d)
        assert d.X_EG.shape == d.X_EG_true.shape == (n, 4, 4)
        assert np.array_equal(d.X_EG, d.X_EG_true)
        assert np.all(np.diff(d.times) > 0) and d.labels.shape == (n,)
        assert d.meta["units"] == {"length": "m", "angle": "rad", "time": "s"}
        assert d.meta["noise"] == [] and len(d.meta["phases"]) == n
    assert len(peg_in_hole_2d(n_frames=30)) == 30
    with pytest.raises(ValueError, match="n_frames=10 is too small"):
        peg_in_hole_2d(n_frames=10)
    with pytest.raises(ValueError, match="tilt_deg"):
        peg_in_hole_2d(tilt_deg=40.0)
    with pytest.raises(ValueError, match="margin"):
        block_tipping(margin=0.0)


# --------------------------------------------------------------------------------------------
# Noise
# --------------------------------------------------------------------------------------------


def pose_errors(d: SyntheticDemo) -> tuple[np.ndarray, np.ndarray]:
    """Centroid position error (m) and rotation angle error (rad) of the observed poses."""
    cg = d.grasped.vertices.mean(axis=0)
    c_obs = d.X_EG[:, :3, :3] @ cg + d.X_EG[:, :3, 3]
    c_true = d.X_EG_true[:, :3, :3] @ cg + d.X_EG_true[:, :3, 3]
    dR = d.X_EG[:, :3, :3] @ np.swapaxes(d.X_EG_true[:, :3, :3], 1, 2)
    ang = np.arccos(np.clip((np.trace(dR, axis1=1, axis2=2) - 1) / 2, -1, 1))
    return c_obs - c_true, ang


def test_noise_is_seeded_and_leaves_the_truth() -> None:
    d = demo("peg_in_hole_2d")
    a = add_noise(d, sigma_mm=1.0, sigma_deg=0.5, seed=7)
    b = add_noise(d, sigma_mm=1.0, sigma_deg=0.5, seed=7)
    c = add_noise(d, sigma_mm=1.0, sigma_deg=0.5, seed=8)
    assert np.array_equal(a.X_EG, b.X_EG) and not np.array_equal(a.X_EG, c.X_EG)
    assert np.array_equal(a.X_EG_true, d.X_EG_true) and np.array_equal(a.labels, d.labels)
    assert a.meta["noise"][0]["sigma_mm"] == 1.0 and d.meta["noise"] == []
    R = a.X_EG[:, :3, :3]
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12)


def test_noise_has_the_requested_size() -> None:
    d = peg_in_hole_2d(n_frames=2000)
    noisy = add_noise(d, sigma_mm=2.0, sigma_deg=1.0, seed=1)
    dp, ang = pose_errors(noisy)
    assert dp.std(axis=0) == pytest.approx([0.002] * 3, rel=0.1)
    # The angle of a rotation vector with N(0, s^2) per axis: RMS sqrt(3) s.
    assert np.sqrt((ang**2).mean()) == pytest.approx(np.sqrt(3) * np.radians(1.0), rel=0.1)
    assert not noisy.outliers.any()


def test_outliers_are_large_and_marked() -> None:
    d = peg_in_hole_2d(n_frames=400)
    noisy = add_noise(d, sigma_mm=0.5, sigma_deg=0.2, outlier_rate=0.1, seed=3)
    dp, ang = pose_errors(noisy)
    out = noisy.outliers
    assert 20 <= out.sum() <= 60
    assert np.linalg.norm(dp[out], axis=1).min() >= 0.01 - 1e-12
    assert ang[out].min() >= np.radians(7.5) - 1e-12
    assert np.linalg.norm(dp[~out], axis=1).max() < 0.005
    assert noisy.meta["noise"][0]["n_outliers"] == int(out.sum())


def test_dropped_frames_keep_times_increasing_and_every_state() -> None:
    d = demo("peg_in_hole_2d")
    noisy = add_noise(d, sigma_mm=0.0, sigma_deg=0.0, drop_rate=0.5, seed=4)
    assert 15 < len(noisy) < 45
    assert np.all(np.diff(noisy.times) > 0) and np.all(np.diff(noisy.frame_ids) > 0)
    assert np.array_equal(noisy.X_EG_true, d.X_EG_true[noisy.frame_ids])
    assert np.array_equal(noisy.labels, d.labels[noisy.frame_ids])
    assert np.allclose(noisy.X_EG, noisy.X_EG_true, atol=1e-15)
    # Every state keeps at least one frame, so the expected sequence stays valid.
    assert noisy.state_sequence == d.state_sequence
    assert len(noisy.meta["phases"]) == len(noisy)
    everything = add_noise(d, sigma_mm=0.0, sigma_deg=0.0, drop_rate=1.0, seed=4)
    assert len(everything) == len(d.segments())


def test_noise_validation() -> None:
    d = demo("block_tipping")
    with pytest.raises(ValueError, match="sigma_mm must be a non-negative"):
        add_noise(d, sigma_mm=-1.0, sigma_deg=0.0)
    with pytest.raises(ValueError, match=r"drop_rate must be in \[0, 1\]"):
        add_noise(d, sigma_mm=1.0, sigma_deg=0.0, drop_rate=1.5)
    g = np.random.default_rng(5)
    assert add_noise(d, sigma_mm=1.0, sigma_deg=1.0, seed=g).meta["noise"][0]["seed"] == (
        "generator"
    )


@pytest.mark.parametrize(
    ("scale", "depth", "margin"), [(0.8, 0.05, 0.003), (1.6, 0.05, 0.0039), (1.0, 0.07, 0.002)]
)
def test_the_t_peg_keeps_its_margin_with_a_short_stem(scale: float, depth: float, margin: float):
    # Nothing that is not scripted to touch comes within the margin, at any frame: with a
    # short stem the crossbar came within 1.2 k mm of the block's top at the start of E
    demo = peg_in_hole_2d(scale=scale, depth=depth, margin=margin)
    finder = ContactFinder(demo.grasped, demo.environment, threshold=0.95 * margin)
    for t, X in enumerate(demo.X_EG_true):
        assert finder.find(X).key == demo.true_states[int(demo.labels[t])].key, t
