"""SE-Sync's model, Newton's method on it, the certificate and the staircase
(hybridpgo.certificate), against naive twins, dense linear algebra, finite differences and
SE-Sync's published optimal values."""

from __future__ import annotations

import pathlib

import numpy as np
import pytest
import scipy.sparse as sp
from graphs import planar_rotations, random_graph, with_gps
from naive import dense_quadratic_form, schur_certificate, sesync_objective
from tolerances import CENTRAL_DIFF, FLOAT64_IDENTITY, ORTHONORMAL

from hybridpgo.certificate import (
    GAP_TOLERANCE,
    SyncProblem,
    certify,
    gps_weights,
    sesync_certificate,
    sesync_weights,
    staircase_start,
)
from hybridpgo.energy import energy
from hybridpgo.generate import generate_city, generate_grid
from hybridpgo.graph import PoseGraph
from hybridpgo.io import bundled_path, read_graph
from hybridpgo.linalg import NotPositiveDefinite, SparseSPD
from hybridpgo.linalg import _factor as _linear
from hybridpgo.solvers.gauss_newton import solve_exact

DATA = pathlib.Path(__file__).parent / "data"


def _grid2d(seed: int = 0, poses: int = 20, rot_sigma: float = 0.05) -> PoseGraph:
    return generate_grid("m3500", seed=seed, num_poses=poses, rot_sigma_rad=rot_sigma).graph


def _tiny3d() -> PoseGraph:
    return read_graph(DATA / "tinyGrid3D.g2o")


def _random_rotations(graph: PoseGraph, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if graph.is_2d:
        return planar_rotations(rng.uniform(-np.pi, np.pi, graph.num_nodes))
    from scipy.spatial.transform import Rotation

    return np.asarray(Rotation.random(graph.num_nodes, random_state=seed).as_matrix())


def _twin_model(graph: PoseGraph):
    """SE-Sync's model written out constraint by constraint: ``(edges, rm, tm, kappa, tau,
    n)`` over the graph's poses and, with GPS, an earth pose appended (index N): each reading
    a constraint from it with the reading as translation, no rotation term (kappa 0) and
    ``tau = d / tr(Omega^-1)`` of the reading's (d, d) information."""
    kappa, tau = sesync_weights(graph)
    n = graph.num_nodes
    edges, rm, tm = graph.edge_nodes, graph.edge_rotations, graph.edge_translations
    if graph.num_gps:
        d = 2 if graph.is_2d else 3
        tau_g = [d / np.trace(np.linalg.inv(w[:d, :d])) for w in graph.gps_information]
        edges = np.concatenate([edges, [[n, int(i)] for i in graph.gps_nodes]])
        rm = np.concatenate([rm, [np.eye(3)] * graph.num_gps])
        tm = np.concatenate([tm, graph.gps_positions])
        kappa = np.concatenate([kappa, np.zeros(graph.num_gps)])
        tau = np.concatenate([tau, tau_g])
        n += 1
    return edges, rm, tm, kappa, tau, n


def _naive_f(graph: PoseGraph, prob: SyncProblem):
    """v (one column of V = [T; Y]) -> SE-Sync's F with the real (d, d) matrices of v."""
    edges, rm, tm, kappa, tau, n = _twin_model(graph)
    if prob.complex:
        rm, tm = rm[:, :2, :2], tm[:, :2]

        def f(v: np.ndarray) -> float:
            t, z = v[:n], v[n:]
            rot = np.stack([np.stack([z.real, -z.imag], -1), np.stack([z.imag, z.real], -1)], 1)
            trans = np.stack([t.real, t.imag], -1)
            return sesync_objective(edges, rm, tm, kappa, tau, rot, trans)
    else:
        def f(v: np.ndarray) -> float:
            # v is column 0 of V (the other columns 0): entry 0 of every t_i and column 0 of
            # every R_i^T, i.e. row 0 of R_i; F's rows are independent, so F = v^T M v
            v = v.real
            trans = np.zeros((n, 3))
            trans[:, 0] = v[:n]
            rot = np.zeros((n, 3, 3))
            rot[:, 0, :] = v[n:].reshape(n, 3)
            return sesync_objective(edges, rm, tm, kappa, tau, rot, trans)
    return f


# --------------------------------------------------------------------------- the model
def _raw_edges(path: pathlib.Path, tag: str) -> list[list[float]]:
    return [[float(x) for x in ln.split()[1:]] for ln in path.read_text().splitlines()
            if ln.startswith(tag)]


def test_weights_are_sesyncs_from_the_file_numbers() -> None:
    """SE-Sync's loader formulas applied to the file's own numbers (g2o units)."""
    path = DATA / "tinyGrid3D.g2o"
    kappa, tau = sesync_weights(read_graph(path))
    for c, row in enumerate(_raw_edges(path, "EDGE_SE3:QUAT")):
        up = row[9:]
        info = np.zeros((6, 6))
        info[np.triu_indices(6)] = up
        info = info + np.triu(info, 1).T
        assert kappa[c] == pytest.approx(3.0 / (2.0 * np.trace(np.linalg.inv(info[3:, 3:]))),
                                         rel=FLOAT64_IDENTITY)
        assert tau[c] == pytest.approx(3.0 / np.trace(np.linalg.inv(info[:3, :3])),
                                       rel=FLOAT64_IDENTITY)
    path = bundled_path("intel.g2o")
    kappa, tau = sesync_weights(read_graph(path))
    for c, row in enumerate(_raw_edges(path, "EDGE_SE2")):
        i11, i12, _i13, i22, _i23, i33 = row[5:]
        assert kappa[c] == i33
        assert tau[c] == pytest.approx(2.0 / np.trace(np.linalg.inv([[i11, i12], [i12, i22]])),
                                       rel=FLOAT64_IDENTITY)


def test_a_gps_readings_weight_is_its_isotropic_information() -> None:
    """An isotropic reading (information w I) weighs w: F's GPS term is E's at the earth frame."""
    for graph in (_grid2d(), _tiny3d()):
        ids = graph.node_ids[:3]
        w = np.array([0.5, 4.0, 25.0])
        info = w[:, None, None] * np.eye(3)
        if graph.is_2d:
            info[:, 2, 2] = 7.0  # the vertical entry of a planar reading plays no part
        pos = graph.translations[:3] * np.array([1.0, 1.0, 0.0 if graph.is_2d else 1.0])
        assert np.abs(gps_weights(graph.add_gps(ids, pos, info)) - w).max() <= (
            FLOAT64_IDENTITY * 10 * w.max())


_GPS_CASES = [lambda: with_gps(_tiny3d()), lambda: with_gps(_grid2d())]


@pytest.mark.parametrize("make", [_tiny3d, _grid2d, *_GPS_CASES],
                         ids=["3D", "2D", "3D+GPS", "2D+GPS"])
def test_data_matrix_and_certificate_match_naive_twins(make) -> None:
    """M against the polarization of SE-Sync's F term by term; S = Q - Lambda against the dense
    Schur complement; F(Y) with optimal positions against the twin at those positions."""
    graph = make()
    prob = SyncProblem(graph)
    n, d = prob.n, prob.d
    f = _naive_f(graph, prob)
    m_twin = dense_quadratic_form(f, n + d * n, prob.complex)
    assert prob.m.has_canonical_format and np.all(prob.m.data != 0)
    m = prob.m.toarray()
    scale = np.abs(m_twin).max()
    assert np.abs(m - m_twin).max() <= 1e3 * FLOAT64_IDENTITY * scale
    y = prob.to_y(_random_rotations(graph, 1))
    s_twin = schur_certificate(m_twin, n, d, prob.gauge, y)
    s = prob.certificate_product(y, np.eye(d * n, dtype=y.dtype))
    assert np.abs(s - s_twin).max() <= 1e3 * FLOAT64_IDENTITY * np.abs(s_twin).max()
    # F at the optimal positions is the twin's F there, and no other positions are lower
    rot = prob.rotations(y)
    trans = prob.translations(prob.positions(y))
    edges, rm, tm, kappa, tau, _ = _twin_model(graph)
    dd = 2 if prob.complex else 3
    rm, tm = rm[:, :dd, :dd], tm[:, :dd]
    twin = sesync_objective(edges, rm, tm, kappa, tau, rot[:, :dd, :dd], trans[:, :dd])
    assert prob.cost(y) == pytest.approx(twin, rel=1e3 * FLOAT64_IDENTITY)
    rng = np.random.default_rng(2)
    moved = trans[:, :dd] + 1e-3 * rng.standard_normal((n, dd))
    moved[prob.gauge] = trans[prob.gauge, :dd]
    assert sesync_objective(edges, rm, tm, kappa, tau, rot[:, :dd, :dd], moved) > twin


@pytest.mark.parametrize("make", [_tiny3d, lambda: _grid2d(poses=12),
                                  lambda: with_gps(_tiny3d(), every=3),
                                  lambda: with_gps(_grid2d(poses=12), every=3)],
                         ids=["3D", "2D", "3D+GPS", "2D+GPS"])
def test_newton_system_matches_finite_differences(make) -> None:
    graph = make()
    prob = SyncProblem(graph)
    y = prob.to_y(_random_rotations(graph, 3))
    h, g, f = prob.newton_system(y)
    n = prob.n
    pp = 3 if prob.complex else 6
    st = 2 if prob.complex else 3
    t0 = prob.positions(y)
    edges, rm, tm, kappa, tau, _ = _twin_model(graph)
    dd = 2 if prob.complex else 3

    def objective(delta: np.ndarray) -> float:
        """The twin's F at the moved rotations and positions."""
        p = delta.reshape(n, pp)
        yy = prob._step(y, p)
        tt = t0 + ((p[:, 0] + 1j * p[:, 1])[:, None] if prob.complex else p[:, :st])
        rot = prob.rotations(yy)[:, :dd, :dd]
        trans = prob.translations(tt)[:, :dd]
        return sesync_objective(edges, rm[:, :dd, :dd], tm[:, :dd], kappa, tau, rot, trans)

    dim = pp * n
    assert objective(np.zeros(dim)) == pytest.approx(f, rel=FLOAT64_IDENTITY * 1e3)
    eye = np.eye(dim)
    step = 1e-5
    g_fd = np.array([(objective(step * eye[i]) - objective(-step * eye[i])) / (2 * step)
                     for i in range(dim)])
    assert np.abs(g_fd - g).max() <= CENTRAL_DIFF * np.abs(g).max()
    hd = h.toarray()
    e = 1e-4
    h_fd = np.zeros((dim, dim))
    for i in range(dim):
        for j in range(i, dim):
            a, b = e * eye[i], e * eye[j]
            h_fd[i, j] = h_fd[j, i] = (objective(a + b) - objective(a - b) - objective(b - a)
                                       + objective(-a - b)) / (4 * e * e)
    assert np.abs(h_fd - hd).max() <= 10 * CENTRAL_DIFF * np.abs(hd).max()


# --------------------------------------------------------------------------- certificate
@pytest.mark.parametrize("make", [_tiny3d, _grid2d, *_GPS_CASES],
                         ids=["3D", "2D", "3D+GPS", "2D+GPS"])
def test_smallest_eigenvalue_matches_a_dense_decomposition(make) -> None:
    graph = make()
    prob = SyncProblem(graph)
    n, d = prob.n, prob.d
    eye = np.eye(d * n)
    # 3D with GPS: at rank d the certificate holds the earth's rotation (its rows deleted)
    keep = np.repeat(np.arange(n) != prob.earth, d) if graph.num_gps and d == 3 else ...
    for y in (prob.to_y(_random_rotations(graph, 4)),  # far from stationary: negative
              prob.refine(prob.to_y(graph.rotations))[0]):  # F's minimum: ~0
        s_dense = prob.certificate_product(y, eye.astype(y.dtype))
        s_dense = 0.5 * (s_dense + s_dense.conj().T)[keep][:, keep]
        exact = float(np.linalg.eigvalsh(s_dense)[0])
        spec = prob.spectrum(y)
        norm = float(np.abs(np.linalg.eigvalsh(s_dense)).max())
        assert spec.lambda_min == pytest.approx(exact, abs=1e-9 * norm)
        if np.isfinite(spec.lower_bound) and not spec.earth_held:  # sigma d n below F
            assert spec.lower_bound == pytest.approx(spec.objective - spec.shift * d * n,
                                                     rel=FLOAT64_IDENTITY)
    assert spec.lower_bound <= spec.objective
    assert spec.objective == pytest.approx(prob.cost(y), rel=FLOAT64_IDENTITY * 1e3)


@pytest.mark.parametrize("make", [_tiny3d, lambda: read_graph(bundled_path("intel.g2o"))],
                         ids=["3D", "2D"])
def test_the_verdict_alone_costs_no_eigenvalue_where_it_fails(make) -> None:
    """``eigenvalue=False``: the same verdict, lower bound and shift as the full spectrum;
    where Y does not certify no eigenvalue, no eigenvector and fewer factorizations (the
    ladder stops at the last rung that could certify); where it certifies, the same
    eigenvalue."""
    graph = make()
    prob = SyncProblem(graph)
    far = prob.to_y(_random_rotations(graph, 4))  # far from stationary: not certified
    optimum = prob.refine(prob.to_y(_chordal(graph)[0]))[0]
    for y, certified in ((far, False), (optimum, True)):
        full = prob.spectrum(y, eigenvector=True)
        verdict = prob.spectrum(y, eigenvector=True, eigenvalue=False)
        assert bool(np.isfinite(full.lower_bound)) is certified
        assert verdict.shift == full.shift and verdict.lower_bound == full.lower_bound
        if certified:
            assert verdict.lambda_min == full.lambda_min
            assert verdict.factorizations == full.factorizations
        else:
            assert full.lambda_min < 0 and full.vector is not None
            assert np.isnan(verdict.lambda_min) and verdict.vector is None
            assert verdict.factorizations < full.factorizations


def test_the_verdict_alone_computes_no_eigenvalue_where_the_first_shift_cannot_certify() -> None:
    """A graph without loops: F = 0 at its minimum, no shift certifies a relative gap, yet
    the ladder's first shift factors; the full spectrum computes the eigenvalue there, the
    verdict alone does not."""
    graph, rot, _ = random_graph(np.random.default_rng(2), n=8, extra=0)
    prob = SyncProblem(graph)
    y = prob.refine(prob.to_y(rot))[0]
    full = prob.spectrum(y)
    verdict = prob.spectrum(y, eigenvalue=False)
    assert full.factorizations == verdict.factorizations == 1  # the first rung factors
    assert not np.isfinite(full.lower_bound) and not np.isfinite(verdict.lower_bound)
    assert np.isfinite(full.lambda_min) and np.isnan(verdict.lambda_min)


@pytest.mark.parametrize("make", [_tiny3d, _grid2d], ids=["3D", "2D"])
def test_the_preconditioner_is_the_shifted_certificate_matrix_inverse(make) -> None:
    """At a point of rank d + 1: ``apply(G) = (S + shift I)^-1 G`` against a dense solve,
    with ``shift`` the first rung of its ladder (from the given sigma, x10) where S + shift I
    is positive definite."""
    graph = make()
    prob = SyncProblem(graph)
    n, d = prob.n, prob.d
    rng = np.random.default_rng(3)
    y0 = prob.to_y(_random_rotations(graph, 5))
    extra = rng.standard_normal((d * n, 1))
    if prob.complex:
        extra = extra + 1j * rng.standard_normal((d * n, 1))
    y = prob.retract(np.concatenate([y0, 0.5 * extra], axis=1))
    s_dense = prob.certificate_product(y, np.eye(d * n).astype(y.dtype))
    s_dense = 0.5 * (s_dense + s_dense.conj().T)
    lam = np.linalg.eigvalsh(s_dense)
    assert lam[0] < 0.0  # a shift is needed
    sigma0 = 3.7e-4 * abs(lam[0])  # no rung at the boundary itself
    apply, shift = prob.preconditioner(y, sigma0)
    assert apply is not None
    rungs = np.log10(shift / sigma0)
    assert rungs == pytest.approx(round(rungs), abs=1e-9)  # a rung of the ladder
    assert lam[0] + shift > 0.0 and lam[0] + shift / 10.0 <= 0.0  # the first definite one
    g = rng.standard_normal((d * n, 2))
    if prob.complex:
        g = g + 1j * rng.standard_normal((d * n, 2))
    want = np.linalg.solve(s_dense + shift * np.eye(d * n), g)
    scale = np.abs(want).max()
    assert np.abs(apply(g) - want).max() <= 1e-9 * scale
    # a sigma that is no finite number above the floor starts the ladder at the floor
    floor_start = prob.preconditioner(y, 0.0)[1]
    assert lam[0] + floor_start > 0.0
    for bad in (float("nan"), float("inf"), -1.0):
        assert prob.preconditioner(y, bad)[1] == floor_start


@pytest.mark.parametrize("make", [_tiny3d, _grid2d], ids=["3D", "2D"])
def test_preconditioned_conjugate_gradients_descend_on_the_relaxation(make) -> None:
    """The relaxation at rank d + 1 minimized from the same start with and without the
    preconditioner: both lower F to the same minimum (within the stopping tolerance's
    reach); the preconditioned run takes fewer iterations."""
    graph = make()
    prob = SyncProblem(graph)
    n, d = prob.n, prob.d
    rng = np.random.default_rng(4)
    extra = rng.standard_normal((d * n, 1))
    if prob.complex:
        extra = extra + 1j * rng.standard_normal((d * n, 1))
    y = prob.retract(np.concatenate([prob.to_y(_random_rotations(graph, 6)), 0.5 * extra],
                                    axis=1))
    f0 = prob.cost(y)
    apply, _ = prob.preconditioner(y, 1.0)
    _, f_plain, its_plain = prob.minimize(y, 2000, gradient_tolerance=1e-8)
    pre, f_pre, its_pre = prob.minimize(y, 2000, gradient_tolerance=1e-8, precondition=apply)
    assert f_pre < f0 and f_plain < f0
    assert abs(f_pre - f_plain) <= 1e-6 * f0
    assert its_pre < its_plain
    # the iterates keep orthonormal block rows
    blocks = pre.reshape(n, d, -1)
    gram = blocks @ np.conj(np.swapaxes(blocks, 1, 2))
    assert np.abs(gram - np.eye(d)).max() <= ORTHONORMAL


@pytest.mark.parametrize("make", [_tiny3d, _grid2d, *_GPS_CASES],
                         ids=["3D", "2D", "3D+GPS", "2D+GPS"])
def test_certificate_matrix_is_the_data_matrix_pose_by_pose(make) -> None:
    """The certificate's factored matrix K, built block by block from the constraints, is M
    (dense, realified: ``p + i q`` as ``[[p, -q], [q, p]]``) with each pose's position and
    rotation entries side by side, plus the anchor of the gauge's position."""
    graph = make()
    prob = SyncProblem(graph)
    n = prob.n
    m = prob.m.toarray()
    if prob.complex:  # real form: entry (r, c) -> rows 2r, 2r + 1, columns 2c, 2c + 1
        real = np.zeros((2 * m.shape[0], 2 * m.shape[1]))
        real[0::2, 0::2], real[1::2, 1::2] = m.real, m.real
        real[0::2, 1::2], real[1::2, 0::2] = -m.imag, m.imag
        slots = [[2 * i, 2 * i + 1, 2 * (n + i), 2 * (n + i) + 1] for i in range(n)]
    else:
        real = m.real
        slots = [[i, n + 3 * i, n + 3 * i + 1, n + 3 * i + 2] for i in range(n)]
    perm = np.ravel(slots)
    twin = real[np.ix_(perm, perm)]
    anchor = np.mean([twin[4 * i, 4 * i] for i in range(n)])
    for k in range(2 if prob.complex else 1):
        twin[4 * prob.gauge + k, 4 * prob.gauge + k] += anchor
    cs = prob._spectrum_setup()
    dim = 4 * n
    blocks = cs["values"].reshape(-1, 4, 4)
    k_mat = np.zeros((dim, dim))
    nb = prob._block_map(np.arange(n))
    rows = np.repeat(np.arange(n), np.diff(nb["indptr"]))
    for blk, r, c in zip(blocks, rows, nb["indices"], strict=True):
        k_mat[4 * r:4 * r + 4, 4 * c:4 * c + 4] = blk
    assert np.abs(k_mat - twin).max() <= 1e3 * FLOAT64_IDENTITY * np.abs(twin).max()
    assert cs["scale"] == pytest.approx(np.abs(np.diagonal(real)).max(), rel=FLOAT64_IDENTITY)


def test_published_optima_are_certified() -> None:
    """SE-Sync's published optimal objectives: intel 52.3482 (SE-Sync's example notebook;
    5.235e1 in IJRR 2019 Table 1), garage 1.263 (IJRR 2019 Table 2).  Certified at LM's
    solution from the file; the polish from the certified start reaches the same energy."""
    for name, published, digits in (("intel.g2o", 52.3482, 6), ("garage.g2o", 1.263, 4)):
        graph = read_graph(bundled_path(name))
        sol = solve_exact(graph)
        cert = certify(graph, sol.rotations, sol.translations, energy=sol.final_energy)
        assert cert.certified, cert.reason
        assert cert.objective == pytest.approx(published, abs=0.5 * 10.0 ** (
            np.floor(np.log10(published)) - digits + 1))
        assert 0.0 <= cert.gap <= 1e-6 * cert.objective
        assert cert.summary().startswith("certified global optimum (gap ≤ ")
        assert abs(cert.stats["polish_energy"] - sol.final_energy) <= 1e-9 * sol.final_energy
        assert np.isfinite(cert.lambda_min) and cert.lambda_min > -1e-6


def test_a_local_minimum_is_not_certified() -> None:
    """LM from scrambled yaws stops in a local minimum of E, and the certificate refuses it
    either way Newton's method on F goes from there: short of a stationary point of F at its
    cap (seed 7: no eigenvalue is computed there, the reason says why) or to F's
    global minimum (seed 5: certified, but LM from there ends at the global optimum, below
    the solution)."""
    made = generate_grid("m3500", seed=0, num_poses=120, rot_sigma_rad=0.05)
    graph = made.graph
    best = solve_exact(graph, made.truth_rotations, made.truth_translations)
    for seed, newton_ends in ((7, "short"), (5, "global")):
        rng = np.random.default_rng(seed)
        rot = made.truth_rotations.copy()
        rot[1:] = planar_rotations(rng.uniform(-np.pi, np.pi, graph.num_nodes))[1:]
        local = solve_exact(graph, rot, made.truth_translations)
        assert local.final_energy > 1.5 * best.final_energy  # a local minimum of E indeed
        cert = certify(graph, local.rotations, local.translations)
        assert not cert.certified
        if newton_ends == "short":
            assert not cert.stats["refine_converged"]
            assert np.isnan(cert.lambda_min) and "short of a stationary point" in cert.reason
            assert cert.summary().startswith("not certified: Newton's method on F stopped")
        else:
            assert np.isfinite(cert.gap) and "below the solution's" in cert.reason
            assert cert.stats["polish_energy"] == pytest.approx(best.final_energy, rel=1e-9)
    good = certify(graph, best.rotations, best.translations)
    assert good.certified, good.reason


def test_the_polish_must_reach_the_solution() -> None:
    """A certified F minimum whose polish ends elsewhere than the given energy is refused."""
    graph = _grid2d(poses=60)
    sol = solve_exact(graph)
    ok = certify(graph, sol.rotations, sol.translations)
    assert ok.certified
    low = certify(graph, sol.rotations, sol.translations, energy=0.99 * sol.final_energy)
    assert not low.certified and "above" in low.reason
    assert low.stats["polish_energy"] == pytest.approx(sol.final_energy, rel=1e-9)
    called = []

    def polish(r, t):
        called.append(1)
        return r, t, energy(graph, r, t)  # no polish at all: F's minimum is not E's

    unpolished = certify(graph, sol.rotations, sol.translations, polish=polish)
    assert called and not unpolished.certified and "above" in unpolished.reason


def test_not_applicable_says_why() -> None:
    import dataclasses

    city = generate_city(None, seed=0, gps_every=50, num_poses=50)
    graph = dataclasses.replace(city.graph, fixed_nodes=np.zeros(1, np.int32))
    cert = sesync_certificate(graph, city.truth_rotations, city.truth_translations)
    assert not cert.certified and "GPS" in cert.reason
    assert cert.summary() == f"not certified: {cert.reason}"


def test_a_3d_graph_with_gps_is_certified_with_the_earth_held() -> None:
    """3D with GPS at rank d: the certificate matrix without the earth's rotation rows and
    columns (a dense twin) gives the eigenvalue and its vector; F's excess over the bound is
    ``tr(G^T P^-1 G)`` (a dense twin), the same for Y turned by any rotation, and F less it is
    the value of a feasible point of the relaxation's dual (``Lambda_i - shift I`` for the
    graph's rotations, ``Q_ee - Q_er P^-1 Q_re`` for the earth's, ``Q - Lambda`` positive
    semidefinite: a dense twin); at F's minimum within the gap tolerance."""
    city = generate_city(None, seed=0, gps_every=20, num_poses=200)
    graph = city.graph
    prob = SyncProblem(graph)
    n, d, e = prob.n, prob.d, prob.earth
    y = prob.refine(prob.to_y(city.truth_rotations))[0]
    assert prob.refine_converged
    spec = prob.spectrum(y, eigenvector=True)
    assert spec.earth_held
    q = prob.q(np.eye(d * n))
    q = 0.5 * (q + q.T)
    lam = prob.lambda_blocks(y)
    keep = np.repeat(np.arange(n) != e, d)
    s_held = (q - sp.block_diag(list(lam)).toarray())[keep][:, keep]
    values, vectors = np.linalg.eigh(s_held)
    scale = np.abs(s_held).max()
    assert spec.lambda_min == pytest.approx(values[0], abs=1e-9 * scale)
    assert values[1] - values[0] > 1e-3 * abs(values[0])  # a simple eigenvalue: its vector
    assert spec.vector is not None and not np.any(spec.vector[~keep])
    assert abs(spec.vector[keep, 0] @ vectors[:, 0]) == pytest.approx(1.0, abs=1e-6)
    assert spec.objective == pytest.approx(prob.cost(y), rel=FLOAT64_IDENTITY * 1e3)
    assert 0.0 <= spec.objective - spec.lower_bound <= GAP_TOLERANCE * spec.objective
    q_re = q[keep][:, ~keep]
    y_r = y[keep]

    def twin_excess(shift: float) -> float:
        shifted = s_held + shift * np.eye(s_held.shape[0])
        g = shifted @ y_r + q_re
        return float(np.trace(g.T @ np.linalg.solve(shifted, g)))

    cs = prob._spectrum_setup()
    big = 1e-2
    cs["spd"].factor(big * cs["mask_fixed"], values=prob._certificate_values(lam, True))
    excess = prob._earth_fixed_gap(y, lam, big)
    assert excess == pytest.approx(twin_excess(big), rel=1e-6)
    assert excess > 1e-3 * big * d * n  # well away from 0: the comparison means something
    turn = np.asarray(_random_rotations(graph, 7)[0])
    assert prob._earth_fixed_gap(y @ turn, lam, big) == pytest.approx(excess, rel=1e-6)
    # the dual point: its value F - excess, Q minus it positive semidefinite
    shifted = s_held + big * np.eye(s_held.shape[0])
    dual = sp.block_diag(list(lam)).toarray()
    dual[keep] -= big * np.eye(d * n)[keep]
    dual[np.ix_(~keep, ~keep)] = q[~keep][:, ~keep] - q_re.T @ np.linalg.solve(shifted, q_re)
    # the twin's trace cancels terms of the size of tr(Q_ee) (the readings' positions squared)
    assert np.trace(dual) == pytest.approx(spec.objective - excess,
                                           abs=1e-10 * np.trace(q[~keep][:, ~keep]))
    assert np.linalg.eigvalsh(q - dual)[0] >= -1e-9 * scale
    cert = sesync_certificate(graph, city.truth_rotations, city.truth_translations)
    assert cert.certified and cert.relative_gap <= GAP_TOLERANCE
    assert cert.reason.startswith("S without the earth's rotation rows + ")


def test_a_graph_that_is_not_connected_is_refused_with_a_value_error() -> None:
    import dataclasses

    g = _grid2d(poses=20)
    SyncProblem(g)  # connected: accepted
    # one more pose that no constraint names
    lone = dataclasses.replace(
        g, node_ids=np.append(g.node_ids, g.node_ids.max() + 1),
        rotations=np.concatenate([g.rotations, np.eye(3)[None]]),
        translations=np.concatenate([g.translations, np.zeros((1, 3))]))
    with pytest.raises(ValueError, match="connected graph"):
        SyncProblem(lone)
    # two parts: the constraints between the first 10 poses and the rest dropped
    a, b = g.edge_nodes[:, 0], g.edge_nodes[:, 1]
    keep = (a < 10) == (b < 10)
    split = dataclasses.replace(
        g, edge_nodes=g.edge_nodes[keep], edge_rotations=g.edge_rotations[keep],
        edge_translations=g.edge_translations[keep],
        edge_information=g.edge_information[keep])
    assert np.unique(split.connected_components()).size == 2
    with pytest.raises(ValueError, match="connected graph"):
        SyncProblem(split)
    # the readings of a pose tie it to the others through the earth
    city = generate_city(None, seed=0, gps_every=1, num_poses=6)
    c = city.graph
    ok = (c.edge_nodes[:, 0] != 5) & (c.edge_nodes[:, 1] != 5)
    tied = dataclasses.replace(
        c, edge_nodes=c.edge_nodes[ok], edge_rotations=c.edge_rotations[ok],
        edge_translations=c.edge_translations[ok], edge_information=c.edge_information[ok])
    assert np.unique(tied.connected_components()).size == 1
    SyncProblem(tied)


# --------------------------------------------------------------------------- staircase
@pytest.mark.parametrize("make", [lambda: read_graph(DATA / "smallGrid3D.g2o"),
                                  lambda: _grid2d(poses=120, rot_sigma=0.1)], ids=["3D", "2D"])
def test_the_staircase_reaches_the_certified_optimum_from_random_rotations(make) -> None:
    graph = make()
    start = _random_rotations(graph, 7)
    start[0] = graph.rotations[0]
    ref = sesync_certificate(graph, *_chordal(graph))
    assert ref.certified
    rot, trans, info = staircase_start(graph, start, graph.translations)
    assert info["certified"]
    assert info["objective"] == pytest.approx(ref.objective, rel=1e-9)
    assert info["rank"] > (1 if graph.is_2d else 3)  # it had to climb
    assert np.abs(rot[0] - start[0]).max() <= FLOAT64_IDENTITY * 10  # the frame of the start
    cert = sesync_certificate(graph, rot, trans)
    assert cert.certified and cert.objective == pytest.approx(ref.objective, rel=1e-9)


def test_the_staircase_goes_on_from_a_failed_certificate_and_returns_its_certificate() -> None:
    """Given the failed certificate of its start, the staircase takes rank d's point and
    spectrum from it when its Newton's method converged, else refines from its point; the
    certificate it returns is that of its poses (:func:`sesync_certificate` of them
    certifies the same objective), and None when it does not certify."""
    import dataclasses

    graph = generate_grid("m3500b", seed=1, num_poses=300).graph  # large rotation noise
    problem = SyncProblem(graph)
    capped = sesync_certificate(graph, *_chordal(graph), problem=problem)
    assert not capped.certified and capped.point is not None
    assert not capped.stats["refine_converged"]  # Newton stopped at its cap: no eigenvalue
    assert np.isnan(capped.lambda_min) and capped.point[1].vector is None
    # the same point as if Newton had converged there: its spectrum with the eigenvector
    y_capped = capped.point[0]
    spec_capped = problem.spectrum(y_capped, eigenvector=True)
    assert spec_capped.lambda_min < 0 and spec_capped.vector is not None
    converged = dataclasses.replace(capped, lambda_min=spec_capped.lambda_min,
                                    stats={**capped.stats, "refine_converged": True},
                                    point=(y_capped, spec_capped))

    def seen(prob: SyncProblem) -> list[np.ndarray]:
        points: list[np.ndarray] = []

        def spy(fn):
            def call(y, *args, **kwargs):
                points.append(np.array(y, copy=True))
                return fn(y, *args, **kwargs)
            return call

        for name in ("refine", "spectrum"):
            setattr(prob, name, spy(getattr(prob, name)))
        return points

    def at(points: list[np.ndarray], y0: np.ndarray) -> bool:
        return any(y.shape == y0.shape and np.abs(y - y0).max() <= 1e-6 for y in points)

    y0 = problem.to_y(capped.rotations)
    points = seen(problem)
    # refined short of F's local minimum (at the cap) Newton goes on from the certificate's
    # point; converged, the point and spectrum are taken as they are
    for start, taken in ((capped, False), (converged, True)):
        points.clear()
        rot, trans, info = staircase_start(graph, start.rotations, start.translations,
                                           problem=problem, start=start)
        assert info["certified"] and at(points, y0) is not taken
        cert = info["certificate"]
        assert cert.certified
        assert np.array_equal(cert.rotations, rot) and np.array_equal(cert.translations, trans)
        again = sesync_certificate(graph, rot, trans)
        assert again.certified and again.objective == pytest.approx(cert.objective, rel=1e-9)
        assert cert.gap <= GAP_TOLERANCE * cert.objective


def test_a_converged_certificate_starts_the_staircase_as_it_is() -> None:
    """Newton's method that converges says so (``refine_converged``); a certified start is the
    staircase's rank d, reported in the frame of the given poses; a start whose rotations or
    gap tolerance are not the staircase's is not taken; a staircase that cannot certify
    (no rank to climb) returns no certificate."""
    graph = read_graph(DATA / "smallGrid3D.g2o")
    problem = SyncProblem(graph)
    start = sesync_certificate(graph, *_chordal(graph), problem=problem)
    assert start.certified and start.stats["refine_converged"] is True
    assert start.stats["gap_tolerance"] == GAP_TOLERANCE
    calls: list[str] = []
    refine = problem.refine

    def counted(*args, **kwargs):
        calls.append("refine")
        return refine(*args, **kwargs)

    problem.refine = counted  # type: ignore[method-assign]
    rot, trans, info = staircase_start(graph, start.rotations, start.translations,
                                       problem=problem, start=start)
    assert info["certified"] and info["rank"] == 3 and not calls
    cert = info["certificate"]
    assert cert.certified and cert.objective == start.objective and cert.gap == start.gap
    assert np.array_equal(cert.rotations, rot) and np.array_equal(cert.translations, trans)
    assert np.abs(rot - start.rotations).max() <= 1e-9
    # not the staircase's rotations, or another gap tolerance: Newton refines the given ones
    for rotations, tol in ((start.rotations.copy() @ _random_rotations(graph, 3)[:1],
                            GAP_TOLERANCE), (start.rotations, 10 * GAP_TOLERANCE)):
        calls.clear()
        staircase_start(graph, rotations, start.translations, problem=problem, start=start,
                        gap_tolerance=tol)
        assert calls
    # a local minimum at rank d and no rank to climb to: not certified, no certificate
    hard = generate_grid("m3500b", seed=1, num_poses=300).graph
    _, _, failed = staircase_start(hard, *_chordal(hard), max_rank=1)  # d = 1 (planar)
    assert not failed["certified"] and failed["certificate"] is None


def _chordal(graph: PoseGraph):
    from hybridpgo.initialization import chordal_initialization

    return chordal_initialization(graph)


# --------------------------------------------------------------------------- SparseSPD
@pytest.mark.parametrize("backend", ["splu", "cholmod"])
def test_sparse_spd_refuses_an_indefinite_matrix(backend, monkeypatch) -> None:
    if backend == "cholmod" and not _linear.cholmod_available():
        pytest.skip("cvxopt not installed")
    if backend == "splu":
        monkeypatch.setattr(_linear, "cholmod_available", lambda: False)
    rng = np.random.default_rng(0)
    a = sp.random(40, 40, density=0.1, random_state=1)
    a = sp.csr_matrix(a @ a.T + sp.identity(40))
    a.sort_indices()
    with pytest.raises(ValueError, match="canonical"):
        SparseSPD(sp.coo_matrix((np.ones(2), ([0, 0], [0, 0])), shape=(2, 2)))
    spd = SparseSPD(a)
    spd.factor()
    b = rng.standard_normal(40)
    assert np.abs(a @ spd.solve(b) - b).max() <= 1e3 * FLOAT64_IDENTITY * np.abs(b).max()
    lam = float(np.linalg.eigvalsh(a.toarray())[0])
    with pytest.raises(NotPositiveDefinite):
        spd.factor(-1.01 * lam)
    spd.factor(-0.99 * lam)
    # new values on the same pattern
    a2 = sp.csr_matrix(2.0 * a)
    a2.sort_indices()  # the canonical order of the values
    spd.factor(values=a2.data)
    assert np.abs(a2 @ spd.solve(b) - b).max() <= 1e3 * FLOAT64_IDENTITY * np.abs(b).max()


def _naive_permuted_lower(a, old_at: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lower triangle of ``P A P^T`` by SciPy (columns, rows, place of each value in
    ``a.data.ravel()``): a matrix of entry numbers, permuted, lower triangle taken."""
    ids = a.copy()
    ids.data = np.arange(1, a.data.size + 1, dtype=np.float64).reshape(a.data.shape)
    low = sp.tril(sp.csc_matrix(ids)[old_at][:, old_at], format="csc")
    low.sort_indices()
    return low.indptr, low.indices, np.asarray(low.data, np.int64) - 1


@pytest.mark.parametrize("fmt", ["csr", "csc", "coo", "bsr"])
@pytest.mark.parametrize("block", [1, 3])
def test_sparse_spd_pattern_and_solve_in_every_format(fmt: str, block: int) -> None:
    # a block matrix on a random graph (SPD: diagonally dominant); the pattern and the place
    # of every value against SciPy's permutation and lower triangle
    rng = np.random.default_rng(block)
    nb = 30
    edges = {(int(i), int(j)) for i, j in rng.integers(0, nb, (60, 2)) if i != j}
    blocks = {(i, i): np.eye(block) * 50.0 for i in range(nb)}
    for i, j in edges:
        w = rng.standard_normal((block, block))
        blocks[(i, j)] = blocks.get((i, j), 0) + w
        blocks[(j, i)] = blocks.get((j, i), 0) + w.T
    dense = np.zeros((nb * block, nb * block))
    for (i, j), w in blocks.items():
        dense[i * block:(i + 1) * block, j * block:(j + 1) * block] += w
    a = sp.bsr_matrix(dense, blocksize=(block, block)) if fmt == "bsr" else (
        sp.csr_matrix(dense).asformat(fmt))
    a.sum_duplicates()
    spd = SparseSPD(a, block)
    ptr, _, src = _naive_permuted_lower(a, spd._old_at)
    assert np.array_equal(spd._diag, ptr[:-1]) and np.array_equal(spd._source, src)
    b = rng.standard_normal(nb * block)
    spd.factor()
    x = spd.solve(b)
    assert np.abs(dense @ x - b).max() <= 1e3 * FLOAT64_IDENTITY * np.abs(b).max()
    # new values, in the order of a.data: twice the matrix
    spd.factor(values=2.0 * np.asarray(a.data).ravel())
    assert (np.abs(2.0 * dense @ spd.solve(b) - b).max()
            <= 1e3 * FLOAT64_IDENTITY * np.abs(b).max())


def test_sparse_spd_refuses_a_missing_diagonal_or_another_format() -> None:
    a = sp.csr_matrix(np.array([[2.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 3.0]]))
    a.eliminate_zeros()
    with pytest.raises(ValueError, match="diagonal entry"):
        SparseSPD(a)
    with pytest.raises(ValueError, match="CSR, CSC, COO or BSR"):
        SparseSPD(sp.lil_matrix(np.eye(3)))


def _svd_polar(b: np.ndarray) -> np.ndarray:
    u, _, vh = np.linalg.svd(b, full_matrices=False)
    return u @ vh


@pytest.mark.parametrize("p", [3, 4, 6])
def test_polar_rows_is_the_svds_polar_factor(p: int) -> None:
    """Newton's polar iteration against the SVD's ``u @ vh``, from near-orthonormal blocks
    (the staircase's retraction), Gaussian and badly scaled ones; blocks with nearly dependent
    rows are refused (``ok`` False) and ``retract`` gives them the SVD's factor."""
    from hybridpgo._sync_kernels import POLAR_SINGULAR, polar_rows

    rng = np.random.default_rng(p)
    n = 400
    q = _svd_polar(rng.standard_normal((n, 3, p)))
    sig = np.array([1.0, 1.0, 1e-7])[None, :, None]
    families = {
        "near": q + 0.05 * rng.standard_normal((n, 3, p)),
        "gauss": rng.standard_normal((n, 3, p)),
        "large": 1e3 * rng.standard_normal((n, 3, p)),
        "small": 1e-3 * rng.standard_normal((n, 3, p)),
        "dependent": _svd_polar(rng.standard_normal((n, 3, 3))) @ (sig * q),
    }
    # blocks that are no polar factor's: zero, NaN, inf
    for k, value in enumerate((0.0, np.nan, np.inf)):
        families["dependent"][k] = value
    for name, b in families.items():
        out, ok = np.full_like(b, np.nan), np.empty(n, np.bool_)
        polar_rows(b, out, ok)
        if name == "dependent":
            assert not ok.any()
            continue
        # refused exactly where the rows are nearly dependent (POLAR_SINGULAR)
        gram_b = b @ np.swapaxes(b, 1, 2)
        ratio = np.linalg.det(gram_b) / (np.trace(gram_b, axis1=1, axis2=2) / 3.0) ** 3
        clear = np.abs(np.log(ratio / POLAR_SINGULAR)) > 1e-6
        assert np.array_equal(ok[clear], (ratio >= POLAR_SINGULAR)[clear]), name
        assert ok.mean() > (0.999 if name == "near" else 0.9), name
        out, ref = out[ok], _svd_polar(b[ok])
        # the polar factor's condition: about s_1 / (s_2 + s_3) for a square block, s_1 / s_3
        # for the rows of a wider one
        s = np.linalg.svd(b[ok], compute_uv=False)
        cond = s[:, 0] / (s[:, -1] + s[:, -2]) if p == 3 else s[:, 0] / s[:, -1]
        err = np.abs(out - ref).max(axis=(1, 2))
        assert np.all(err <= FLOAT64_IDENTITY * np.maximum(cond, 1.0)), name
        gram = out @ np.swapaxes(out, 1, 2)
        np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), rtol=0,
                                   atol=ORTHONORMAL * 10)
    # the retraction: the kernel where it converges, the SVD where it refuses
    prob = SyncProblem(_tiny3d())
    v = np.concatenate([q[:prob.n - 1], families["dependent"][-1:]]).reshape(3 * prob.n, p)
    np.testing.assert_allclose(prob.retract(v), _svd_polar(v.reshape(prob.n, 3, p)).reshape(
        v.shape), rtol=0, atol=FLOAT64_IDENTITY)


def test_newton_on_f_does_not_retry_an_indefinite_undamped_hessian_every_step(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Where F's undamped Hessian is indefinite (here: every undamped factorization refused),
    Newton's method keeps the floor's damping until a step meets its model, instead of
    retrying mu = 0 after every damped step (a failed factorization costs about as much as a
    good one): at most one failed factorization for three good ones."""
    graph = read_graph(bundled_path("garage.g2o"))
    prob = SyncProblem(graph)
    prob._newton_setup()  # the Newton system's analysis, before the stub
    outcomes: list[bool] = []
    factor = _linear.SparseSPD.factor

    def indefinite_unless_damped(self: SparseSPD, shift: object = 0.0, check: bool = False,
                                 values: np.ndarray | None = None) -> None:
        if not np.any(np.asarray(shift)):
            outcomes.append(False)
            raise NotPositiveDefinite("stub: indefinite")
        outcomes.append(True)
        return factor(self, shift, check, values)

    monkeypatch.setattr(_linear.SparseSPD, "factor", indefinite_unless_damped)
    start = prob.to_y(graph.rotations)
    _, f, count = prob.refine(start)
    # every factorization counted, F lowered (30 damped ones do not reach garage's minimum)
    assert count == len(outcomes) and f < prob.cost(start)
    assert 3 * outcomes.count(False) <= outcomes.count(True), outcomes
