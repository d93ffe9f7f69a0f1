"""Tests of the accuracy metrics and trajectory files ``hybridpgo.metrics``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from tolerances import FLOAT64_IDENTITY

from hybridpgo.errors import FormatError, GraphError
from hybridpgo.geometry import so3
from hybridpgo.metrics import (
    align_rigid,
    evaluate,
    match_by_ids,
    read_ground_truth,
    read_tum,
    write_tum,
)

#: Metrics of exactly equal poses: rounding of angles near 0 (atan2 of ~1e-16) and positions.
EXACT = 1e-9
#: Ours vs evo's (same formulas, different code paths: quaternions, SVD): relative; measured
#: agreement 1e-14 (evo 1.38.1).
EVO_AGREEMENT = 1e-12


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


def trajectory(rng: np.random.Generator, n: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """A wiggly 3D drive: rotations from a random walk, positions 100s of metres apart."""
    rot = Rotation.from_rotvec(np.cumsum(rng.normal(scale=0.1, size=(n, 3)), axis=0)).as_matrix()
    trans = np.cumsum(rng.normal(scale=2.0, size=(n, 3)), axis=0) + np.array([500.0, -300.0, 20.0])
    return rot, trans


def test_identical_poses_have_zero_errors(rng: np.random.Generator) -> None:
    rot, trans = trajectory(rng)
    for align in (False, True):
        m = evaluate(rot, trans, rot, trans, align=align)
        assert m["num_poses"] == 200 and m["aligned"] is align
        assert m["rpe_num_pairs"] == 199
        for key in ("position_rmse_m", "position_max_m", "rotation_error_mean_deg",
                    "rotation_error_max_deg", "heading_error_max_deg", "rpe_translation_rmse_m",
                    "rpe_rotation_rmse_deg", "alignment_rotation_deg"):
            assert m[key] < EXACT, (key, m[key])
        json.dumps(m)  # plain numbers
        assert all(type(v) in (int, float, bool) for v in m.values())


def test_rigidly_moved_copy(rng: np.random.Generator) -> None:
    rot, trans = trajectory(rng)
    r = Rotation.from_rotvec([0.1, -0.2, 0.7]).as_matrix()
    t = np.array([30.0, -4.0, 2.5])
    mrot, mtrans = r @ rot, trans @ r.T + t
    aligned = evaluate(mrot, mtrans, rot, trans, align=True)
    assert aligned["position_rmse_m"] < EXACT * 1e3  # positions ~1e3 m
    assert aligned["rotation_error_max_deg"] < EXACT
    assert aligned["alignment_rotation_deg"] == pytest.approx(math.degrees(so3.angle(r)),
                                                              abs=EXACT)
    raw = evaluate(mrot, mtrans, rot, trans, align=False)
    expected = np.linalg.norm(mtrans - trans, axis=1)
    assert raw["position_rmse_m"] == pytest.approx(np.sqrt(np.mean(expected**2)),
                                                   rel=FLOAT64_IDENTITY)
    assert raw["position_max_m"] == pytest.approx(expected.max(), rel=FLOAT64_IDENTITY)
    # R_gt^T (R R_gt) is conjugate to R: the same angle for every pose.
    angle = math.degrees(float(so3.angle(r)))
    assert raw["rotation_error_mean_deg"] == pytest.approx(angle, abs=EXACT)
    assert raw["rotation_error_max_deg"] == pytest.approx(angle, abs=EXACT)
    assert raw["rotation_error_std_deg"] < EXACT
    # The relative pose error does not see a rigid motion.
    for m in (aligned, raw):
        assert m["rpe_translation_rmse_m"] < EXACT * 1e3
        assert m["rpe_rotation_rmse_deg"] < EXACT


def test_pure_offset_without_alignment_is_the_offset(rng: np.random.Generator) -> None:
    rot, trans = trajectory(rng)
    offset = np.array([3.0, 4.0, 0.0])
    m = evaluate(rot, trans + offset, rot, trans, align=False)
    assert m["position_rmse_m"] == pytest.approx(5.0, rel=FLOAT64_IDENTITY * 1e3)
    assert m["position_mean_m"] == pytest.approx(5.0, rel=FLOAT64_IDENTITY * 1e3)
    assert m["rotation_error_max_deg"] == 0.0 and m["heading_error_max_deg"] == 0.0


def test_rotation_error_of_known_rotations(rng: np.random.Generator) -> None:
    rot, trans = trajectory(rng, n=100)
    axes = rng.normal(size=(100, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    deg = np.where(np.arange(100) < 50, 2.0, 6.0)
    est = rot @ so3.exp(axes * np.radians(deg)[:, None])  # body-frame error of known angle
    m = evaluate(est, trans, rot, trans, align=False)
    assert m["rotation_error_mean_deg"] == pytest.approx(4.0, abs=EXACT)
    assert m["rotation_error_max_deg"] == pytest.approx(6.0, abs=EXACT)
    assert m["rotation_error_rmse_deg"] == pytest.approx(math.sqrt(20.0), abs=EXACT)
    assert m["rotation_error_median_deg"] == pytest.approx(4.0, abs=EXACT)  # mid of 2s and 6s
    assert m["rotation_error_std_deg"] == pytest.approx(2.0, abs=EXACT)  # ddof=0, as evo
    assert m["position_rmse_m"] == 0.0


def planar(yaw: np.ndarray) -> np.ndarray:
    """Rotations about z by ``yaw`` (radians)."""
    return so3.exp(np.outer(yaw, [0.0, 0.0, 1.0]))


def test_heading_error_is_the_yaw_difference(rng: np.random.Generator) -> None:
    n = 60
    yaw = rng.uniform(-np.pi, np.pi, n)
    trans = rng.normal(size=(n, 3))
    deg = np.linspace(-170.0, 170.0, n)  # signed yaw errors, some across +-180
    m = evaluate(planar(yaw + np.radians(deg)), trans, planar(yaw), trans, align=False)
    assert m["heading_error_max_deg"] == pytest.approx(170.0, abs=EXACT * 1e3)
    assert m["heading_error_mean_deg"] == pytest.approx(np.abs(deg).mean(), abs=EXACT * 1e3)
    assert m["heading_error_median_deg"] == pytest.approx(np.median(np.abs(deg)),
                                                          abs=EXACT * 1e3)
    # a pure yaw error is the whole rotation error
    assert m["rotation_error_mean_deg"] == pytest.approx(m["heading_error_mean_deg"],
                                                         abs=EXACT * 1e3)
    # wrap-around: 179 deg against -179 deg is 2 deg
    m = evaluate(planar(np.radians([179.0])), trans[:1], planar(np.radians([-179.0])),
                 trans[:1], align=False)
    assert m["heading_error_max_deg"] == pytest.approx(2.0, abs=EXACT * 1e3)


def test_roll_and_pitch_errors_are_not_heading_errors(rng: np.random.Generator) -> None:
    n = 40
    gt = planar(rng.uniform(-np.pi, np.pi, n))  # a level vehicle
    trans = rng.normal(size=(n, 3))
    for axis in ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]):  # body roll, body pitch of 5 deg
        est = gt @ so3.exp(np.radians(5.0) * np.array(axis))
        m = evaluate(est, trans, gt, trans, align=False)
        assert m["heading_error_max_deg"] < EXACT
        assert m["rotation_error_mean_deg"] == pytest.approx(5.0, abs=EXACT)


def test_statistics_are_numpys(rng: np.random.Generator) -> None:
    """The naive twin of every summary: NumPy on the per-pose position errors."""
    rot, trans = trajectory(rng, n=77)
    est = trans + rng.normal(scale=0.5, size=trans.shape)
    m = evaluate(rot, est, rot, trans, align=False)
    err = np.linalg.norm(est - trans, axis=1)
    expected = {"rmse": np.sqrt(np.mean(err**2)), "mean": err.mean(), "median": np.median(err),
                "std": err.std(), "max": err.max()}
    for stat, value in expected.items():
        assert m[f"position_{stat}_m"] == pytest.approx(value, rel=FLOAT64_IDENTITY)


def test_agrees_with_evo(rng: np.random.Generator) -> None:
    """Every statistic that evo computes too is evo's to (nearly) every digit: APE of the
    translation and of the rotation angle, aligned or not, and the RPE over consecutive poses."""
    evo_metrics = pytest.importorskip("evo.core.metrics")
    from evo.core.trajectory import PoseTrajectory3D

    def traj(rot: np.ndarray, trans: np.ndarray) -> PoseTrajectory3D:
        quat_wxyz = np.roll(so3.matrix_to_quat_xyzw(rot), 1, axis=1)
        return PoseTrajectory3D(positions_xyz=trans, orientations_quat_wxyz=quat_wxyz,
                                timestamps=np.arange(rot.shape[0], dtype=float))

    rot, trans = trajectory(rng, n=150)
    est_rot = rot @ so3.exp(rng.normal(scale=0.05, size=(150, 3)))
    est_trans = trans + rng.normal(scale=0.8, size=trans.shape)
    r = Rotation.from_rotvec([0.0, 0.1, 0.4]).as_matrix()
    est_rot, est_trans = r @ est_rot, est_trans @ r.T + [3.0, 1.0, 0.0]
    pe = evo_metrics.PoseRelation
    for align in (False, True):
        ours = evaluate(est_rot, est_trans, rot, trans, align=align)
        ref, est = traj(rot, trans), traj(est_rot, est_trans)
        if align:
            est.align(ref, correct_scale=False)
        for relation, prefix, unit in ((pe.translation_part, "position", "m"),
                                       (pe.rotation_angle_deg, "rotation_error", "deg")):
            ape = evo_metrics.APE(relation)
            ape.process_data((ref, est))
            for stat in ("rmse", "mean", "median", "std", "max"):
                assert ours[f"{prefix}_{stat}_{unit}"] == pytest.approx(
                    ape.get_statistic(getattr(evo_metrics.StatisticsType, stat)),
                    rel=EVO_AGREEMENT), (align, prefix, stat)
        for relation, key in ((pe.translation_part, "rpe_translation_rmse_m"),
                              (pe.rotation_angle_deg, "rpe_rotation_rmse_deg")):
            rpe = evo_metrics.RPE(relation, delta=1, delta_unit=evo_metrics.Unit.frames,
                                  all_pairs=False)
            rpe.process_data((traj(rot, trans), traj(est_rot, est_trans)))
            assert ours[key] == pytest.approx(
                rpe.get_statistic(evo_metrics.StatisticsType.rmse), rel=EVO_AGREEMENT), key


def test_relative_pose_error_of_one_displaced_pose(rng: np.random.Generator) -> None:
    rot, trans = trajectory(rng, n=50)
    est = trans.copy()
    est[20] += [0.3, 0.0, -0.4]  # |d| = 0.5: pairs (19, 20) and (20, 21) each see 0.5 m
    m = evaluate(rot, est, rot, trans, align=False)
    assert m["rpe_translation_rmse_m"] == pytest.approx(math.sqrt(2 * 0.25 / 49),
                                                        rel=FLOAT64_IDENTITY * 1e3)
    assert m["rpe_rotation_rmse_deg"] == 0.0
    m5 = evaluate(rot, est, rot, trans, align=False, rpe_delta=5)
    assert m5["rpe_num_pairs"] == 45 and m5["rpe_delta"] == 5


def test_align_rigid_recovers_a_transform(rng: np.random.Generator) -> None:
    pts = rng.normal(scale=50.0, size=(30, 3))
    r = Rotation.from_rotvec([2.0, 0.5, -1.0]).as_matrix()  # large: 130 degrees
    t = np.array([1.0, 2.0, 3.0])
    ra, ta = align_rigid(pts, pts @ r.T + t)
    np.testing.assert_allclose(ra, r, atol=FLOAT64_IDENTITY * 1e2)
    np.testing.assert_allclose(ta, t, atol=FLOAT64_IDENTITY * 1e3)
    assert np.linalg.det(ra) == pytest.approx(1.0, abs=FLOAT64_IDENTITY)
    # A mirrored target is fitted by a rotation, never a reflection.
    rm, _ = align_rigid(pts, pts * [1.0, 1.0, -1.0])
    assert np.linalg.det(rm) == pytest.approx(1.0, abs=FLOAT64_IDENTITY)


def test_evaluate_rejects_bad_shapes(rng: np.random.Generator) -> None:
    rot, trans = trajectory(rng, n=10)
    with pytest.raises(ValueError, match="match_by_ids"):
        evaluate(rot[:5], trans[:5], rot, trans, align=False)
    with pytest.raises(ValueError, match=r"\(N, 3, 3\)"):
        evaluate(rot, trans[:, :2], rot, trans, align=False)
    bad = trans.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        evaluate(rot, bad, rot, trans, align=True)


# --------------------------------------------------------------------------- ids
def test_match_by_ids_pairs_permuted_ids() -> None:
    gt_ids = np.array([7, 3, 10, 42, 5])
    est_ids = np.array([42, 5, 7])
    ie, ig = match_by_ids(est_ids, gt_ids)
    np.testing.assert_array_equal(est_ids[ie], gt_ids[ig])
    np.testing.assert_array_equal(ie, [0, 1, 2])


def test_match_by_ids_lists_missing_ids() -> None:
    with pytest.raises(GraphError, match=r"2 of 4 estimated pose\(s\) have no ground truth: "
                                         r"node id\(s\) 8, 99"):
        match_by_ids([1, 8, 2, 99], [1, 2, 3])
    with pytest.raises(GraphError, match=r"and 5 more"):
        match_by_ids(np.arange(100, 115), [1])
    with pytest.raises(GraphError, match="no ground truth"):
        match_by_ids([1], np.zeros(0, np.int64))


def test_match_by_ids_rejects_repeated_ids() -> None:
    with pytest.raises(GraphError, match=r"the estimate repeats node id\(s\) 2"):
        match_by_ids([1, 2, 2], [1, 2])
    with pytest.raises(GraphError, match=r"the ground truth repeats node id\(s\) 1"):
        match_by_ids([1, 2], [1, 1, 2])


# --------------------------------------------------------------------------- files
def test_tum_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    rot, trans = trajectory(rng, n=40)
    ids = np.arange(40) * 3 + 100
    path = tmp_path / "est.tum"
    write_tum(path, rot, trans, timestamps=ids)
    r2, t2, ids2 = read_ground_truth(path)
    np.testing.assert_array_equal(ids2, ids)
    np.testing.assert_allclose(t2, trans, rtol=0, atol=0)  # repr: exact
    np.testing.assert_allclose(r2, rot, atol=FLOAT64_IDENTITY)
    first = path.read_text().splitlines()[0].split()
    assert len(first) == 8 and float(first[0]) == 100.0
    # Default timestamps: the pose index; fractional timestamps give ids 0..N-1.
    write_tum(path, rot, trans)
    assert read_ground_truth(path)[2].tolist() == list(range(40))
    write_tum(path, rot, trans, timestamps=np.arange(40) * 0.1)
    stamps, _, _ = read_tum(path)
    np.testing.assert_array_equal(stamps, np.arange(40) * 0.1)
    assert read_ground_truth(path)[2].tolist() == list(range(40))


def test_tum_reader_errors_name_the_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.tum"
    path.write_text("# t x y z qx qy qz qw\n0 1 2 3 0 0 0 1\n1 1 2 3 0 0 1\n")
    with pytest.raises(FormatError, match=r"bad\.tum:3: a TUM line needs 8 numbers"):
        read_ground_truth(path)
    path.write_text("0 1 2 3 0 0 0 x\n")
    with pytest.raises(FormatError, match=r"bad\.tum:1: not a number"):
        read_tum(path)
    path.write_text("0 1 2 3 0 0 0 0\n")
    with pytest.raises(FormatError, match=r"bad\.tum:1: .*quaternion non-zero"):
        read_tum(path)
    with pytest.raises(FormatError, match="cannot read"):
        read_ground_truth(tmp_path / "missing.tum")


def test_read_ground_truth_of_a_g2o_file(tmp_path: Path) -> None:
    path = tmp_path / "gt.g2o"
    path.write_text("VERTEX_SE3:QUAT 5 1 2 3 0 0 0 1\nVERTEX_SE3:QUAT 9 4 5 6 0 0 1 0\n")
    rot, trans, ids = read_ground_truth(path)
    assert ids.tolist() == [5, 9]
    np.testing.assert_array_equal(trans, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_allclose(rot[1], np.diag([-1.0, -1.0, 1.0]), atol=FLOAT64_IDENTITY)
