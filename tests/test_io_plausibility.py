"""Poses that do not fit the models' size (metres read as millimetres, or the reverse)."""

from __future__ import annotations

import numpy as np
import pytest

from apo.io.plausibility import scale_warnings
from apo.synthetic import add_noise, peg_in_hole_2d


def _scaled(X_EG: np.ndarray, f: float) -> np.ndarray:
    X = np.array(X_EG, dtype=np.float64)
    X[:, :3, 3] *= f
    return X


@pytest.fixture(scope="module")
def demo():
    return peg_in_hole_2d()


@pytest.mark.parametrize("seed", range(4))
def test_consistent_poses_give_no_warning(demo, seed: int) -> None:
    noisy = add_noise(demo, sigma_mm=1.0, sigma_deg=1.0, seed=seed)
    assert scale_warnings(demo.grasped, demo.environment, noisy.X_EG, units="mm") == []


@pytest.mark.parametrize("seed", range(3))
def test_metres_read_as_millimetres_name_metres(demo, seed: int) -> None:
    """Positions 1000 times too small: the motion is tiny for the models; m would fit."""
    rng = np.random.default_rng(seed)
    X = _scaled(add_noise(demo, sigma_mm=0.5, sigma_deg=0.5, seed=seed).X_EG, 1e-3)
    (line,) = scale_warnings(
        demo.grasped, demo.environment, X, units="mm", threshold=float(rng.uniform(1e-3, 5e-3))
    )
    assert "motion spans" in line and "would fit the models in m (--units m)" in line


@pytest.mark.parametrize("seed", range(3))
def test_millimetres_read_as_metres_say_never_within_threshold(demo, seed: int) -> None:
    """Positions 1000 times too large: G never comes near E; mm names the fitting unit."""
    X = _scaled(add_noise(demo, sigma_mm=0.5, sigma_deg=0.5, seed=seed).X_EG, 1e3)
    (line,) = scale_warnings(demo.grasped, demo.environment, X, units="m")
    assert "never comes within the threshold of the environment" in line
    assert "would fit the models in mm (--units mm)" in line
    # read as mm already, nothing smaller is on offer: the factor is named instead
    (line,) = scale_warnings(demo.grasped, demo.environment, X, units="mm")
    assert "no unit of m, cm, mm, in fits" in line and "1000 times too large" in line


def test_models_read_in_the_same_units_say_convert(demo) -> None:
    X = _scaled(demo.X_EG, 1e-3)
    (line,) = scale_warnings(
        demo.grasped, demo.environment, X, units="mm", models_follow_units=True
    )
    assert "convert the pose file" in line


def test_a_single_pose_is_judged_by_reach_only(demo) -> None:
    X = np.asarray(demo.X_EG)[-1:]
    assert scale_warnings(demo.grasped, demo.environment, X, units="mm") == []
    (line,) = scale_warnings(demo.grasped, demo.environment, _scaled(X, 1e3), units="mm")
    assert "never comes within" in line


@pytest.mark.realdata
def test_the_real_demonstration_fits_and_its_rescaled_copies_warn(real_data_dir, tmp_path, capsys):
    from apo.cli import main

    src = (real_data_dir / "peg_in_hole.pose.list").read_text()
    for name in ("peg.step", "hole.step"):
        (tmp_path / name).write_bytes((real_data_dir / name).read_bytes())

    def scaled(f: float) -> str:
        out = []
        for line in src.splitlines():
            t = line.split()
            if len(t) == 8:
                t[1:4] = [repr(float(v) * f) for v in t[1:4]]
                line = " ".join(t)
            out.append(line)
        return "\n".join(out) + "\n"

    for f, expect in ((1.0, None), (1e-3, "would fit the models in m (--units m)")):
        demo = tmp_path / f"x{f:g}.pose.list"
        demo.write_text(scaled(f))
        code = main(
            ["analyze", str(demo), "--out", str(tmp_path / f"o{f:g}"), "--no-plot", "--no-report"]
        )
        err = capsys.readouterr().err
        assert code == 0  # a warning, not an error: see docs/outputs.md
        if expect is None:
            assert "do not fit" not in err
        else:
            assert expect in err and "apo analyze: warning: poses read in mm" in err
