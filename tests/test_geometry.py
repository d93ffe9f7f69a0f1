"""SO(3)/SE(3): the Numba kernels, the vectorised NumPy API (so3, se3) and their conventions.

Oracles: scipy's Rotation, the NumPy twins of ``tests/naive.py`` (matrix exponentials, eigenvector
quaternions, 4x4 inverses), central finite differences for every Jacobian
(docs/mathematics.md#jacobians) and exact
group identities.  Angles are drawn in regimes (``tests/strategies.py``) so that each formula switch
of ``_kernels`` is crossed: near 0 (1e-8), near pi (pi - 1e-6) and at the thresholds themselves.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import naive
import numpy as np
import pytest
import ref_kernels as K
import strategies as gs
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from tolerances import CENTRAL_DIFF, CENTRAL_DIFF_STEP, FLOAT64_IDENTITY, ORTHONORMAL

from hybridpgo.geometry import se3, so3
from hybridpgo.geometry._kernels import skew_into

Pose = tuple[np.ndarray, np.ndarray]

IDENTITY: Pose = (np.eye(3), np.zeros(3))
#: Errors of the Jacobian tests stay this far below pi, so that finite differences never wrap.
FD_MAX_ANGLE = math.pi - gs.NORMAL_MARGIN


# --------------------------------------------------------------------------------- helpers
def assert_close(actual: object, expected: object, tol: float, scale: float = 1.0) -> None:
    """|actual - expected| <= tol * scale elementwise (absolute; ``scale`` = size of the data)."""
    np.testing.assert_allclose(actual, expected, rtol=0.0, atol=tol * scale)


def assert_pose_close(actual: Pose, expected: Pose, tol: float, scale: float = 1.0) -> None:
    assert_close(actual[0], expected[0], tol)
    assert_close(actual[1], expected[1], tol, scale)


def assert_log_close(actual: np.ndarray, expected: np.ndarray, tol: float,
                     scale: float = 1.0) -> None:
    """Compare logarithms (rotation vectors, or (rho, phi)); at an angle of pi either sign is right,
    so there compare the angles and the group elements instead."""
    if np.linalg.norm(expected[-3:]) > math.pi - 1e-9:
        assert abs(np.linalg.norm(actual[-3:]) - np.linalg.norm(expected[-3:])) <= tol
        if actual.shape[-1] == 6:
            assert_pose_close(K.se3_exp(actual), K.se3_exp(expected), tol, scale)
        else:
            assert_close(K.so3_exp(actual), K.so3_exp(expected), tol)
        return
    assert_close(actual, expected, tol, scale)


def pose_scale(*poses: Pose) -> float:
    """Size of the translations involved (rounding grows with them)."""
    return 1.0 + sum(float(np.linalg.norm(p[1])) for p in poses)


def inverse(pose: Pose) -> Pose:
    return K.between(pose[0], pose[1], *IDENTITY)


def compose(*poses: Pose) -> Pose:
    out = poses[0]
    for p in poses[1:]:
        out = K.compose(out[0], out[1], p[0], p[1])
    return out


def exp(xi: np.ndarray) -> Pose:
    r, t = K.se3_exp(np.ascontiguousarray(xi))
    return r, t


def log(pose: Pose) -> np.ndarray:
    return np.asarray(K.se3_log(pose[0], pose[1]))


def central_difference(f: Callable[[np.ndarray], np.ndarray], n: int) -> np.ndarray:
    """Jacobian of f at 0 by central differences, column j = (f(h e_j) - f(-h e_j)) / 2h."""
    h = CENTRAL_DIFF_STEP
    cols = []
    for j in range(n):
        d = np.zeros(n)
        d[j] = h
        cols.append((f(d) - f(-d)) / (2.0 * h))
    return np.stack(cols, axis=1)


def wrap_angle(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a) + math.pi) % (2.0 * math.pi) - math.pi


def axes_for(n: int) -> np.ndarray:
    """n fixed unit axes (deterministic tests)."""
    v = np.random.default_rng(12345).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


# ------------------------------------------------------------------------------ SO(3) basics
@settings(deadline=None)
@given(v=gs.translations(), w=gs.translations())
def test_skew_is_the_cross_product(v: np.ndarray, w: np.ndarray) -> None:
    s = np.empty((3, 3))
    skew_into(v[0], v[1], v[2], s)
    assert_close(s, -s.T, 0.0)
    assert_close(s @ w, np.cross(v, w), FLOAT64_IDENTITY, 1.0 + float(v @ v + w @ w))
    assert_close(s, naive.skew(v), 0.0)
    assert_close(so3.hat(v), s, 0.0)


@settings(deadline=None)
@given(phi=gs.rotation_vectors())
def test_so3_exp_matches_scipy_rotvec(phi: np.ndarray) -> None:
    r = K.so3_exp(phi)
    assert_close(r, Rotation.from_rotvec(phi).as_matrix(), FLOAT64_IDENTITY)
    assert_close(r.T @ r, np.eye(3), FLOAT64_IDENTITY)
    assert abs(np.linalg.det(r) - 1.0) < FLOAT64_IDENTITY


@settings(deadline=None)
@given(phi=gs.rotation_vectors())
def test_so3_log_inverts_exp(phi: np.ndarray) -> None:
    """Log(Exp(phi)) = phi for |phi| < pi, in every regime (near 0, near pi, thresholds)."""
    assert_close(K.so3_log(K.so3_exp(phi)), phi, FLOAT64_IDENTITY)
    assert_close(K.so3_log(Rotation.from_rotvec(phi).as_matrix()), phi, FLOAT64_IDENTITY)


@settings(deadline=None)
@given(r=gs.rotations())
def test_so3_exp_inverts_log(r: np.ndarray) -> None:
    phi = K.so3_log(r)
    assert np.linalg.norm(phi) <= math.pi + FLOAT64_IDENTITY
    assert_close(K.so3_exp(phi), r, FLOAT64_IDENTITY)


@settings(deadline=None)
@given(theta=gs.angles("near_pi"), axis=gs.unit_vectors())
def test_so3_log_near_pi_keeps_axis_and_sign(theta: float, axis: np.ndarray) -> None:
    """pi - 1e-6 is not pi: the sign of the axis is determined and must be recovered."""
    r = Rotation.from_rotvec(theta * axis).as_matrix()
    phi = K.so3_log(r)
    assert_close(phi, theta * axis, FLOAT64_IDENTITY)
    assert_close(K.so3_log(r.T), -theta * axis, FLOAT64_IDENTITY)
    assert_close(so3.log(r), theta * axis, FLOAT64_IDENTITY)


@settings(deadline=None)
@given(axis=gs.unit_vectors(), t=gs.translations())
def test_log_at_exactly_pi(axis: np.ndarray, t: np.ndarray) -> None:
    """At pi, Log returns +-pi * axis (both right) and Exp(Log(T)) = T."""
    r = 2.0 * np.outer(axis, axis) - np.eye(3)  # rotation by pi about axis
    phi = K.so3_log(r)
    assert abs(np.linalg.norm(phi) - math.pi) < FLOAT64_IDENTITY
    assert abs(abs(phi @ axis) - math.pi) < FLOAT64_IDENTITY
    assert_close(K.so3_exp(phi), r, FLOAT64_IDENTITY)
    assert_pose_close(exp(log((r, t))), (r, t), FLOAT64_IDENTITY, pose_scale((r, t)))
    assert_close(so3.exp(so3.log(r)), r, FLOAT64_IDENTITY)


@settings(deadline=None)
@given(phi=gs.rotation_vectors(("near_zero", "threshold")).filter(
    lambda p: np.linalg.norm(p) < 1e-3))
def test_small_angles_are_relatively_accurate(phi: np.ndarray) -> None:
    """Below and around SMALL_ANGLE the O(theta) parts are right to *relative* 1e-12.

    An absolute 1e-12 check cannot see a wrong series term at theta ~ 1e-4 (it moves entries by
    ~1e-13), so compare the parts that are of order theta against closed forms relative to theta.
    """
    th = float(np.linalg.norm(phi))
    scale = th  # at theta = 0 this demands exact zeros, which the kernels deliver
    sinc = float(np.sinc(th / math.pi))  # sin(th)/th
    half_sinc = 2.0 * math.sin(0.5 * th) ** 2 / th**2 if th > 0.0 else 0.5
    assert_close(naive.vee(K.so3_exp(phi)), sinc * phi, FLOAT64_IDENTITY, scale)
    assert_close(K.so3_log(K.so3_exp(phi)), phi, FLOAT64_IDENTITY, scale)
    assert_close(K.so3_log(Rotation.from_rotvec(phi).as_matrix()), phi, FLOAT64_IDENTITY, scale)
    assert_close(naive.vee(K.so3_left_jacobian(phi)), half_sinc * phi, FLOAT64_IDENTITY, scale)
    assert_close(naive.vee(K.so3_left_jacobian_inv(phi)), -0.5 * phi, FLOAT64_IDENTITY, scale)
    q = K.matrix_to_quat_xyzw(K.so3_exp(phi))
    half = 0.5 * float(np.sinc(0.5 * th / math.pi))  # sin(th/2)/th
    assert_close(q[:3], half * phi, FLOAT64_IDENTITY, scale)
    xi = np.concatenate([np.ones(3), phi])
    assert_close(log(exp(xi))[3:], phi, FLOAT64_IDENTITY, scale)
    assert_close(so3.log(so3.exp(phi)), phi, FLOAT64_IDENTITY, scale)


@settings(deadline=None)
@given(phi=gs.rotation_vectors())
def test_so3_left_jacobian_matches_central_difference(phi: np.ndarray) -> None:
    """Exp(phi + d) = Exp(J_l(phi) d) Exp(phi) to first order."""
    r0t = K.so3_exp(phi).T

    def f(d: np.ndarray) -> np.ndarray:
        return np.asarray(K.so3_log(K.so3_exp(phi + d) @ r0t))

    assert_close(K.so3_left_jacobian(phi), central_difference(f, 3), CENTRAL_DIFF)


@settings(deadline=None)
@given(phi=gs.rotation_vectors())
def test_so3_left_jacobian_inv_is_the_inverse(phi: np.ndarray) -> None:
    j = K.so3_left_jacobian(phi)
    assert_close(K.so3_left_jacobian_inv(phi) @ j, np.eye(3), FLOAT64_IDENTITY)
    # J_l(phi) = R J_r(phi) = R J_l(-phi): the left/right relation.
    assert_close(j, K.so3_exp(phi) @ K.so3_left_jacobian(-phi), FLOAT64_IDENTITY)


# -------------------------------------------------------------------- quaternions and Euler
@settings(deadline=None)
@given(q=gs.quaternions())
def test_quat_to_matrix_matches_scipy(q: np.ndarray) -> None:
    """Scalar-last (x, y, z, w), any norm: normalized like scipy does."""
    assert_close(K.quat_xyzw_to_matrix(q), Rotation.from_quat(q).as_matrix(), FLOAT64_IDENTITY)


@settings(deadline=None)
@given(r=gs.rotations())
def test_matrix_to_quat_matches_scipy_with_w_nonnegative(r: np.ndarray) -> None:
    q = K.matrix_to_quat_xyzw(r)
    assert q[3] >= 0.0
    assert abs(np.linalg.norm(q) - 1.0) < FLOAT64_IDENTITY
    ref = Rotation.from_matrix(r).as_quat()
    ref = ref if ref @ q >= 0.0 else -ref  # q and -q are one rotation; w = 0 allows both
    assert_close(q, ref, FLOAT64_IDENTITY)
    assert_close(K.quat_xyzw_to_matrix(q), r, FLOAT64_IDENTITY)


@settings(deadline=None)
@given(q=gs.quaternions())
def test_quat_round_trip(q: np.ndarray) -> None:
    unit = q / np.linalg.norm(q)
    back = K.matrix_to_quat_xyzw(K.quat_xyzw_to_matrix(q))
    expected = unit if unit[3] > 0.0 else -unit
    if abs(unit[3]) <= FLOAT64_IDENTITY and back @ expected < 0.0:
        expected = -expected  # w ~ 0: R cannot tell q from -q, both have w >= 0 up to rounding
    assert_close(back, expected, FLOAT64_IDENTITY)


_ROLL_YAW = st.floats(-math.pi, math.pi, allow_nan=False)
_PITCH = st.floats(-math.pi / 2, math.pi / 2, allow_nan=False)
_PITCH_AWAY_FROM_LOCK = st.floats(-math.pi / 2 + 1e-3, math.pi / 2 - 1e-3, allow_nan=False)


@settings(deadline=None)
@given(roll=_ROLL_YAW, pitch=_PITCH, yaw=_ROLL_YAW)
def test_euler_to_matrix_matches_scipy_zyx(roll: float, pitch: float, yaw: float) -> None:
    """R = Rz(yaw) Ry(pitch) Rx(roll) = scipy 'ZYX' (intrinsic) with angles (yaw, pitch, roll)."""
    r = K.euler_rpy_to_matrix(roll, pitch, yaw)
    assert_close(r, Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix(), FLOAT64_IDENTITY)
    assert_close(r, naive.euler_rpy_to_matrix(roll, pitch, yaw), FLOAT64_IDENTITY)


@settings(deadline=None)
@given(roll=_ROLL_YAW, pitch=_PITCH_AWAY_FROM_LOCK, yaw=_ROLL_YAW)
def test_matrix_to_euler_matches_scipy_away_from_gimbal_lock(roll: float, pitch: float,
                                                             yaw: float) -> None:
    r = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
    rpy = K.matrix_to_euler_rpy(r)
    ref = Rotation.from_matrix(r).as_euler("ZYX")[::-1]
    assert_close(wrap_angle(rpy - ref), 0.0, FLOAT64_IDENTITY)
    assert_close(wrap_angle(rpy - np.array([roll, pitch, yaw])), 0.0, FLOAT64_IDENTITY)
    assert_close(wrap_angle(rpy - naive.matrix_to_euler_rpy(r)), 0.0, FLOAT64_IDENTITY)


@settings(deadline=None)
@given(roll=_ROLL_YAW, yaw=_ROLL_YAW, sign=st.sampled_from([-1.0, 1.0]),
       delta=st.one_of(st.just(0.0), st.floats(-16.0, -2.0).map(lambda u: 10.0**u)))
def test_matrix_to_euler_round_trip_near_gimbal_lock(roll: float, yaw: float, sign: float,
                                                     delta: float) -> None:
    """pitch = +-(pi/2 - delta): the angles may trade roll for yaw, but must reproduce R."""
    r = K.euler_rpy_to_matrix(roll, sign * (math.pi / 2 - delta), yaw)
    rpy = K.matrix_to_euler_rpy(r)
    assert -math.pi / 2 <= rpy[1] <= math.pi / 2
    assert np.all(np.abs(rpy[[0, 2]]) <= math.pi)
    assert_close(K.euler_rpy_to_matrix(rpy[0], rpy[1], rpy[2]), r, FLOAT64_IDENTITY)
    assert_close(so3.euler_rpy_to_matrix(so3.matrix_to_euler_rpy(r)), r, FLOAT64_IDENTITY)


@settings(deadline=None)
@given(r=gs.rotations())
def test_matrix_to_euler_round_trip(r: np.ndarray) -> None:
    rpy = K.matrix_to_euler_rpy(r)
    assert -math.pi / 2 <= rpy[1] <= math.pi / 2
    assert_close(K.euler_rpy_to_matrix(rpy[0], rpy[1], rpy[2]), r, FLOAT64_IDENTITY)


def test_planar_rotation_is_pure_yaw() -> None:
    """2D graphs are lifted with roll = pitch = 0 (docs/conventions.md): the yaw comes back
    exactly."""
    for yaw in np.linspace(-math.pi, math.pi, 13):
        rpy = K.matrix_to_euler_rpy(K.euler_rpy_to_matrix(0.0, 0.0, yaw))
        assert rpy[0] == 0.0
        assert rpy[1] == 0.0
        assert abs(wrap_angle(rpy[2] - yaw)) < FLOAT64_IDENTITY


# ----------------------------------------------------------------------------- orthonormalize
@settings(deadline=None)
@given(r=gs.rotations(), e=gs.perturbations(1e-5))
def test_orthonormalize_returns_the_nearest_rotation(r: np.ndarray, e: np.ndarray) -> None:
    """A rotation drifted by up to 1e-5 per entry: orthonormal to 1e-14 and equal to the polar
    factor of the SVD (the nearest rotation in the Frobenius norm)."""
    m = r + e
    out = K.orthonormalize(m)
    assert_close(out.T @ out, np.eye(3), ORTHONORMAL)
    assert abs(np.linalg.det(out) - 1.0) < ORTHONORMAL
    assert_close(out, naive.orthonormalize(m), FLOAT64_IDENTITY)
    # No farther from the input than the rotation it drifted from.
    assert np.linalg.norm(out - m) <= np.linalg.norm(e) + FLOAT64_IDENTITY


@settings(deadline=None)
@given(r=gs.rotations())
def test_orthonormalize_keeps_a_rotation(r: np.ndarray) -> None:
    assert_close(K.orthonormalize(r), r, FLOAT64_IDENTITY)


# --------------------------------------------------------------------------------- SE(3)
@settings(deadline=None)
@given(xi=gs.tangents())
def test_se3_log_inverts_exp(xi: np.ndarray) -> None:
    assert_close(log(exp(xi)), xi, FLOAT64_IDENTITY, 1.0 + float(np.linalg.norm(xi)))


@settings(deadline=None)
@given(pose=gs.poses())
def test_se3_exp_inverts_log(pose: Pose) -> None:
    xi = log(pose)
    assert np.linalg.norm(xi[3:]) <= math.pi + FLOAT64_IDENTITY
    assert_pose_close(exp(xi), pose, FLOAT64_IDENTITY, pose_scale(pose))


@settings(deadline=None)
@given(a=gs.poses(), b=gs.poses(), c=gs.poses())
def test_group_axioms(a: Pose, b: Pose, c: Pose) -> None:
    scale = pose_scale(a, b, c) ** 2
    assert_pose_close(compose(compose(a, b), c), compose(a, compose(b, c)), FLOAT64_IDENTITY, scale)
    assert_pose_close(compose(a, IDENTITY), a, 0.0)
    assert_pose_close(compose(IDENTITY, a), a, 0.0)
    assert_pose_close(compose(a, inverse(a)), IDENTITY, FLOAT64_IDENTITY, scale)
    assert_pose_close(compose(inverse(a), a), IDENTITY, FLOAT64_IDENTITY, scale)
    assert_pose_close(compose(a, K.between(*a, *b)), b, FLOAT64_IDENTITY, scale)
    assert_pose_close(K.between(*a, *b), compose(inverse(a), b), FLOAT64_IDENTITY, scale)


@settings(deadline=None)
@given(pose=gs.poses(), xi=gs.tangents())
def test_adjoint_identity(pose: Pose, xi: np.ndarray) -> None:
    """T Exp(xi) T^-1 = Exp(Ad(T) xi)."""
    lhs = compose(pose, exp(xi), inverse(pose))
    rhs = exp(K.se3_adjoint(*pose) @ xi)
    assert_pose_close(lhs, rhs, FLOAT64_IDENTITY, pose_scale(pose) * (1.0 + np.linalg.norm(xi)))


@settings(deadline=None)
@given(xi=gs.tangents(gs.BELOW_PI_REGIMES))
def test_se3_right_jacobian_inv_matches_central_difference(xi: np.ndarray) -> None:
    """Log(Exp(xi) Exp(d)) = xi + Jr^-1(xi) d + O(d^2)."""
    t0 = exp(xi)
    jac = K.se3_right_jacobian_inv(xi)
    fd = central_difference(lambda d: log(compose(t0, exp(d))), 6)
    assert_close(jac, fd, CENTRAL_DIFF, 1.0 + float(np.abs(jac).max()))


@settings(deadline=None)
@given(xi=gs.tangents(gs.BELOW_PI_REGIMES))
def test_se3_left_jacobian_inv_matches_central_difference(xi: np.ndarray) -> None:
    """Log(Exp(d) Exp(xi)) = xi + Jl^-1(xi) d + O(d^2)."""
    t0 = exp(xi)
    jac = K.se3_left_jacobian_inv(xi)
    fd = central_difference(lambda d: log(compose(exp(d), t0)), 6)
    assert_close(jac, fd, CENTRAL_DIFF, 1.0 + float(np.abs(jac).max()))
    assert_close(K.se3_right_jacobian_inv(xi), K.se3_left_jacobian_inv(-xi), 0.0)


# ------------------------------------------------------ docs/mathematics.md#jacobians: Jacobian of
# the error
def relative_error(z: Pose, xa: Pose, xb: Pose) -> np.ndarray:
    """e = Log(Z^-1 X_a^-1 X_b) (docs/conventions.md)."""
    return np.asarray(K.relative_error(z[0], z[1], *K.between(*xa, *xb)))


@settings(deadline=None)
@given(z=gs.poses(), xa=gs.poses(), xb=gs.poses())
def test_relative_error_jacobians_match_central_difference(z: Pose, xa: Pose, xb: Pose) -> None:
    """X_b <- X_b Exp(d): de/dd = Jr^-1(e);  X_a <- X_a Exp(d): de/dd = -Jr^-1(e) Ad(X_b^-1 X_a).

    Random poses, rotations up to pi: only the error itself stays below pi (no wrap in the FD).
    """
    e0 = relative_error(z, xa, xb)
    assume(np.linalg.norm(e0[3:]) < FD_MAX_ANGLE)
    jr_inv = K.se3_right_jacobian_inv(e0)
    jac_b = jr_inv
    jac_a = -jr_inv @ K.se3_adjoint(*K.between(*xb, *xa))
    fd_b = central_difference(lambda d: relative_error(z, xa, compose(xb, exp(d))), 6)
    fd_a = central_difference(lambda d: relative_error(z, compose(xa, exp(d)), xb), 6)
    assert_close(jac_b, fd_b, CENTRAL_DIFF, 1.0 + float(np.abs(jac_b).max()))
    assert_close(jac_a, fd_a, CENTRAL_DIFF, 1.0 + float(np.abs(jac_a).max()))


@settings(deadline=None, max_examples=50)
@given(z=gs.poses(), root=gs.poses(), a_side=st.lists(gs.poses(), max_size=3),
       b_side=st.lists(gs.poses(), min_size=1, max_size=3))
def test_tree_path_jacobian_matches_central_difference(z: Pose, root: Pose, a_side: list[Pose],
                                                       b_side: list[Pose]) -> None:
    """docs/mathematics.md#jacobians in the tree parametrization: perturbing a local transform T_i
    <- T_i Exp(d)
    on the path a -> root -> b moves a whole subtree; de/dd_i = s_i Jr^-1(e) Ad(X_b^-1 X_i)."""

    def globals_of(locals_: list[Pose]) -> list[Pose]:
        out, x = [], root
        for t in locals_:
            x = compose(x, t)
            out.append(x)
        return out

    def error(a_locals: list[Pose], b_locals: list[Pose]) -> np.ndarray:
        xa = globals_of(a_locals)[-1] if a_locals else root
        return relative_error(z, xa, globals_of(b_locals)[-1])

    e0 = error(a_side, b_side)
    assume(np.linalg.norm(e0[3:]) < FD_MAX_ANGLE)
    jr_inv = K.se3_right_jacobian_inv(e0)
    xb = globals_of(b_side)[-1]
    for sign, side in ((-1.0, a_side), (1.0, b_side)):
        for i, xi_global in enumerate(globals_of(side)):
            jac = sign * jr_inv @ K.se3_adjoint(*K.between(*xb, *xi_global))

            def perturbed(d: np.ndarray, side: list[Pose] = side, i: int = i) -> np.ndarray:
                moved = [*side[:i], compose(side[i], exp(d)), *side[i + 1:]]
                return error(moved, b_side) if side is a_side else error(a_side, moved)

            fd = central_difference(perturbed, 6)
            assert_close(jac, fd, CENTRAL_DIFF, 1.0 + float(np.abs(jac).max()))


# ------------------------------------------------------------------- kernels vs NumPy twins
@settings(deadline=None)
@given(phi=gs.rotation_vectors())
def test_so3_kernels_match_twins(phi: np.ndarray) -> None:
    r = Rotation.from_rotvec(phi).as_matrix()
    assert_close(K.so3_exp(phi), r, FLOAT64_IDENTITY)
    assert_log_close(K.so3_log(r), Rotation.from_matrix(r).as_rotvec(), FLOAT64_IDENTITY)
    assert_close(K.so3_left_jacobian(phi), naive.so3_left_jacobian(phi), FLOAT64_IDENTITY)
    assert_close(K.so3_left_jacobian_inv(phi), naive.so3_left_jacobian_inv(phi), FLOAT64_IDENTITY)
    q = naive.matrix_to_quat_xyzw(r)
    assert_close(K.quat_xyzw_to_matrix(q), naive.quat_xyzw_to_matrix(q), FLOAT64_IDENTITY)
    assert_close(K.matrix_to_quat_xyzw(r), q, FLOAT64_IDENTITY)
    assert_close(K.orthonormalize(r), naive.orthonormalize(r), FLOAT64_IDENTITY)


@settings(deadline=None)
@given(xi=gs.tangents(), pose=gs.poses(), other=gs.poses())
def test_se3_kernels_match_twins(xi: np.ndarray, pose: Pose, other: Pose) -> None:
    scale = 1.0 + float(np.linalg.norm(xi))
    assert_pose_close(exp(xi), naive.se3_exp(xi), FLOAT64_IDENTITY, scale)
    assert_close(K.se3_left_jacobian_inv(xi), naive.se3_left_jacobian_inv(xi), FLOAT64_IDENTITY,
                 scale)
    assert_close(K.se3_right_jacobian_inv(xi), naive.se3_right_jacobian_inv(xi),
                 FLOAT64_IDENTITY, scale)
    scale = pose_scale(pose, other)
    assert_log_close(log(pose), naive.se3_log(*pose), FLOAT64_IDENTITY, scale)
    assert_close(K.se3_adjoint(*pose), naive.se3_adjoint(*pose), FLOAT64_IDENTITY, scale)
    assert_pose_close(compose(pose, other), naive.compose(*pose, *other), FLOAT64_IDENTITY, scale)
    assert_pose_close(K.between(*pose, *other), naive.between(*pose, *other), FLOAT64_IDENTITY,
                      scale)
    rab = K.between(*pose, *other)
    assert_log_close(K.relative_error(*xi_pose(xi), *rab), naive.relative_error(*xi_pose(xi), *rab),
                     FLOAT64_IDENTITY, scale**2)


def xi_pose(xi: np.ndarray) -> Pose:
    """A measurement Z built from a tangent (covers near-0 and near-pi measurements)."""
    return naive.se3_exp(xi)


@pytest.mark.parametrize("threshold", [K.SMALL_ANGLE, K.Q_SERIES_ANGLE, math.pi - K.NEAR_PI],
                         ids=["SMALL_ANGLE", "Q_SERIES_ANGLE", "pi-NEAR_PI"])
@pytest.mark.parametrize("side", [1.0 - 1e-9, 1.0 + 1e-9], ids=["below", "above"])
def test_formula_switches_are_seamless(threshold: float, side: float) -> None:
    """Just below and just above every switch, every kernel agrees with its twin."""
    rho = np.array([3.0, -7.0, 5.0])
    for axis in axes_for(8):
        phi = threshold * side * axis
        xi = np.concatenate([rho, phi])
        r = Rotation.from_rotvec(phi).as_matrix()
        assert_close(K.so3_exp(phi), r, FLOAT64_IDENTITY)
        assert_close(K.so3_log(r), phi, FLOAT64_IDENTITY)
        assert_close(K.so3_left_jacobian(phi), naive.so3_left_jacobian(phi), FLOAT64_IDENTITY)
        assert_close(K.so3_left_jacobian_inv(phi), naive.so3_left_jacobian_inv(phi),
                     FLOAT64_IDENTITY)
        assert_pose_close(exp(xi), naive.se3_exp(xi), FLOAT64_IDENTITY, 10.0)
        assert_close(K.se3_log(*naive.se3_exp(xi)), xi, FLOAT64_IDENTITY, 10.0)
        assert_close(K.se3_left_jacobian_inv(xi), naive.se3_left_jacobian_inv(xi),
                     FLOAT64_IDENTITY, 10.0)


# ------------------------------------------------------------- vectorised API (so3, se3)
@settings(deadline=None)
@given(phis=st.lists(gs.rotation_vectors(), min_size=1, max_size=6),
       quats=st.lists(gs.quaternions(), min_size=1, max_size=6))
def test_so3_vectorized_matches_kernels(phis: list[np.ndarray], quats: list[np.ndarray]) -> None:
    phi = np.stack(phis)
    r = so3.exp(phi)
    rq = so3.quat_xyzw_to_matrix(np.stack(quats))
    for i, p in enumerate(phis):
        assert_close(r[i], K.so3_exp(p), FLOAT64_IDENTITY)
        assert_close(so3.left_jacobian(phi)[i], K.so3_left_jacobian(p), FLOAT64_IDENTITY)
        assert_close(so3.left_jacobian_inv(phi)[i], K.so3_left_jacobian_inv(p), FLOAT64_IDENTITY)
    for rot in (r, rq):
        logs, quat, rpy = so3.log(rot), so3.matrix_to_quat_xyzw(rot), so3.matrix_to_euler_rpy(rot)
        for i in range(rot.shape[0]):
            assert_log_close(logs[i], K.so3_log(rot[i]), FLOAT64_IDENTITY)
            want = K.matrix_to_quat_xyzw(rot[i])
            if abs(want[3]) <= FLOAT64_IDENTITY and quat[i] @ want < 0.0:
                # a half turn: q and -q are the same rotation and both have w = 0 (>= 0); the
                # two take the largest diagonal entry's branch on ties differently
                want = -want
            assert_close(quat[i], want, FLOAT64_IDENTITY)
            assert_close(wrap_angle(rpy[i] - K.matrix_to_euler_rpy(rot[i])), 0.0, FLOAT64_IDENTITY)
            assert abs(so3.angle(rot)[i] - np.linalg.norm(K.so3_log(rot[i]))) < FLOAT64_IDENTITY
        assert_close(so3.euler_rpy_to_matrix(rpy), rot, FLOAT64_IDENTITY)
        assert_close(so3.quat_xyzw_to_matrix(quat), rot, FLOAT64_IDENTITY)
    for i, q in enumerate(quats):
        assert_close(rq[i], K.quat_xyzw_to_matrix(q), FLOAT64_IDENTITY)
    assert_close(so3.vee(so3.hat(phi)), phi, 0.0)
    assert_close(so3.compose(r, so3.inverse(r)), np.broadcast_to(np.eye(3), r.shape),
                 FLOAT64_IDENTITY)


@settings(deadline=None)
@given(xis=st.lists(gs.tangents(), min_size=1, max_size=6), data=st.data())
def test_se3_vectorized_matches_kernels(xis: list[np.ndarray], data: st.DataObject) -> None:
    n = len(xis)
    others = data.draw(st.lists(gs.poses(), min_size=n, max_size=n))
    xi = np.stack(xis)
    r, t = se3.exp(xi)
    ro = np.stack([p[0] for p in others])
    to = np.stack([p[1] for p in others])
    logs = se3.log(r, t)
    rc, tc = se3.compose(r, t, ro, to)
    rb, tb = se3.between(r, t, ro, to)
    ri, ti = se3.inverse(r, t)
    ad = se3.adjoint(ro, to)
    for i in range(n):
        scale = pose_scale(others[i]) * (1.0 + np.linalg.norm(xis[i]))
        assert_pose_close((r[i], t[i]), exp(xis[i]), FLOAT64_IDENTITY, scale)
        assert_log_close(logs[i], log((r[i], t[i])), FLOAT64_IDENTITY, scale)
        assert_pose_close((rc[i], tc[i]), compose((r[i], t[i]), others[i]), FLOAT64_IDENTITY,
                          scale)
        assert_pose_close((rb[i], tb[i]), K.between(r[i], t[i], *others[i]), FLOAT64_IDENTITY,
                          scale)
        assert_pose_close((ri[i], ti[i]), inverse((r[i], t[i])), FLOAT64_IDENTITY, scale)
        assert_close(ad[i], K.se3_adjoint(*others[i]), FLOAT64_IDENTITY, scale)
    assert_pose_close(se3.from_matrix(se3.to_matrix(r, t)), (r, t), 0.0)
    m = se3.to_matrix(r, t) @ se3.to_matrix(ro, to)
    assert_pose_close(se3.from_matrix(m), (rc, tc), FLOAT64_IDENTITY, 100.0)


def test_vectorized_shapes_and_broadcasting() -> None:
    rng = np.random.default_rng(0)
    phi = rng.normal(size=(2, 5, 3))
    r = so3.exp(phi)
    assert r.shape == (2, 5, 3, 3)
    assert so3.log(r).shape == (2, 5, 3)
    assert so3.matrix_to_quat_xyzw(r).shape == (2, 5, 4)
    assert so3.matrix_to_euler_rpy(r).shape == (2, 5, 3)
    assert so3.exp(phi[0, 0]).shape == (3, 3)
    assert so3.log(np.zeros((0, 3, 3))).shape == (0, 3)
    assert se3.log(np.zeros((0, 3, 3)), np.zeros((0, 3))).shape == (0, 6)
    # One pose composed with a stack broadcasts.
    xi = rng.normal(size=(4, 6))
    r4, t4 = se3.exp(xi)
    rc, tc = se3.compose(r4[0], t4[0], r4, t4)
    assert rc.shape == (4, 3, 3)
    assert tc.shape == (4, 3)
    for i in range(4):
        assert_pose_close((rc[i], tc[i]), compose((r4[0], t4[0]), (r4[i], t4[i])),
                          FLOAT64_IDENTITY, 10.0)
    assert se3.to_matrix(r4, t4[0]).shape == (4, 4, 4)
    assert se3.log(r4[0], t4).shape == (4, 6)


def test_vectorized_matches_scipy_on_a_batch() -> None:
    rot = Rotation.random(200, random_state=1)
    r = rot.as_matrix()
    quat = so3.matrix_to_quat_xyzw(r)
    ref = rot.as_quat()
    ref = np.where(np.sum(ref * quat, axis=1, keepdims=True) < 0.0, -ref, ref)
    assert np.all(quat[:, 3] >= 0.0)
    assert_close(quat, ref, FLOAT64_IDENTITY)
    assert_close(so3.log(r), rot.as_rotvec(), FLOAT64_IDENTITY)
    assert_close(so3.exp(rot.as_rotvec()), r, FLOAT64_IDENTITY)
    ypr = rot.as_euler("ZYX")
    assert_close(so3.euler_rpy_to_matrix(ypr[:, ::-1]), r, FLOAT64_IDENTITY)
    assert_close(wrap_angle(so3.matrix_to_euler_rpy(r) - ypr[:, ::-1]), 0.0, FLOAT64_IDENTITY)
    assert_close(so3.angle(r), rot.magnitude(), FLOAT64_IDENTITY)
    noisy = r + 1e-3 * np.random.default_rng(2).normal(size=r.shape)
    fixed = so3.orthonormalize(noisy)
    assert_close(fixed @ np.swapaxes(fixed, 1, 2), np.broadcast_to(np.eye(3), r.shape),
                 ORTHONORMAL)
    for i in range(0, 200, 20):
        assert_close(fixed[i], naive.orthonormalize(noisy[i]), FLOAT64_IDENTITY)


@pytest.mark.parametrize(("fn", "arg"), [
    (so3.exp, np.zeros((2, 4))),
    (so3.log, np.zeros((3, 4))),
    (so3.quat_xyzw_to_matrix, np.zeros(3)),
    (so3.quat_xyzw_to_matrix, np.zeros(4)),
    (so3.matrix_to_euler_rpy, np.zeros(3)),
    (se3.exp, np.zeros(3)),
    (se3.from_matrix, np.zeros((3, 3))),
])
def test_vectorized_rejects_bad_input(fn: Callable[[np.ndarray], object], arg: np.ndarray) -> None:
    with pytest.raises(ValueError, match=r"shape|norm"):
        fn(arg)
