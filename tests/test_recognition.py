import numpy as np
import pytest

from apo.errors import InputFormatError
from apo.recognition import check_sequence, element_distances, viterbi
from apo.shapes import box
from apo.spatial import matrix_from_axis_angle


def _poses(zs, angle=0.0):
    X = np.tile(np.eye(4), (len(zs), 1, 1))
    X[:, :3, :3] = matrix_from_axis_angle([0, 0, 1], angle)
    X[:, 2, 3] = zs
    return X


# ---------------------------------------------------------------------------------------------
# Viterbi
# ---------------------------------------------------------------------------------------------


def test_viterbi_smooths_a_one_frame_blip_when_switching_is_dearer():
    # State 1 is cheaper at frame 2 by 1.0 but entering and leaving costs 2 x 1.5.
    e = np.array([[0, 9], [0, 9], [1.0, 0], [0, 9], [0, 9]])
    tr = np.array([[0, 1.5], [1.5, 0]])
    path, cost = viterbi(e, tr)
    assert path.tolist() == [0, 0, 0, 0, 0]
    assert cost == pytest.approx(1.0)


def test_viterbi_keeps_a_one_frame_state_that_is_needed():
    # 0 -> 2 is forbidden (huge cost): the path must pass through state 1.
    e = np.array([[0, 5, 5], [0, 5, 5], [5, 3, 5], [5, 5, 0], [5, 5, 0]], dtype=float)
    tr = np.array([[0, 1, 1e6], [1, 0, 1], [1e6, 1, 0]])
    path, _ = viterbi(e, tr)
    assert path.tolist() == [0, 0, 1, 2, 2]


def test_viterbi_uniform_matches_viterbi():
    from apo.recognition import viterbi_uniform

    rng = np.random.default_rng(4)
    for _ in range(20):
        e = rng.random((30, 6)) * 3
        tr = np.full((6, 6), 1.2)
        np.fill_diagonal(tr, 0)
        p_full, c_full = viterbi(e, tr)
        p_fast = viterbi_uniform(e, 1.2)
        cost = e[np.arange(30), p_fast].sum() + 1.2 * np.count_nonzero(np.diff(p_fast))
        assert cost == pytest.approx(c_full)
        assert p_fast.tolist() == p_full.tolist()


def test_viterbi_matches_brute_force():
    rng = np.random.default_rng(3)
    import itertools

    for _ in range(20):
        e = rng.random((5, 3)) * 4
        tr = rng.random((3, 3)) * 2
        np.fill_diagonal(tr, 0)
        best = min(
            itertools.product(range(3), repeat=5),
            key=lambda p: (
                sum(e[t, p[t]] for t in range(5)) + sum(tr[p[t], p[t + 1]] for t in range(4))
            ),
        )
        _path, cost = viterbi(e, tr)
        ref = sum(e[t, best[t]] for t in range(5)) + sum(tr[best[t], best[t + 1]] for t in range(4))
        assert cost == pytest.approx(ref)


# ---------------------------------------------------------------------------------------------
# Element distances
# ---------------------------------------------------------------------------------------------


def _top_face(b):
    return int(np.argmax(b.face_normals[:, 2]))


def test_element_distances_vertex_face_and_face_vertex():
    E = box([1.0, 1.0, 1.0])  # top at z = 0.5
    G = box([0.2, 0.2, 0.2])  # bottom at z = -0.1 in its frame
    v = int(np.argmin(G.vertices @ [1, 1, 1]))  # bottom corner (-0.1, -0.1, -0.1)
    top, bottom = _top_face(E), int(np.argmin(G.face_normals[:, 2]))
    ve = int(np.argmax(E.vertices @ [1, 1, 1]))  # E's corner (0.5, 0.5, 0.5)
    X = _poses([0.6, 0.65, 0.8])  # G's bottom at 0.5, 0.55, 0.7
    X[:, 0, 3] = 0.45
    X[:, 1, 3] = 0.45  # E's top corner lies under G's bottom face
    keys = [("VF", ("v", v), ("f", top)), ("FV", ("f", bottom), ("v", ve))]
    d = element_distances(G, E, X, keys)
    np.testing.assert_allclose(d[:, 0], [0.0, 0.05, 0.2], atol=1e-12)
    np.testing.assert_allclose(d[:, 1], [0.0, 0.05, 0.2], atol=1e-12)


def test_element_distances_edges_and_vertices():
    E = box([1.0, 1.0, 1.0])
    G = box([0.2, 0.2, 0.2])
    # G's bottom edge along y at x = -0.1 and E's top edge along y at x = +0.5: shift G so
    # that they are parallel and 0.03 apart in z.
    ge = next(i for i, (a, b) in enumerate(G.edges)
              if np.allclose(G.vertices[[a, b]][:, [0, 2]], [[-0.1, -0.1]] * 2))  # fmt: skip
    ee = next(i for i, (a, b) in enumerate(E.edges)
              if np.allclose(E.vertices[[a, b]][:, [0, 2]], [[0.5, 0.5]] * 2))  # fmt: skip
    gv = int(np.argmin(G.vertices @ [1, 1, 1]))
    ev = int(np.argmax(E.vertices @ [1, 1, 1]))
    X = _poses([0.63])
    X[0, 0, 3] = 0.6
    X[0, 1, 3] = 0.6  # G's corner (-0.1,-0.1,-0.1) -> (0.5, 0.5, 0.53)
    keys = [
        ("EE", ("e", ge), ("e", ee)),
        ("VE", ("v", gv), ("e", ee)),
        ("EV", ("e", ge), ("v", ev)),
        ("VV", ("v", gv), ("v", ev)),
    ]
    d = element_distances(G, E, X, keys)
    np.testing.assert_allclose(d[0], [0.03, 0.03, 0.03, 0.03], atol=1e-12)


def test_element_distances_rejects_bad_keys():
    E = box()
    with pytest.raises(ValueError, match="unsupported feature pair"):
        element_distances(E, E, _poses([0.0]), [("VF", ("f", 0), ("f", 1))])


# ---------------------------------------------------------------------------------------------
# Input validation
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("times", "X", "match"),
    [
        (None, np.zeros((0, 4, 4)), "empty sequence"),
        (None, np.zeros((3, 3, 3)), r"expected poses of shape \(N, 4, 4\)"),
        (np.arange(2.0), _poses([0, 0, 0]), "expected 3 time stamps"),
        (np.array([0, 1, 0.5]), _poses([0, 0, 0]), "frame 2: time goes backwards"),
        (np.array([0, np.nan, 2]), _poses([0, 0, 0]), "frame 1: time is not finite"),
    ],
)
def test_check_sequence_errors(times, X, match):
    with pytest.raises(InputFormatError, match=match):
        check_sequence(times, X, source="demo.csv")


def test_check_sequence_names_the_nan_frame_and_file():
    X = _poses([0, 0, 0, 0])
    X[2, 1, 3] = np.nan
    with pytest.raises(InputFormatError, match=r"^demo.csv: frame 2: pose is not finite"):
        check_sequence(None, X, source="demo.csv")


def test_check_sequence_rejects_non_rigid():
    X = _poses([0, 0])
    X[1, :3, :3] *= 1.001
    with pytest.raises(InputFormatError, match="frame 1: not a rigid pose"):
        check_sequence(None, X, source="d")


def test_check_sequence_defaults_times_to_frame_indices():
    t, X = check_sequence(None, _poses([0, 1, 2]))
    assert t.tolist() == [0.0, 1.0, 2.0]
    assert X.shape == (3, 4, 4)


# ---------------------------------------------------------------------------------------------
# The pipeline on a scripted scene: a cube lowered onto a table, then slid along it
# ---------------------------------------------------------------------------------------------


def _table_and_cube():
    table = box([0.4, 0.4, 0.1], center=[0.0, 0.0, -0.05], name="table")
    cube = box([0.05, 0.05, 0.05], center=[0.0, 0.0, 0.025], name="cube")
    return cube, table


def _lower_and_slide(n_down=20, n_slide=20):
    z = np.r_[np.linspace(0.03, 0.0, n_down), np.zeros(n_slide)]
    x = np.r_[np.zeros(n_down), np.linspace(0.0, 0.05, n_slide)]
    X = _poses(z)
    X[:, 0, 3] = x
    return np.arange(len(z)) * 0.1, X


def test_cube_on_table_two_states_and_a_push_to():
    from apo.recognition import recognize_frames

    cube, table = _table_and_cube()
    t, X = _lower_and_slide()
    rec = recognize_frames(cube, table, t, X, threshold=0.002)
    task = rec.task
    assert [s.id for s in task.states] == ["A", "B"]
    a, b = task.states
    assert a.elements == () and a.fig25 == (3, 0, 0, 3, 0, 0, 0, 0)
    # Face on face: 4 VF at the cube's bottom corners; z translation detaching, rotation
    # about z maintaining, about x and y detaching (the cube tips over an edge).
    assert len(b.elements) == 4 and {e.kind for e in b.elements} == {"VF"}
    assert b.fig25[:6] == (2, 1, 0, 1, 2, 0)
    assert not b.singular
    assert b.times[0] == pytest.approx(t[b.frames[0]])
    tr = task.transitions[0]
    kinds = {(s.kind, s.space) for s in tr.subskills}
    assert ("push_to", "translation") in kinds
    push = next(s for s in tr.subskills if s.kind == "push_to" and s.space == "translation")
    assert abs(push.direction[2]) == pytest.approx(1.0, abs=1e-6)
    assert not tr.critical
    assert rec.converged.all()
    # The representative pose of B is corrected onto the table.
    assert b.X_EG[2, 3] == pytest.approx(0.0, abs=1e-9)
    assert task.n_frames == len(t)
    assert len(rec.state_of_frame) == len(t)


def test_noise_blips_are_repaired_and_recorded():
    from apo.recognition import recognize_frames

    cube, table = _table_and_cube()
    t, X = _lower_and_slide(30, 30)
    # Tilt the cube at one sliding frame so that only one bottom edge stays within the
    # threshold (a noise blip), and lift it at another (a spurious free frame).
    from apo.spatial import matrix_from_axis_angle

    X[40, :3, :3] = matrix_from_axis_angle([1, 0, 0], 0.06)
    X[40, 2, 3] = 0.0008
    X[50, 2, 3] = 0.0021
    rec = recognize_frames(cube, table, t, X, threshold=0.002)
    assert [s.id for s in rec.task.states] == ["A", "B"]
    assert rec.repaired[[40, 50]].all()
    assert {r.frames for r in rec.task.rejected} >= {(40, 40), (50, 50)}
    assert all(r.replaced_by == ("B",) for r in rec.task.rejected if r.frames[0] >= 40)


def test_empty_and_nan_sequences_are_rejected():
    from apo.recognition import recognize

    cube, table = _table_and_cube()
    with pytest.raises(InputFormatError, match="empty sequence"):
        recognize(cube, table, None, np.zeros((0, 4, 4)))
    X = _poses([0.01, np.nan])
    with pytest.raises(InputFormatError, match="frame 1: pose is not finite"):
        recognize(cube, table, None, X, source="x.csv")


def test_poses_in_the_wrong_units_are_rejected():
    from apo.recognition import recognize

    cube, table = _table_and_cube()
    X = _poses([30.0, 31.0])  # millimetres read as metres: 30 m above the table
    with pytest.raises(InputFormatError, match=r"^x.csv: the grasped object is never near"):
        recognize(cube, table, None, X, source="x.csv")


# ---------------------------------------------------------------------------------------------
# Batched pose correction
# ---------------------------------------------------------------------------------------------


def test_correct_poses_makes_contacts_hold_and_reports_residuals():
    from apo.contact import ContactFinder
    from apo.recognition import correct_poses

    cube, table = _table_and_cube()
    finder = ContactFinder(cube, table, threshold=0.003)
    X0 = _poses([0.0])[0]
    state = finder.find(X0)
    rng = np.random.default_rng(1)
    X = np.tile(X0, (20, 1, 1))
    X[:, :3, 3] += rng.normal(0, 0.001, (20, 3))
    for i in range(20):
        X[i, :3, :3] = matrix_from_axis_angle(rng.normal(size=3), rng.normal(0, 0.01))
    Xc, before, after, ok = correct_poses(cube, table, X, state.elements)
    assert ok.all()
    assert (after <= 1e-7).all() and np.median(before) > 1e-4
    # Flat on the table again: bottom corners at z = 0, rotation only about z.
    corners = cube.vertices[cube.vertices[:, 2] < 1e-9]
    for Xi in Xc:
        z = corners @ Xi[:3, :3].T[:, 2] + Xi[2, 3]
        np.testing.assert_allclose(z, 0.0, atol=1e-7)
    # x, y drift is not corrected (a free direction of the state): min-norm steps.
    np.testing.assert_allclose(Xc[:, :2, 3], X[:, :2, 3], atol=2e-3)


def test_near_signatures_separate_every_contact_state():
    from apo.contact import ContactFinder
    from apo.recognition import near_signatures
    from apo.shapes import t_peg, u_block
    from apo.spatial import pose_from_twist

    peg, block = t_peg(), u_block()
    rng = np.random.default_rng(5)
    # A noisy descent of the peg into the slot: free, touching the walls, seated.
    X = []
    for y in np.linspace(0.06, 0.035, 60):
        X0 = np.eye(4)
        X0[1, 3] = y
        X.append(pose_from_twist(np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.001, 3)]) @ X0)
    X = np.array(X)
    theta = 0.002
    keys = [s.key for s in ContactFinder(peg, block, threshold=theta).find_batch(X)]
    labels = near_signatures(peg, block, X, theta, chunk=7)
    assert labels[0] == 0 and labels.max() + 1 == len(set(labels.tolist()))
    for lab in set(labels.tolist()):
        assert len({keys[i] for i in np.flatnonzero(labels == lab)}) == 1
    assert len(set(keys)) >= 5  # the scene is not trivial


def test_meet_of_a_corner_passing_a_corner_is_vertex_vertex():
    from apo.contact import ContactElement, ContactKind
    from apo.recognition import meet_elements
    from apo.shapes import t_peg, u_block

    peg, block = t_peg(), u_block()
    gv, ev = 0, 3
    ge = int(np.flatnonzero((peg.edges == gv).any(axis=1))[0])  # an edge of the peg at gv
    ee = int(np.flatnonzero((block.edges == ev).any(axis=1))[0])  # an edge of the block at ev
    other_e = int(np.flatnonzero(~(block.edges == ev).any(axis=1))[0])  # not bounded by ev
    n = np.array([[0.0, 1.0, 0.0]])
    p = np.zeros(3)
    ve = ContactElement(ContactKind.VE, ("v", gv), ("e", ee), p, n)
    ev_ = ContactElement(ContactKind.EV, ("e", ge), ("v", ev), p, n)
    far = ContactElement(ContactKind.VE, ("v", gv), ("e", other_e), p, n)
    meet = meet_elements(peg, block, [ve], [ev_])
    assert [e.key for e in meet] == [("VV", ("v", gv), ("v", ev))]
    # No meet when the edge does not end at the vertex: plain union.
    union = meet_elements(peg, block, [far], [ev_])
    assert sorted(e.key for e in union) == sorted([far.key, ev_.key])


# ---------------------------------------------------------------------------------------------
# A T-peg lowered straight into a U-slot (zero clearance), with and without noise
# ---------------------------------------------------------------------------------------------


def _straight_insertion(sigma=0.0, seed=0):
    from apo.spatial import pose_from_twist

    ys = np.r_[
        np.linspace(0.14, 0.089, 20),  # free, above the slot
        np.full(3, 0.088),  # stem corners on the slot's top corners (singular)
        np.linspace(0.087, 0.036, 20),  # sliding down between the walls
        np.full(20, 0.035),  # seated: stem on the slot bottom, bar on the block top
    ]
    X = _poses(np.zeros_like(ys))
    X[:, 1, 3] = ys
    X[:, 2, 3] = 0.0
    rng = np.random.default_rng(seed)
    noise = [
        pose_from_twist(np.r_[rng.normal(0, np.deg2rad(sigma), 3), rng.normal(0, sigma * 1e-3, 3)])
        for _ in ys
    ]
    return np.arange(len(ys)) / 30.0, np.array([m @ x for m, x in zip(noise, X, strict=True)])


def test_straight_insertion_free_singular_critical_seated():
    from apo.recognition import recognize_frames
    from apo.shapes import t_peg, u_block

    peg, block = t_peg(), u_block()
    t, X = _straight_insertion()
    rec = recognize_frames(peg, block, t, X)
    task = rec.task
    assert len(task.states) >= 3
    assert task.states[0].elements == ()
    assert any(s.singular for s in task.states)
    seated = task.states[-1]
    assert seated.frames[1] == len(t) - 1 and seated.frames[0] <= 43
    assert seated.fig25[2] >= 1 and seated.fig25[5] >= 2
    assert any(tr.critical for tr in task.transitions)
    assert all(tr.direct for tr in task.transitions)
    assert ("push_to", "translation") in {(k.kind, k.space) for k in task.transitions[-1].subskills}
    assert rec.converged[rec.assigned != rec.assigned[0]].all()
    # Observation noise well below the threshold changes nothing in the sub-skills.
    t, Xn = _straight_insertion(sigma=0.3, seed=1)
    noisy = recognize_frames(peg, block, t, Xn).task
    assert noisy.subskill_sequence() == task.subskill_sequence()
    assert [tr.critical for tr in noisy.transitions] == [tr.critical for tr in task.transitions]


def test_a_demonstration_without_contact_is_one_free_state():
    from apo.recognition import recognize_frames

    cube, table = _table_and_cube()
    t = np.linspace(0.0, 1.0, 12)
    X = _poses(np.linspace(0.2, 0.05, 12))
    rec = recognize_frames(cube, table, t, X, threshold=0.002, units="cm", source="air")
    task = rec.task
    assert len(task.states) == 1 and task.transitions == () and task.rejected == ()
    s = task.states[0]
    assert s.frames == (0, 11) and s.times == (0.0, 1.0)
    assert s.fig25 == (3, 0, 0, 3, 0, 0, 0, 0) and s.elements == ()
    assert s.pose_converged and s.pose_frame is not None
    assert task.units == "cm" and task.source == "air" and task.threshold == 0.002
    assert rec.state_of_frame == ["A"] * 12
    assert rec.converged.all() and not rec.repaired.any()
    assert (rec.residual_before == 0).all()
    assert set(rec.timings) >= {"contacts", "segmentation", "analysis", "correction", "total"}


def test_default_threshold_is_scale_aware():
    from apo.recognition import THRESHOLD_FRACTION, default_threshold

    cube, table = _table_and_cube()
    big = box([0.5, 0.5, 0.5])
    assert default_threshold(cube, table) == pytest.approx(THRESHOLD_FRACTION * cube.scale)
    assert default_threshold(big, table) == pytest.approx(THRESHOLD_FRACTION * table.scale)
