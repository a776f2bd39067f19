"""The numpy-only fast paths of issue 9 (whole-process speed) give scipy's / json's results."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components as scipy_components
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from apo.geometry import _close_pairs, connected_components
from apo.outputs import json_text
from apo.spatial import quaternion_from_matrix, quaternions_from_matrices


@pytest.mark.parametrize("noise", [0.0, 1e-13, 1e-9, 1e-4])
def test_quaternions_equal_scipy_bit_for_bit(noise: float) -> None:
    rng = np.random.default_rng(7)
    R = Rotation.random(5000, random_state=3).as_matrix()
    R = R + rng.normal(scale=noise, size=R.shape)  # not quite orthogonal: scipy's SVD branch
    special = np.array([np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]),
                        np.diag([-1.0, -1, 1])])  # fmt: skip
    for M in (R, special):
        xyzw = Rotation.from_matrix(M).as_quat()
        want = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
        want[want[:, 0] < 0] *= -1.0
        assert np.array_equal(quaternions_from_matrices(M), want)
    assert np.array_equal(quaternion_from_matrix(R[0]), quaternions_from_matrices(R[:1])[0])
    assert quaternions_from_matrices(np.zeros((0, 3, 3))).shape == (0, 4)


def test_connected_components_number_like_scipy() -> None:
    rng = np.random.default_rng(1)
    for _ in range(200):
        n = int(rng.integers(1, 400))
        m = int(rng.integers(0, 2 * n))
        a, b = rng.integers(0, n, m), rng.integers(0, n, m)
        g = coo_matrix((np.ones(m), (a, b)), shape=(n, n))
        k, labels = connected_components(n, a, b)
        for directed, conn in ((False, "weak"), (True, "weak")):
            k2, l2 = scipy_components(g, directed=directed, connection=conn)
            assert k == k2 and np.array_equal(labels, l2)


@pytest.mark.parametrize("n", [1, 50, 1500, 2500])
def test_close_pairs_are_the_kd_tree_pairs(n: int) -> None:
    V = np.random.default_rng(n).random((n, 3))
    d = 0.6 / max(n, 1) ** (1 / 3)
    want = cKDTree(V).query_pairs(d, output_type="ndarray")
    want = want[np.lexsort((want[:, 1], want[:, 0]))] if len(want) else want.reshape(0, 2)
    got = _close_pairs(V, d)
    assert np.array_equal(got.reshape(-1, 2), want.reshape(-1, 2))


def test_json_text_reads_back_as_json_dumps() -> None:
    rng = np.random.default_rng(0)

    def value(depth: int) -> object:
        k = int(rng.integers(0, 7 if depth < 5 else 4))
        if k == 0:
            return {f"k{i}\u00e9<": value(depth + 1) for i in range(int(rng.integers(0, 4)))}
        if k == 1:
            return [value(depth + 1) for _ in range(int(rng.integers(0, 4)))]
        return [None, True, 1.5e-17, -3, 's\n"x'][k - 2] if k < 7 else 0

    for _ in range(300):
        doc = {"a": value(0), "b": [value(0), value(0)]}
        for depth in (0, 1, 2, 3, 9):
            text = json_text(doc, depth=depth)
            assert text.endswith("\n") and json.loads(text) == json.loads(json.dumps(doc))
    # layout: json.dumps(indent=2), except that arrays/objects of scalars take one line
    doc = {"a": [1, {"b": [2, 3]}], "c": {}, "d": [[1, [2]]]}
    want = '{\n  "a": [\n    1,\n    {\n      "b": [2, 3]\n    }\n  ],\n  "c": {},\n'
    want += '  "d": [\n    [\n      1,\n      [2]\n    ]\n  ]\n}\n'
    assert json_text(doc, depth=99) == want


def test_apo_analyze_imports_no_scipy_or_plotting(tmp_path) -> None:
    """A pose file on small models, their triangles cached: numpy only, no scipy or plotting."""
    import os

    from apo.cli.demo import _write_stl
    from apo.io.poses import write_pose_csv
    from apo.synthetic import peg_in_hole_2d

    demo = peg_in_hole_2d()
    _write_stl(demo.grasped, tmp_path / "g.stl", 1000.0)
    _write_stl(demo.environment, tmp_path / "e.stl", 1000.0)
    csv = write_pose_csv(tmp_path / "in.csv", demo.times, demo.X_EG, units="mm")
    code = (
        "import sys, runpy; sys.argv = ['apo', 'analyze', {!r}, '--out', {!r}, '--grasped', "
        "{!r}, '--environment', {!r}]\n"
        "try:\n    runpy.run_module('apo.cli', run_name='__main__')\n"
        "except SystemExit as e:\n    assert not e.code, e.code\n"
        "heavy = ('scipy', 'matplotlib', 'plotly', 'trimesh', 'networkx', 'highspy', 'tqdm')\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in heavy))\n"
    ).format(str(csv), str(tmp_path / "out"), str(tmp_path / "g.stl"), str(tmp_path / "e.stl"))
    env = {**os.environ, "APO_CACHE_DIR": str(tmp_path / "cache")}
    for _ in range(2):  # the first run reads the STL files (trimesh) and fills the cache
        out = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env
        ).stdout
    loaded = out.strip().splitlines()[-1]
    # HiGHS (a small extension) is allowed: the DOF analysis may need an LP
    assert all(m.split(".")[0] == "highspy" for m in eval(loaded)), loaded
    assert (tmp_path / "out" / "report.html").exists() and (tmp_path / "out" / "task.json").exists()


def test_repeated_poses_are_searched_once_with_the_same_states() -> None:
    """Exact repeats reuse the state found at the first frame; the result is unchanged."""
    from apo.recognition.contacts import distinct_poses, observed_states
    from apo.recognition.pipeline import make_scene
    from apo.recognition.types import SegmentationCosts
    from apo.synthetic import add_noise, peg_in_hole_2d

    demo = add_noise(peg_in_hole_2d(), sigma_mm=0.5, sigma_deg=0.5, seed=2)
    X = np.concatenate([demo.X_EG, demo.X_EG[::3], demo.X_EG])
    X[-1, 0, 3] += 1e-12  # one near-repeat: searched again
    first, inverse = distinct_poses(X)
    n = len(demo.X_EG)
    assert len(first) == n + 1 and np.array_equal(X[first[inverse]], X)
    scene = make_scene(demo.grasped, demo.environment, X, 0.004, SegmentationCosts())
    states = observed_states(scene)
    every = scene.finder.find_batch(X)
    assert [s.key for s in states] == [s.key for s in every]
    assert states[n] is states[0] and states[-1] is not states[n - 1]


def test_correction_of_repeated_poses_is_that_of_each_pose() -> None:
    """correct_by_label corrects a repeated pose once; each frame gets its own result."""
    from apo.recognition.contacts import observed_states
    from apo.recognition.correction import correct_by_label, correct_poses
    from apo.recognition.pipeline import make_scene
    from apo.recognition.types import SegmentationCosts
    from apo.synthetic import add_noise, peg_in_hole_2d

    demo = add_noise(peg_in_hole_2d(), sigma_mm=0.5, sigma_deg=0.5, seed=4)
    X = np.concatenate([demo.X_EG, demo.X_EG[::-2]])
    scene = make_scene(demo.grasped, demo.environment, X, 0.004, SegmentationCosts())
    states = observed_states(scene)
    distinct = list({id(s): s for s in states}.values())
    label = {id(s): i for i, s in enumerate(distinct)}
    labels = np.array([label[id(s)] for s in states])
    got = correct_by_label(demo.grasped, demo.environment, X, distinct, labels, 0.004)
    for t in range(0, len(X), 7):
        if states[t].elements:
            want = correct_poses(demo.grasped, demo.environment, X[t : t + 1],
                                 states[t].elements, threshold=0.004)  # fmt: skip
            assert np.array_equal(got[0][t], want[0][0]) and got[1][t] == want[1][0]
            assert got[2][t] == want[2][0] and got[3][t] == want[3][0]
