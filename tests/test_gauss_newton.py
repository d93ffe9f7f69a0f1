"""Tests of the exact solver (docs/mathematics.md#exact-solver): Jacobians, normal equations, GN/LM
optima."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from ref_kernels import assemble_in_order, relative_error, se3_exp
from tolerances import (
    CENTRAL_DIFF,
    CENTRAL_DIFF_STEP,
    FLOAT64_IDENTITY,
    SPARSE_VS_DENSE_GN,
    TWIN_JACOBIAN,
)

from hybridpgo import _cost
from hybridpgo.energy import energy
from hybridpgo.errors import GraphError, SolverError
from hybridpgo.graph import PoseGraph
from hybridpgo.io import bundled_path, read_graph
from hybridpgo.linalg import cholmod_available
from hybridpgo.solvers import _gn_kernels, _normal, gauss_newton
from hybridpgo.solvers.config import GaussNewtonConfig
from hybridpgo.solvers.gauss_newton import (
    ExactSolver,
    default_fixed_nodes,
    gn_step,
    normal_equations,
    solve_exact,
)
from hybridpgo.solvers.result import Status

#: Two converged optima (GN vs LM, relabelled graphs): relative energy agreement.
OPTIMUM_RTOL = 1e-9
#: At a converged optimum: |g|_inf relative to the gradient scale sum_c |J_c^T Omega_c| |e_c|.
STATIONARY = 1e-7


# --------------------------------------------------------------------------- fixtures
def _rotation(rng: np.random.Generator, max_angle: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis *= rng.uniform(0.0, max_angle) / np.linalg.norm(axis)
    return se3_exp(np.r_[0.0, 0.0, 0.0, axis])[0]


def _spd(rng: np.random.Generator, d: int, scale: float = 1.0) -> np.ndarray:
    a = rng.normal(size=(d, d))
    return scale * (a @ a.T + d * np.eye(d))


def random_graph(rng: np.random.Generator, n: int = 12, extra: int = 10, noise: float = 0.1,
                 init_noise: float = 0.2, num_gps: int = 0, fixed: tuple[int, ...] = (),
                 max_angle: float = np.pi) -> PoseGraph:
    """Connected random graph: odometry chain plus random loop edges, large absolute rotations.

    Measurements are the true relative poses perturbed by ``noise`` (so errors stay well inside
    the injectivity radius of Log); the initial estimate is the truth perturbed by ``init_noise``.
    """
    rot = np.array([_rotation(rng, max_angle) for _ in range(n)])
    trans = rng.normal(scale=3.0, size=(n, 3))
    edges = [(i, i + 1) for i in range(n - 1)]
    while len(edges) < n - 1 + extra:
        a, b = rng.choice(n, 2, replace=False)
        edges.append((int(a), int(b)))
    en = np.array(edges, dtype=np.int32)
    er = np.empty((len(en), 3, 3))
    et = np.empty((len(en), 3))
    for c, (a, b) in enumerate(en):
        dr, dt = se3_exp(rng.normal(scale=noise, size=6))
        rz = rot[a].T @ rot[b]
        tz = rot[a].T @ (trans[b] - trans[a])
        er[c] = rz @ dr
        et[c] = rz @ dt + tz
    info = np.array([_spd(rng, 6) for _ in en])
    init_r = np.array([r @ se3_exp(rng.normal(scale=init_noise, size=6))[0] for r in rot])
    init_t = trans + rng.normal(scale=init_noise, size=trans.shape)
    kw: dict[str, np.ndarray] = {}
    if num_gps:
        gn = rng.choice(n, num_gps, replace=False).astype(np.int32)
        kw = {"gps_nodes": gn,
              "gps_positions": trans[gn] + rng.normal(scale=noise, size=(num_gps, 3)),
              "gps_information": np.array([_spd(rng, 3) for _ in gn])}
    return PoseGraph(node_ids=np.arange(n) * 10 + 3, rotations=init_r, translations=init_t,
                     edge_nodes=en, edge_rotations=er, edge_translations=et,
                     edge_information=info, fixed_nodes=np.array(fixed, np.int32), **kw)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


def _perturb(rot: np.ndarray, trans: np.ndarray, i: int, xi: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    r = rot.copy()
    t = trans.copy()
    dr, dt = se3_exp(xi)
    r[i] = rot[i] @ dr
    t[i] = trans[i] + rot[i] @ dt
    return r, t


def _errors(graph: PoseGraph, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """Errors of every relative edge, computed as the energy kernel does."""
    out = np.empty((graph.num_edges, 6))
    for c, (a, b) in enumerate(graph.edge_nodes):
        out[c] = relative_error(graph.edge_rotations[c], graph.edge_translations[c],
                                rot[a].T @ rot[b], rot[a].T @ (trans[b] - trans[a]))
    return out


def _whitened_residuals(graph: PoseGraph, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """Stacked L_c^T e_c (Omega_c = L_c L_c^T), so that E = |r|^2."""
    res = []
    for c, e in enumerate(_errors(graph, rot, trans)):
        res.append(np.linalg.cholesky(graph.edge_information[c]).T @ e)
    for c, n in enumerate(graph.gps_nodes):
        e = trans[n] - graph.gps_positions[c]
        res.append(np.linalg.cholesky(graph.gps_information[c]).T @ e)
    return np.concatenate(res)


def dense_normal_equations(graph: PoseGraph, rot: np.ndarray, trans: np.ndarray,
                           free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dense reference: J of the whitened residuals by central differences; (J^T J, J^T r)."""
    r0 = _whitened_residuals(graph, rot, trans)
    jac = np.empty((r0.shape[0], 6 * free.shape[0]))
    for k, i in enumerate(free):
        for d in range(6):
            xi = np.zeros(6)
            xi[d] = CENTRAL_DIFF_STEP
            rp = _whitened_residuals(graph, *_perturb(rot, trans, i, xi))
            rm = _whitened_residuals(graph, *_perturb(rot, trans, i, -xi))
            jac[:, 6 * k + d] = (rp - rm) / (2 * CENTRAL_DIFF_STEP)
    return jac.T @ jac, jac.T @ r0


def relabelled(graph: PoseGraph, rng: np.random.Generator) -> PoseGraph:
    """Same problem with permuted nodes, shuffled edges and some edges reversed.

    A reversed edge measures ``Z^-1``; its error is ``Log(Z E^-1 Z^-1) = -Ad(Z) e``, so the
    information ``Ad(Z)^-T Omega Ad(Z)^-1`` gives exactly the same energy.
    """
    n = graph.num_nodes
    perm = rng.permutation(n)  # new index of old node i: perm[i]
    inv = np.argsort(perm)
    order = rng.permutation(graph.num_edges)
    en = perm[graph.edge_nodes[order]].astype(np.int32)
    er = graph.edge_rotations[order].copy()
    et = graph.edge_translations[order].copy()
    info = graph.edge_information[order].copy()
    for c in np.flatnonzero(rng.uniform(size=len(order)) < 0.5):
        r, t = er[c], et[c]
        ad = np.zeros((6, 6))
        ad[:3, :3] = r
        ad[3:, 3:] = r
        ad[:3, 3:] = _skew(t) @ r
        adi = np.linalg.inv(ad)
        info[c] = adi.T @ info[c] @ adi
        info[c] = 0.5 * (info[c] + info[c].T)
        er[c], et[c] = r.T, -(r.T @ t)
        en[c] = en[c, ::-1]
    gps = {}
    if graph.num_gps:
        gps = {"gps_nodes": perm[graph.gps_nodes], "gps_positions": graph.gps_positions,
               "gps_information": graph.gps_information}
    return PoseGraph(node_ids=graph.node_ids[inv], rotations=graph.rotations[inv],
                     translations=graph.translations[inv], edge_nodes=en, edge_rotations=er,
                     edge_translations=et, edge_information=info, **gps)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _gradient_scale(graph: PoseGraph, rot: np.ndarray, trans: np.ndarray) -> float:
    """sum_c |J_c| |Omega_c| |e_c|: the size of g's terms, against which g ~ 0 is judged."""
    m = graph.num_edges
    err = np.empty((m, 6))
    ja = np.empty((m, 6, 6))
    jb = np.empty((m, 6, 6))
    _gn_kernels.edge_jacobians(rot, trans, graph.edge_nodes, graph.edge_rotations,
                               graph.edge_translations, err, ja, jb)
    scale = 0.0
    for c in range(m):
        oe = np.abs(graph.edge_information[c] @ err[c]).sum()
        scale += (np.abs(ja[c]).max() + np.abs(jb[c]).max()) * oe
    for c, n in enumerate(graph.gps_nodes):
        scale += np.abs(graph.gps_information[c] @ (trans[n] - graph.gps_positions[c])).sum()
    return scale


# --------------------------------------------------------------------------- kernels vs geometry
def _error_pose(rng: np.random.Generator, regime: str) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a relative error Z^-1 X_a^-1 X_b in one of three angle regimes."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = {"normal": rng.uniform(0.1, 3.0), "near_zero": 10 ** rng.uniform(-9, -4),
             "near_pi": np.pi - 10 ** rng.uniform(-7, -2.5), "mid_series": rng.uniform(1e-4, 0.1)
             }[regime]
    r, _ = se3_exp(np.r_[0.0, 0.0, 0.0, angle * axis])
    return r, rng.normal(scale=2.0, size=3)


@pytest.mark.parametrize("regime", ["normal", "near_zero", "near_pi", "mid_series"])
def test_allocation_free_kernels_match_geometry_kernels(regime: str) -> None:
    """The solver's inner kernels are twins of the reference kernels
    (docs/mathematics.md#jacobians)."""
    from ref_kernels import se3_adjoint, se3_right_jacobian_inv

    rng = np.random.default_rng(7)
    for _ in range(20):
        ra = _rotation(rng, np.pi)
        ta = rng.normal(size=3)
        rz = _rotation(rng, np.pi)
        tz = rng.normal(size=3)
        re, te = _error_pose(rng, regime)
        rb = ra @ rz @ re  # so that Z^-1 X_a^-1 X_b = (re, te)
        tb = ta + ra @ (tz + rz @ te)
        e = np.empty(6)
        ja = np.empty((6, 6))
        jb = np.empty((6, 6))
        _gn_kernels._edge_linearization(np.stack([ra, rb]), np.stack([ta, tb]), rz[None],
                                        tz[None], 0, 1, 0, e, ja, jb)
        ref_e = relative_error(rz, tz, ra.T @ rb, ra.T @ (tb - ta))
        np.testing.assert_allclose(e, ref_e, rtol=0, atol=FLOAT64_IDENTITY * 10)
        jri = se3_right_jacobian_inv(ref_e)
        rba = rb.T @ ra
        tba = rb.T @ (ta - tb)
        np.testing.assert_allclose(jb, jri, rtol=0, atol=FLOAT64_IDENTITY * np.abs(jri).max())
        ref_a = -jri @ se3_adjoint(rba, tba)
        np.testing.assert_allclose(ja, ref_a, rtol=0, atol=FLOAT64_IDENTITY * np.abs(ref_a).max())
        # the block the assembly leaves out is 0 in the independent formulas too
        assert np.all(jri[3:, :3] == 0.0) and np.all(ref_a[3:, :3] == 0.0)


def test_total_energy_kernel_matches_energy_module(rng: np.random.Generator) -> None:
    g = random_graph(rng, n=15, extra=12, noise=0.5, init_noise=0.5, num_gps=4)
    ours = _cost.total_energy(np.array(g.rotations), np.array(g.translations),
                                    g.edge_nodes, g.edge_rotations, g.edge_translations,
                                    g.edge_information, g.gps_nodes, g.gps_positions,
                                    g.gps_information)
    assert ours == pytest.approx(energy(g), rel=FLOAT64_IDENTITY)


# --------------------------------------------------------------------------- Jacobians
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_edge_jacobians_match_central_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    g = random_graph(rng, n=8, extra=8, noise=0.4, init_noise=0.5)  # large rotations everywhere
    rot, trans = np.array(g.rotations), np.array(g.translations)
    m = g.num_edges
    err = np.empty((m, 6))
    ja = np.empty((m, 6, 6))
    jb = np.empty((m, 6, 6))
    _gn_kernels.edge_jacobians(rot, trans, g.edge_nodes, g.edge_rotations, g.edge_translations,
                               err, ja, jb)
    np.testing.assert_allclose(err, _errors(g, rot, trans), rtol=0, atol=FLOAT64_IDENTITY)
    assert np.abs(err[:, 3:]).max() > 0.5  # the check covers large error rotations
    for c, (a, b) in enumerate(g.edge_nodes):
        for node, jac in ((a, ja[c]), (b, jb[c])):
            fd = np.empty((6, 6))
            for d in range(6):
                xi = np.zeros(6)
                xi[d] = CENTRAL_DIFF_STEP
                ep = _errors(g, *_perturb(rot, trans, node, xi))[c]
                em = _errors(g, *_perturb(rot, trans, node, -xi))[c]
                fd[:, d] = (ep - em) / (2 * CENTRAL_DIFF_STEP)
            np.testing.assert_allclose(jac, fd, rtol=0,
                                       atol=CENTRAL_DIFF * max(1.0, np.abs(fd).max()))


def _rot_z(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


_PLANAR = [0, 1, 5]  # x, y, yaw


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 1e-3, 0.1, 0.3, 0.49, 0.51, 1.0, 3.0])
def test_planar_linearization_is_se3s_restricted_to_the_plane(angle: float) -> None:
    """SE(2)'s error and Jacobians (the planar system's) against SE(3)'s x, y, yaw rows and
    columns on planar poses and measurements, for error angles on both sides of the series'
    switch: equal to rounding; SE(3)'s out-of-plane rows of the planar columns are exactly 0
    (what the planar system leaves out)."""
    rng = np.random.default_rng(int(angle * 1e3))
    for sign in (1.0, -1.0):
        for _ in range(20):
            ra = _rot_z(rng.uniform(-np.pi, np.pi))
            rz = _rot_z(rng.uniform(-np.pi, np.pi))
            rb = ra @ rz @ _rot_z(sign * angle)  # the error's rotation: angle about z
            ta = np.r_[rng.normal(size=2) * 5.0, 0.0]
            tb = np.r_[rng.normal(size=2) * 5.0, 0.0]
            tz = np.r_[rng.normal(size=2) * 3.0, 0.0]
            e3, ja3, jb3 = np.empty(6), np.empty((6, 6)), np.empty((6, 6))
            _gn_kernels._edge_linearization(np.stack([ra, rb]), np.stack([ta, tb]), rz[None],
                                            tz[None], 0, 1, 0, e3, ja3, jb3)
            e2, ja2, jb2 = np.empty(6), np.empty((6, 6)), np.empty((6, 6))
            rel = _cost.planar_residual(rz, tz, ra, ta, rb, tb, e2)
            _cost.planar_jacobians(e2, rel, ja2, jb2)
            assert np.all(ja2[3:, :3] == 0.0) and np.all(jb2[3:, :3] == 0.0)
            assert e2[5] == pytest.approx(sign * angle, abs=FLOAT64_IDENTITY)
            np.testing.assert_allclose(e2, e3, rtol=0,
                                       atol=TWIN_JACOBIAN * max(1.0, np.abs(e3).max()))
            for j2, j3 in ((ja2, ja3), (jb2, jb3)):
                np.testing.assert_allclose(j2[np.ix_(_PLANAR, _PLANAR)],
                                           j3[np.ix_(_PLANAR, _PLANAR)], rtol=0,
                                           atol=TWIN_JACOBIAN * np.abs(j3).max())
                assert np.all(j3[np.ix_([2, 3, 4], _PLANAR)] == 0.0)
                assert np.all(j2[[2, 3, 4], :] == 0.0)
                assert np.all(j2[:, [2, 3, 4]] == 0.0)


def test_planar_jacobians_match_central_differences() -> None:
    """The planar Jacobians against central differences of the planar error under planar
    right perturbations of either pose."""
    rng = np.random.default_rng(7)

    def error(ra: np.ndarray, ta: np.ndarray, rb: np.ndarray, tb: np.ndarray) -> np.ndarray:
        out = np.empty(6)
        _cost.planar_residual(rz, tz, ra, ta, rb, tb, out)
        return out[_PLANAR]

    def moved(r: np.ndarray, t: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dr, dt = se3_exp(np.r_[xi[0], xi[1], 0.0, 0.0, 0.0, xi[2]])
        return r @ dr, t + r @ dt

    for _ in range(20):
        ra, rb, rz = (_rot_z(rng.uniform(-np.pi, np.pi)) for _ in range(3))
        ta, tb, tz = (np.r_[rng.normal(size=2) * 4.0, 0.0] for _ in range(3))
        e, ja, jb = np.empty(6), np.empty((6, 6)), np.empty((6, 6))
        _cost.planar_jacobians(e, _cost.planar_residual(rz, tz, ra, ta, rb, tb, e), ja, jb)
        for side, jac in ((0, ja), (1, jb)):
            fd = np.empty((3, 3))
            for d in range(3):
                xi = np.zeros(3)
                xi[d] = CENTRAL_DIFF_STEP
                if side == 0:
                    ep = error(*moved(ra, ta, xi), rb, tb)
                    em = error(*moved(ra, ta, -xi), rb, tb)
                else:
                    ep = error(ra, ta, *moved(rb, tb, xi))
                    em = error(ra, ta, *moved(rb, tb, -xi))
                fd[:, d] = (ep - em) / (2 * CENTRAL_DIFF_STEP)
            np.testing.assert_allclose(jac[np.ix_(_PLANAR, _PLANAR)], fd, rtol=0,
                                       atol=CENTRAL_DIFF * max(1.0, np.abs(fd).max()))


@pytest.mark.parametrize(("num_gps", "fixed"), [(0, ()), (3, ()), (2, (4, 7))])
def test_sparse_normal_equations_match_dense_finite_differences(num_gps: int,
                                                                fixed: tuple[int, ...]) -> None:
    rng = np.random.default_rng(10 + num_gps)
    g = random_graph(rng, n=9, extra=7, noise=0.3, init_noise=0.4, num_gps=num_gps, fixed=fixed)
    neq = normal_equations(g)
    free = neq.free_nodes
    expected_fixed = set(fixed) if fixed else ({0} if num_gps == 0 else set())
    assert set(range(g.num_nodes)) - set(free.tolist()) == expected_fixed
    h_ref, g_ref = dense_normal_equations(g, np.array(g.rotations), np.array(g.translations), free)
    h = neq.hessian.toarray()
    np.testing.assert_allclose(h, h.T, rtol=0, atol=FLOAT64_IDENTITY * np.abs(h).max())
    np.testing.assert_allclose(h, h_ref, rtol=0, atol=CENTRAL_DIFF * np.abs(h_ref).max())
    np.testing.assert_allclose(neq.gradient, g_ref, rtol=0,
                               atol=CENTRAL_DIFF * np.abs(g_ref).max())
    assert neq.energy == pytest.approx(energy(g), rel=FLOAT64_IDENTITY)
    # The GN step (fill-reducing ordering, SuperLU) solves the same system as a dense solve.
    step = gn_step(g)
    dense = np.linalg.solve(h, -neq.gradient).reshape(-1, 6)
    np.testing.assert_allclose(step[free], dense, rtol=0,
                               atol=SPARSE_VS_DENSE_GN * np.abs(dense).max())
    assert np.all(step[list(expected_fixed)] == 0.0) if expected_fixed else True
    ref_step = np.linalg.solve(h_ref, -g_ref).reshape(-1, 6)
    np.testing.assert_allclose(step[free], ref_step, rtol=0,
                               atol=CENTRAL_DIFF * 10 * np.abs(ref_step).max())


def test_gn_step_with_explicit_fixed_set(rng: np.random.Generator) -> None:
    g = random_graph(rng, n=7, extra=5)
    step = gn_step(g, fixed=[2, 5])
    assert np.all(step[[2, 5]] == 0.0)
    neq = normal_equations(g, fixed=[5, 2])
    np.testing.assert_array_equal(neq.free_nodes, [0, 1, 3, 4, 6])
    dense = np.linalg.solve(neq.hessian.toarray(), -neq.gradient).reshape(-1, 6)
    np.testing.assert_allclose(step[neq.free_nodes], dense, rtol=0,
                               atol=SPARSE_VS_DENSE_GN * np.abs(dense).max())


# --------------------------------------------------------------------------- optima
@pytest.mark.parametrize("num_gps", [0, 4])
def test_gn_and_lm_reach_the_same_stationary_point(num_gps: int) -> None:
    rng = np.random.default_rng(20 + num_gps)
    g = random_graph(rng, n=25, extra=25, noise=0.05, init_noise=0.1, num_gps=num_gps)
    res = {m: solve_exact(g, config=GaussNewtonConfig(method=m)) for m in ("gn", "lm")}
    for m, r in res.items():
        assert r.status is Status.CONVERGED, (m, r.message)
        assert r.method == "exact" and r.stats["algorithm"] == m
        assert r.final_energy == pytest.approx(energy(g, r.rotations, r.translations),
                                               rel=FLOAT64_IDENTITY)
        neq = normal_equations(g, r.rotations, r.translations)
        scale = _gradient_scale(g, r.rotations, r.translations)
        assert np.abs(neq.gradient).max() < STATIONARY * scale, m
        np.testing.assert_allclose(np.einsum("nij,nkj->nik", r.rotations, r.rotations),
                                   np.broadcast_to(np.eye(3), (g.num_nodes, 3, 3)), rtol=0,
                                   atol=FLOAT64_IDENTITY)
    assert res["gn"].final_energy == pytest.approx(res["lm"].final_energy, rel=OPTIMUM_RTOL)
    assert res["lm"].final_energy < 0.1 * res["lm"].initial_energy
    if num_gps == 0:  # node 0 is the gauge: untouched
        for r in res.values():
            np.testing.assert_array_equal(r.rotations[0], g.rotations[0])
            np.testing.assert_array_equal(r.translations[0], g.translations[0])


@pytest.mark.parametrize("linear_solver", ["auto", "splu"])
@pytest.mark.parametrize("num_gps", [0, 3])
def test_exact_solver_analyzes_once_and_solves_like_fresh_solves(
        num_gps: int, linear_solver: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """One ExactSolver solving from several starts gives, bit for bit, the poses and energies
    of a fresh solve_exact from each start, and analyzes the pattern once."""
    rng = np.random.default_rng(40 + num_gps)
    g = random_graph(rng, n=20, extra=20, noise=0.05, init_noise=0.3, num_gps=num_gps)
    starts = [(g.rotations, g.translations)]
    for scale in (0.1, 0.5):
        h = random_graph(np.random.default_rng(7), n=20, extra=20, noise=0.05,
                         init_noise=scale, num_gps=num_gps)
        starts.append((h.rotations, h.translations))
    cfg = GaussNewtonConfig(linear_solver=linear_solver)
    fresh = [solve_exact(g, r, t, cfg) for r, t in starts]
    calls = []
    real = _normal.analyze
    monkeypatch.setattr(gauss_newton, "analyze", lambda *a, **k: calls.append(1) or real(*a, **k))
    solver = ExactSolver(g, cfg)
    for (r, t), want in zip(starts, fresh, strict=True):
        got = solver.solve(r, t)
        np.testing.assert_array_equal(got.rotations, want.rotations)
        np.testing.assert_array_equal(got.translations, want.translations)
        np.testing.assert_array_equal(got.energy_history, want.energy_history)
        assert got.iterations == want.iterations and got.status is want.status
    assert len(calls) == 1
    limited = solver.solve(*starts[1], max_iterations=1)
    assert limited.iterations == 1


@pytest.mark.parametrize("num_gps", [0, 3])
def test_optimum_energy_unchanged_by_relabelling(num_gps: int) -> None:
    rng = np.random.default_rng(30 + num_gps)
    g = random_graph(rng, n=20, extra=20, noise=0.05, init_noise=0.05, num_gps=num_gps)
    h = relabelled(g, rng)
    assert energy(h) == pytest.approx(energy(g), rel=FLOAT64_IDENTITY)
    eg = solve_exact(g).final_energy
    eh = solve_exact(h).final_energy
    assert eh == pytest.approx(eg, rel=OPTIMUM_RTOL)


@pytest.mark.parametrize("method", ["lm", "gn"])
def test_planar_reduction_equals_full_solve(method: str) -> None:
    """A lifted 2D graph solved on (x, y, yaw) only equals the full 6-dof solve."""
    from test_energy import planar_graph

    rng = np.random.default_rng(50)
    g2, *_ = planar_graph(rng, n=30, extra=25, noise=0.05)
    fields = {name: getattr(g2, name) for name in (
        "node_ids", "rotations", "translations", "edge_nodes", "edge_rotations",
        "edge_translations", "edge_information")}
    g3 = PoseGraph(**fields, is_2d=False)  # same data, not flagged 2D: full 6-dof system
    cfg = GaussNewtonConfig(method=method)
    r2 = solve_exact(g2, config=cfg)
    r3 = solve_exact(g3, config=cfg)
    assert r2.stats["planar"] and not r3.stats["planar"]
    assert r2.stats["num_variables"] * 2 == r3.stats["num_variables"]
    assert r2.status is Status.CONVERGED and r3.status is Status.CONVERGED
    assert r2.final_energy == pytest.approx(r3.final_energy, rel=OPTIMUM_RTOL)
    np.testing.assert_allclose(r2.translations, r3.translations, rtol=0, atol=1e-7)
    # The reduced solve keeps the poses exactly planar.
    assert np.all(r2.translations[:, 2] == 0.0)
    assert np.all(r2.rotations[:, 2, :] == [0.0, 0.0, 1.0])
    # Non-planar initial poses switch the reduction off.
    rot = np.array(g2.rotations)
    rot[3] = rot[3] @ se3_exp(np.r_[0, 0, 0, 0.01, 0, 0])[0]
    assert not solve_exact(g2, rotations=rot, config=cfg).stats["planar"]


@pytest.mark.parametrize("robust", [(0, 1.0), (_cost.robust_kind("huber", 1.0), 1.0)])
def test_planar_system_is_assembled_as_the_rows_and_columns_of_the_whole(robust) -> None:
    """The planar system written by the assembly (SE(2)'s linearization) equals the x, y, yaw
    rows and columns of the whole H (SE(3)'s) taken by SciPy, and g's entries and E are the
    same, to rounding: the same pattern, and the same numbers by another route through
    float64."""
    import scipy.sparse as sp
    from test_energy import planar_graph

    rng = np.random.default_rng(51)
    g, *_ = planar_graph(rng, n=30, extra=25, noise=0.2)
    fixed = _normal.default_fixed_nodes(g)
    pat = _normal.analyze(g, fixed, reorder=True)
    rot, trans = np.array(g.rotations), np.array(g.translations)
    assert _normal.is_planar(g, rot, trans)
    data, grad = np.empty(pat.nnz), np.empty(pat.dim)
    full = _normal.assemble(g, pat, rot, trans, data, grad, robust)
    system = _normal.planar_system(pat)
    sdata, sgrad = np.full(system.nnz, np.nan), np.full(pat.dim, np.nan)
    planar = _normal.assemble(g, pat, rot, trans, sdata, sgrad, robust, system)
    assert planar == pytest.approx(full, rel=TWIN_JACOBIAN)
    h = sp.csc_matrix((data, pat.lower_indices(), pat.indptr), shape=(pat.dim, pat.dim))
    keep = system.dofs
    sub = h[keep][:, keep].tocsc()
    sub.sort_indices()
    assert np.array_equal(sub.indptr, system.indptr)
    assert np.array_equal(sub.indices, system.indices)
    np.testing.assert_allclose(sdata, sub.data, rtol=0,
                               atol=TWIN_JACOBIAN * np.abs(sub.data).max())
    np.testing.assert_allclose(sgrad[keep], grad[keep], rtol=0,
                               atol=TWIN_JACOBIAN * np.abs(grad).max())
    assert np.all(sgrad[np.setdiff1d(np.arange(pat.dim), keep)] == 0.0)


def test_fixed_nodes_are_held_constant(rng: np.random.Generator) -> None:
    g = random_graph(rng, n=15, extra=10, fixed=(3, 9))
    assert default_fixed_nodes(g).tolist() == [3, 9]
    r = solve_exact(g)
    assert r.status is Status.CONVERGED
    for i in (3, 9):
        np.testing.assert_array_equal(r.rotations[i], g.rotations[i])
        np.testing.assert_array_equal(r.translations[i], g.translations[i])
    assert not np.array_equal(r.translations[0], g.translations[0])


def test_zero_energy_at_ground_truth_converges_immediately(rng: np.random.Generator) -> None:
    g = random_graph(rng, n=6, extra=3, noise=0.0, init_noise=0.0)
    r = solve_exact(g)
    assert r.status is Status.CONVERGED
    assert r.final_energy < FLOAT64_IDENTITY


@pytest.mark.parametrize("method", ["lm", "gn"])
def test_energy_never_increases_from_a_bad_start(method: str) -> None:
    rng = np.random.default_rng(40)
    g = random_graph(rng, n=30, extra=40, noise=0.1, init_noise=1.0)
    r = solve_exact(g, config=GaussNewtonConfig(method=method, max_iterations=60))
    hist = r.energy_history
    assert np.all(np.diff(hist) <= 0.0)
    assert hist[-1] < hist[0]
    assert np.all(np.isfinite(r.rotations)) and np.all(np.isfinite(r.translations))


def test_unguarded_gn_takes_every_step(rng: np.random.Generator) -> None:
    g = random_graph(rng, n=10, extra=8, noise=0.05, init_noise=0.05)
    r = solve_exact(g, config=GaussNewtonConfig(method="gn", step_guard=False))
    assert r.status is Status.CONVERGED
    assert r.stats["rejected_steps"] == 0 and r.stats["step_halvings"] == 0


def test_max_iterations_and_progress_callback(rng: np.random.Generator) -> None:
    g = random_graph(rng, n=10, extra=8, init_noise=0.5)
    seen: list[tuple[int, float]] = []
    r = solve_exact(g, config=GaussNewtonConfig(max_iterations=2),
                    progress=lambda p: seen.append((p.iteration, p.energy)))
    assert r.status is Status.MAX_ITERATIONS
    assert r.iterations == 2
    assert [k for k, _ in seen] == [0, 1, 2]
    np.testing.assert_array_equal([e for _, e in seen], r.energy_history)
    assert r.times.shape == r.energy_history.shape and np.all(np.diff(r.times) >= 0)
    zero = solve_exact(g, config=GaussNewtonConfig(max_iterations=0))
    assert zero.iterations == 0 and zero.final_energy == pytest.approx(energy(g), rel=1e-12)


@pytest.mark.skipif(not cholmod_available(), reason="scikit-sparse (CHOLMOD) not installed")
def test_cholmod_and_superlu_agree(rng: np.random.Generator) -> None:
    g = random_graph(rng, n=20, extra=15)
    a = solve_exact(g, config=GaussNewtonConfig(linear_solver="splu"))
    b = solve_exact(g, config=GaussNewtonConfig(linear_solver="cholmod"))
    assert a.stats["linear_solver"] == "splu" and b.stats["linear_solver"] == "cholmod"
    assert a.final_energy == pytest.approx(b.final_energy, rel=OPTIMUM_RTOL)


# --------------------------------------------------------------------------- errors
def test_non_finite_initial_pose_raises_solver_error(rng: np.random.Generator) -> None:
    g = random_graph(rng, n=5, extra=2)
    t = np.array(g.translations)
    t[2, 1] = np.nan
    with pytest.raises(SolverError, match=r"translations\[2\] \(id 23\)"):
        solve_exact(g, translations=t)


def test_unanchored_part_raises_graph_error(rng: np.random.Generator) -> None:
    g = random_graph(rng, n=6, extra=0)
    en = np.array(g.edge_nodes)
    keep = ~((en[:, 0] == 2) & (en[:, 1] == 3))  # cut the chain 0-1-2 | 3-4-5
    h = PoseGraph(node_ids=g.node_ids, rotations=g.rotations, translations=g.translations,
                  edge_nodes=en[keep], edge_rotations=g.edge_rotations[keep],
                  edge_translations=g.edge_translations[keep],
                  edge_information=g.edge_information[keep])
    with pytest.raises(GraphError, match="neither a fixed pose nor a GPS"):
        solve_exact(h)
    fixed = PoseGraph(node_ids=h.node_ids, rotations=h.rotations, translations=h.translations,
                      edge_nodes=h.edge_nodes, edge_rotations=h.edge_rotations,
                      edge_translations=h.edge_translations,
                      edge_information=h.edge_information, fixed_nodes=np.array([0, 4]))
    assert solve_exact(fixed).status is Status.CONVERGED


def test_gauss_newton_without_gauge_raises_solver_error(rng: np.random.Generator) -> None:
    g = random_graph(rng, n=5, extra=3, noise=0.0, init_noise=0.1)
    with pytest.raises(SolverError):
        gn_step(g, fixed=[])


@pytest.mark.parametrize(
    ("field", "value"),
    [("method", "newton"), ("max_iterations", -1), ("max_iterations", 2.5),
     ("energy_tolerance", -1e-3), ("energy_tolerance", float("nan")),
     ("step_tolerance", float("inf")), ("initial_damping", 0.0), ("step_guard", 1),
     ("max_step_halvings", -2), ("linear_solver", "umfpack")],
)
def test_config_validation(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        GaussNewtonConfig(**{field: value})  # type: ignore[arg-type]


def test_config_is_frozen() -> None:
    cfg = GaussNewtonConfig()
    assert (cfg.method, cfg.max_iterations, cfg.energy_tolerance, cfg.step_tolerance,
            cfg.initial_damping) == ("lm", 100, 1e-10, 1e-12, 1e-8)
    with pytest.raises(AttributeError):
        cfg.method = "gn"  # type: ignore[misc]


def _assembly_case(seed: int, planar: bool, planar_size: tuple[int, int, float],
                   size: tuple[int, int, float], num_gps: int
                   ) -> tuple[PoseGraph, _normal.Pattern, np.ndarray, np.ndarray]:
    """A planar graph (``planar_size``: poses, extra constraints, noise) or a 3D one
    (``size``, with ``num_gps`` readings), its analyzed pattern and poses; planar exactly
    when asked."""
    from test_energy import planar_graph

    rng = np.random.default_rng(seed)
    if planar:
        n, extra, noise = planar_size
        g, *_ = planar_graph(rng, n=n, extra=extra, noise=noise)
    else:
        n, extra, noise = size
        g = random_graph(rng, n=n, extra=extra, noise=noise, init_noise=noise, num_gps=num_gps)
    pat = _normal.analyze(g, _normal.default_fixed_nodes(g), reorder=True)
    rot, trans = np.array(g.rotations), np.array(g.translations)
    assert _normal.is_planar(g, rot, trans) == planar
    return g, pat, rot, trans


@pytest.mark.parametrize("robust", [(0, 1.0), (_cost.robust_kind("huber", 1.0), 1.0)])
@pytest.mark.parametrize("planar", [False, True])
def test_the_trial_energy_is_the_assemblys_to_the_bit(robust, planar: bool) -> None:
    """LM reads E at the new poses from its trial and assembles only a step that does not
    converge: the trial's ``(E_rho, E)`` must be the assembly's exactly, in the whole system
    and in the planar one (the same terms summed in the same order)."""
    g, pat, rot, trans = _assembly_case(52, planar, (30, 25, 0.2), (20, 15, 0.4), num_gps=3)
    system = _normal.planar_system(pat) if planar else None
    nnz = system.nnz if system is not None else pat.nnz
    data, grad = np.empty(nnz), np.empty(pat.dim)
    assembled = _normal.assemble(g, pat, rot, trans, data, grad, robust, system)
    assert _normal.energies_at(g, rot, trans, robust, planar) == assembled


@pytest.mark.parametrize("robust", [(0, 1.0), (_cost.robust_kind("huber", 1.0), 1.0)])
@pytest.mark.parametrize("planar", [False, True])
def test_assembly_equals_the_full_products_to_the_bit(robust, planar: bool) -> None:
    """The assembly sums each product only over the Jacobians' rows that can be non-zero; the
    same products summed over all six rows in order (``ref_kernels.assemble_in_order``, from
    the same Jacobians) give H and g equal to the bit, in the whole and the planar system."""
    g, pat, rot, trans = _assembly_case(53, planar, (25, 20, 0.3), (18, 14, 0.5), num_gps=0)
    system = _normal.planar_system(pat) if planar else _normal.full_system(pat)
    m = g.num_edges
    e, ja, jb = np.empty((m, 6)), np.empty((m, 6, 6)), np.empty((m, 6, 6))
    nodes = g.edge_nodes
    if planar:
        for c in range(m):
            a, b = nodes[c]
            rel = _cost.planar_residual(g.edge_rotations[c], g.edge_translations[c], rot[a],
                                        trans[a], rot[b], trans[b], e[c])
            _cost.planar_jacobians(e[c], rel, ja[c], jb[c])
    else:
        _gn_kernels.edge_jacobians(rot, trans, nodes, g.edge_rotations, g.edge_translations, e,
                                   ja, jb)
    weight = np.ones(m)
    if robust[0] != _cost.ROBUST_NONE:
        info = g.edge_information
        for c in range(m):
            chi = _cost.chi2(info[c], e[c], 6, np.empty(6))
            weight[c] = _cost.robust_cost(robust[0], robust[1], chi)[1]
        assert weight.min() < 1.0  # some constraints down-weighted
    data, grad = np.empty(system.nnz), np.empty(pat.dim)
    _normal.assemble(g, pat, rot, trans, data, grad, robust, system)
    ref_data, ref_grad = np.empty(system.nnz), np.empty(pat.dim)
    var = pat.var_of_node
    assemble_in_order(ja, jb, g.edge_information, weight, var[nodes[:, 0]], var[nodes[:, 1]],
                      pat.edge_off, tuple(int(d) for d in system.tangent), system.indptr,
                      ref_data, ref_grad, e)
    assert np.array_equal(data, ref_data)
    assert np.array_equal(grad, ref_grad)


# --------------------------------------------------------------------------- convergence test
def _feed(energies: list[float], tolerance: float = 1e-10,
          newton: bool = True) -> list[bool]:
    """The convergence test's answer after each step of an energy sequence."""
    stop = gauss_newton._Convergence(tolerance)
    return [stop.accepted(a, b, newton) for a, b in itertools.pairwise(energies)]


def test_a_linear_fall_goes_on_while_its_tail_is_above_the_tolerance() -> None:
    # E = 100 + 0.9^k: the tail of each step is 9 times the step, so steps change E by less
    # than 1e-10 E (~1e-8) for some 20 steps before the tail is below it too
    e = [100.0 + 0.9 ** k for k in range(250)]
    done = _feed(e)
    first = done.index(True)
    drops = -np.diff(e)
    small_step = int(np.argmax(drops <= 1e-10 * np.asarray(e[:-1])))
    assert first > small_step + 15  # went on while only the step was small
    assert 9.0 * drops[first] <= 1e-10 * e[first] < 9.0 * drops[first - 1]
    assert not any(done[:first])


def test_a_superlinear_fall_stops_at_the_step_that_shows_it() -> None:
    # decreases 1, 1e-3, 1e-7: rates 1e-3 then 1e-4 (falling, below 0.01); the last step's
    # change (1e-7, 1e-9 of E) is above the tolerance (1e-8), its tail (1e-11, 1e-13 of E) ten
    # times below it
    e = [100.0 + 1.0 + 1e-3 + 1e-7, 100.0 + 1e-3 + 1e-7, 100.0 + 1e-7, 100.0]
    assert _feed(e) == [False, False, True]
    # the same fall, not a full Newton-like step: the step's own change must be small
    assert _feed(e, newton=False) == [False, False, False]
    # a rate that rises again (1e-4, then 1e-3) is no proof of a superlinear fall
    rising = [100.0 + 1.0 + 1e-4 + 1e-7, 100.0 + 1e-4 + 1e-7, 100.0 + 1e-7, 100.0]
    assert _feed(rising) == [False, False, False]
    # nor are the first two steps (no rate before theirs)
    assert _feed(e[1:]) == [False, False]


def test_a_superlinear_exit_keeps_a_margin_below_the_tolerance() -> None:
    # sphere2500_isam's LM from its certified start: decreases 1450, 97.4, 4.8e-3 (rates
    # 0.067, 5e-5), then 1.8e-6 more to the optimum, 1.2e-10 of E: the tail at 5e-5 (2.4e-7,
    # 1.6e-11 of E) underestimates it 7.5x, so the third step is not an exit
    e = [16354.1842, 14904.23616, 14806.86102, 14806.8562]
    assert _feed(e) == [False, False, False]
    # a last decrease ten times smaller (rate 5e-6): its tail, 100 times smaller, is an exit
    e[3] = e[2] - (e[2] - e[3]) / 10.0
    assert _feed(e) == [False, False, True]


def test_a_rise_of_the_energy_is_never_a_superlinear_fall() -> None:
    # unguarded Gauss-Newton takes a step that raises E: not converged (the change is large)
    e = [100.0 + 1.0 + 1e-3, 100.0 + 1e-3, 100.0 + 1e-6, 150.0]
    assert _feed(e) == [False, False, False]
    # a rise below the tolerance is converged, as a fall below it is
    e[3] = e[2] + 1e-9
    assert _feed(e) == [False, False, True]


def test_lm_stops_at_a_superlinear_step_within_the_tolerance_of_the_optimum() -> None:
    g = read_graph(bundled_path("intel.g2o"))
    r = solve_exact(g)
    tight = solve_exact(g, config=GaussNewtonConfig(energy_tolerance=0.0, max_iterations=30))
    assert r.status is Status.CONVERGED
    # the step r stopped at changed E by more than the tolerance: the superlinear rule ended it
    h = r.energy_history
    assert h[-2] - h[-1] > 1e-10 * h[-2]
    assert r.final_energy - tight.final_energy <= 1e-10 * tight.final_energy


def test_only_full_newton_like_steps_count_as_superlinear() -> None:
    lm = GaussNewtonConfig()  # initial_damping 1e-8
    mu0 = lm.initial_damping
    assert gauss_newton._newton_like(lm, mu0, mu0 / 10.0, 1.0)
    assert not gauss_newton._newton_like(lm, 2.0 * mu0, mu0, 1.0)  # damped when solved
    assert not gauss_newton._newton_like(lm, mu0, 1.5 * mu0, 1.0)  # its gain raised mu
    gn = GaussNewtonConfig(method="gn")
    assert gauss_newton._newton_like(gn, 0.0, 0.0, 1.0)
    assert not gauss_newton._newton_like(gn, 0.0, 0.0, 0.5)  # a halved step
