"""UR5e kinematics against independent truth: the arm's rigid geometry (product of exponentials), hand-derived
poses, and IK round trips verified by FK."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from cell.errors import PlanningError
from cell.planning.kinematics import UR5E, URKinematics, trapezoid_duration, wrap_angle

D1, A2, A3, D4, D5, D6 = 162.5, -425.0, -392.2, 133.3, 99.7, 99.6


def _poe_fk(q: np.ndarray) -> np.ndarray:
    """Flange pose by the product of exponentials from the arm's zero-pose geometry (not from DH).

    Joint axes at q = 0, read off the UR5e drawing: base axis up; shoulder, elbow and wrist 1 horizontal
    along -y at the shoulder height; wrist 2 pointing down; wrist 3 along -y.
    """
    axes = [
        ((0, 0, 1), (0, 0, 0)),
        ((0, -1, 0), (0, 0, D1)),
        ((0, -1, 0), (A2, 0, D1)),
        ((0, -1, 0), (A2 + A3, 0, D1)),
        ((0, 0, -1), (A2 + A3, -D4, D1)),
        ((0, -1, 0), (A2 + A3, -D4, D1 - D5)),
    ]
    M = np.array([[1, 0, 0, A2 + A3], [0, 0, -1, -(D4 + D6)], [0, 1, 0, D1 - D5], [0, 0, 0, 1.0]])
    T = np.eye(4)
    for qi, (w, p) in zip(q, axes, strict=True):
        w = np.asarray(w, float)
        v = -np.cross(w, p)
        xi = np.zeros((4, 4))
        xi[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
        xi[:3, 3] = v
        T = T @ expm(xi * qi)
    return T @ M


def test_zero_pose_flange_matches_the_arm_dimensions():
    T = UR5E.fk(np.zeros(6))
    np.testing.assert_allclose(T[:3, 3], [A2 + A3, -(D4 + D6), D1 - D5], atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [-817.2, -232.9, 62.8], atol=1e-12)
    # flange z along -y (wrist 3 axis), flange x along base x
    np.testing.assert_allclose(T[:3, :3], [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)


def test_home_pose_matches_planar_geometry():
    """[0, -90, 90, -90, -90, 0] deg: upper arm up, forearm toward -x, flange down."""
    T = UR5E.fk(np.deg2rad([0, -90, 90, -90, -90, 0]))
    np.testing.assert_allclose(T[:3, 3], [A3 - D5, -D4, D1 - A2 - D6], atol=1e-9)
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-12)


def test_fk_equals_product_of_exponentials_on_random_joints():
    rng = np.random.default_rng(1)
    Q = rng.uniform(-2 * np.pi, 2 * np.pi, (50, 6))
    T_batch = UR5E.fk(Q)
    for q, T in zip(Q, T_batch, strict=True):
        np.testing.assert_allclose(T, _poe_fk(q), atol=1e-9)


def test_ik_round_trip_on_thousands_of_random_poses():
    rng = np.random.default_rng(2)
    Q = rng.uniform(-np.pi, np.pi, (3000, 6))
    T = UR5E.fk(Q)
    q, valid, _ = UR5E.ik_all(T)
    assert valid.any(axis=1).all()
    # every returned solution reproduces the pose (independent FK check, not the solver's own tolerance)
    Tq = UR5E.fk(np.where(valid[..., None], q, 0.0))
    pos = np.linalg.norm(Tq[..., :3, 3] - T[:, None, :3, 3], axis=-1)[valid]
    R = np.einsum("nkji,njl->nkil", Tq[..., :3, :3], T[:, :3, :3])[valid]
    ang = np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1))
    assert pos.max() < 1e-6 and ang.max() < 1e-6  # arccos of a rotation this close to I is limited to ~1e-8
    skew = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1)
    assert np.abs(0.5 * np.linalg.norm(skew, axis=-1)).max() < 1e-9
    # the generating joint set is one of the solutions (mod 2 pi)
    diff = np.abs(wrap_angle(np.where(valid[..., None], q, 1e3) - Q[:, None])).max(axis=-1)
    assert (np.nanmin(diff, axis=1) < 1e-7).mean() == 1.0
    assert valid.sum(axis=1).mean() > 6  # generic poses have (up to) 8 branches


def test_ik_nearest_picks_the_reference_branch_and_unwraps_to_it():
    rng = np.random.default_rng(3)
    for _ in range(200):
        q0 = rng.uniform(-1.5 * np.pi, 1.5 * np.pi, 6)
        q = UR5E.ik_nearest(UR5E.fk(q0), q0 + rng.normal(0, 0.01, 6))
        np.testing.assert_allclose(q, q0, atol=1e-7)


def _nearest_in_turn(kin: URKinematics, poses: np.ndarray, q: np.ndarray) -> np.ndarray | str:
    """What the planner did before ik_follow: ik_nearest pose by pose; the error's text at the first
    failure."""
    out = []
    try:
        for T in poses:
            q = kin.ik_nearest(T, q)
            out.append(q)
    except PlanningError as exc:
        return str(exc)
    return np.array(out)


def test_ik_follow_is_ik_nearest_pose_by_pose_to_the_bit():
    """The batched path IK gives the very joints (and the very error) of ik_nearest called pose by pose, on
    lines through the workspace, past the wrist singularity, out of reach, into the joint limits and through a
    pose that is not rigid; the joints are also checked against the poses by FK."""
    rng = np.random.default_rng(14)
    narrow = URKinematics(joint_min_rad=(-np.pi,) * 6, joint_max_rad=(np.pi,) * 6)
    cases = {"ok": 0, "error": 0}
    for trial in range(28):
        kin = (UR5E, narrow)[trial % 2]
        q_a = rng.uniform(-np.pi, np.pi, 6)
        q_b = q_a + rng.normal(0.0, 0.5, 6)
        if trial % 4 == 0:
            q_a[4] = q_b[4] = rng.normal(0.0, 0.01)  # along the wrist singularity (q6 from the reference)
        T_a, T_b = UR5E.fk(q_a), UR5E.fk(q_b)
        if trial % 7 == 0:
            T_b[:3, 3] *= 2.0  # leaves the reach part way
        n = 20
        s = np.linspace(0.0, 1.0, n)[:, None]
        poses = np.tile(np.eye(4), (n, 1, 1))
        poses[:, :3, :3] = UR5E.fk(q_a + s * (q_b - q_a))[:, :3, :3]
        poses[:, :3, 3] = T_a[:3, 3] + s * (T_b[:3, 3] - T_a[:3, 3])
        if trial % 9 == 0:
            poses[15, 0, 0] = 2.0  # not a rigid transform
        expected = _nearest_in_turn(kin, poses, q_a)
        if isinstance(expected, str):
            cases["error"] += 1
            with pytest.raises(PlanningError) as err:
                kin.ik_follow(poses, q_a)
            assert str(err.value) == expected
        else:
            cases["ok"] += 1
            got = kin.ik_follow(poses, q_a)
            assert np.array_equal(got, expected)
            np.testing.assert_allclose(UR5E.fk(got), poses, atol=1e-6)
    assert min(cases.values()) >= 5, cases


def test_reachable_each_is_reachable_pose_by_pose():
    """The batched reachability answers (and reasons) of reachable() called pose by pose: poses of random
    joints, some in the wrist singularity, some moved out of reach or onto the base axis, under wide and
    narrow joint limits."""
    rng = np.random.default_rng(15)
    q = rng.uniform(-np.pi, np.pi, (120, 6))
    q[::5, 4] = rng.normal(0.0, 0.01, 24)  # wrist singular (or nearly)
    poses = UR5E.fk(q)
    poses[1::7, :3, 3] *= 2.5  # out of reach
    poses[2::9, :2, 3] = 0.0  # flange on the base axis
    narrow = URKinematics(joint_min_rad=(-0.5,) + (-np.pi,) * 5, joint_max_rad=(0.5,) + (np.pi,) * 5)
    for kin in (UR5E, narrow):
        expected = [kin.reachable(T) for T in poses]
        assert kin.reachable_each(poses) == expected
        reasons = {why.split(":")[0] for ok, why in expected if not ok}
        assert sum(ok for ok, _ in expected) >= 20 and len(reasons) >= 2, reasons


def test_unreachable_poses_are_refused_with_the_reason():
    far = np.eye(4)
    far[:3, 3] = [1500.0, 0, 300]
    ok, why = UR5E.reachable(far)
    assert not ok and "out of reach" in why
    with pytest.raises(PlanningError, match="out of reach"):
        UR5E.ik_nearest(far, np.zeros(6))
    on_axis = np.diag([1.0, -1.0, -1.0, 1.0])  # flange down, wrist centre on the joint 1 axis
    on_axis[:3, 3] = [0, 0, 400]
    ok, why = UR5E.reachable(on_axis)
    assert not ok and "base axis" in why


def test_wrist_singular_pose_is_reachable_but_flagged():
    q = np.array([0.3, -1.2, 1.0, -0.5, 0.0, 0.7])  # q5 = 0: wrist 1 and wrist 3 axes aligned
    T = UR5E.fk(q)
    q_all, valid, singular = UR5E.ik_all(T, q6_default=0.7)
    own = np.abs(wrap_angle(q_all - q)).max(axis=1) < 1e-7
    assert own.any() and valid[own].all() and singular[own].all()
    # the other shoulder branch is regular, so the pose counts as reachable ...
    assert UR5E.reachable(T) == (True, "ok")
    # ... unless the joint limits keep the arm on the singular branch
    shoulder_right = URKinematics(joint_min_rad=(0.0, -7, -7, -7, -7, -7), joint_max_rad=(1.0, 7, 7, 7, 7, 7))
    ok, why = shoulder_right.reachable(T)
    assert not ok and "wrist singular" in why
    sols = shoulder_right.ik(T, q)
    assert sols.ok and sols.singular
    np.testing.assert_allclose(UR5E.fk(sols.joints), np.broadcast_to(T, (len(sols.joints), 4, 4)), atol=1e-6)


def test_joint_limits_are_respected_and_reported():
    narrow = URKinematics(
        joint_min_rad=(-0.1, -np.pi, -np.pi, -np.pi, -np.pi, -np.pi),
        joint_max_rad=(0.1, np.pi, np.pi, np.pi, np.pi, np.pi),
    )
    q = np.array([1.0, -1.2, 1.0, -1.3, -1.5, 0.2])
    ok, why = narrow.reachable(UR5E.fk(q))
    assert not ok and "joint limits" in why
    sols = UR5E.ik(UR5E.fk(q))
    assert np.all(np.abs(sols.joints) <= 2 * np.pi)


def test_not_a_rigid_transform_is_refused():
    T = np.eye(4)
    T[0, 0] = 2.0
    with pytest.raises(PlanningError, match="rigid"):
        UR5E.ik(T)


@pytest.mark.parametrize("dist, v, a", [(200.0, 100.0, 500.0), (5.0, 100.0, 500.0), (0.0, 1.0, 1.0)])
def test_trapezoid_duration_formula(dist, v, a):
    # textbook: cruise reached when d >= v^2 / a, else triangular apex sqrt(d a)
    expected = dist / v + v / a if dist >= v * v / a else 2 * np.sqrt(dist / a)
    assert trapezoid_duration(dist, v, a) == pytest.approx(expected, rel=1e-12, abs=1e-15)
