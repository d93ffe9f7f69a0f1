"""The default pipeline's certificate (``AutoConfig.certify``, ``certify_first``): the first
start is certified before any sweep and, when it is, LM from the certified start is the answer;
without the early try the first polished start is certified and, when it is, no other start is
polished; the result is the one every start gives;
a start in a local minimum is not certified and the other starts run; the certificate's
eigenvalue agrees with a dense decomposition."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest
from graphs import planar_rotations, with_gps

from hybridpgo import read_graph
from hybridpgo.certificate import SyncProblem
from hybridpgo.cli import main
from hybridpgo.generate import generate_city, generate_grid
from hybridpgo.graph import PoseGraph
from hybridpgo.solvers import AutoConfig
from hybridpgo.solvers.auto import solve_auto
from hybridpgo.solvers.gauss_newton import solve_exact

#: Energies of the same minimum reached from two starts (the pipeline's tie rule).
SAME = 1e-9


def _grid2d() -> PoseGraph:
    return generate_grid("m3500", seed=0, num_poses=120, rot_sigma_rad=0.05).graph


def _dense_lambda_min(graph: PoseGraph, rotations: np.ndarray) -> tuple[float, float]:
    """lambda_min of S = Q - Lambda at F's Newton-refined rotations, by a dense eigvalsh of
    the matrix built column by column from its products, and its largest |eigenvalue|."""
    prob = SyncProblem(graph)
    y = prob.refine(prob.to_y(rotations))[0]
    eye = np.eye(prob.d * prob.n).astype(y.dtype)
    s = prob.certificate_product(y, eye)
    vals = np.linalg.eigvalsh(0.5 * (s + s.conj().T))
    return float(vals[0]), float(np.abs(vals).max())


GRAPHS = pytest.mark.parametrize("make", [_grid2d, lambda: read_graph(
    Path(__file__).parent / "data" / "smallGrid3D.g2o"), lambda: with_gps(_grid2d(), every=10)],
    ids=["grid2d", "smallGrid3D", "grid2d+GPS"])


@GRAPHS
def test_the_default_certifies_its_first_start_before_any_sweep(make) -> None:
    """The early try: the chordal start's rotations refined on F and certified, LM from the
    certified start is the answer: no sweep, no other start, the energy every start gives."""
    graph = make()
    res = solve_auto(graph)
    every = solve_auto(graph, AutoConfig(certify=False))
    cert = res.stats["certificate"]
    assert cert["computed"] and cert["certified"], cert["summary"]
    assert cert["summary"].startswith("certified global optimum (gap ≤ ")
    assert 0.0 <= cert["relative_gap"] <= 1e-6
    assert cert["start"] == "chordal" and cert["polished_before"] == 0
    assert res.stats["start"] == "certified start" and res.stats["init"] == "chordal"
    assert res.stats["finalists"] == ["certified start"] and res.stats["polished_starts"] == 1
    assert set(res.stats["candidates"]) == {"chordal", "certified start"}
    assert res.stats["sweeps"] == 0 and res.timings["sweeps"] == 0.0
    assert res.stats["relaxation"] == {"ran": False, "why": "the winner is certified"}
    assert "no other start polished" in res.stats["reason"]
    assert abs(cert["polish_energy"] - res.final_energy) == 0.0
    assert abs(res.final_energy - every.final_energy) <= SAME * every.final_energy
    assert every.stats["polished_starts"] > 1
    # the eigenvalue the certificate found, against a dense decomposition of S
    exact, norm = _dense_lambda_min(graph, res.rotations)
    assert cert["lambda_min"] == pytest.approx(exact, abs=1e-9 * norm)
    assert res.timings["certificate"] == cert["seconds"] > 0.0


@GRAPHS
def test_a_certified_start_is_the_only_one_polished(make) -> None:
    """Without the early try: the starts are swept, the first polished one is certified and no
    other is polished."""
    graph = make()
    res = solve_auto(graph, AutoConfig(certify_first=False))
    every = solve_auto(graph, AutoConfig(certify=False))
    cert = res.stats["certificate"]
    assert cert["computed"] and cert["certified"], cert["summary"]
    assert cert["summary"].startswith("certified global optimum (gap ≤ ")
    assert 0.0 <= cert["relative_gap"] <= 1e-6
    # one start polished (plus the certificate's own check from the certified start) ...
    assert res.stats["polished_starts"] == 1 and cert["polished_before"] == 1
    assert res.stats["finalists"] == every.stats["finalists"][:1]
    assert res.stats["relaxation"] == {"ran": False, "why": "the winner is certified"}
    assert "certified start" not in res.stats["candidates"]  # its polish ties: not the result
    assert abs(cert["polish_energy"] - res.final_energy) <= SAME * res.final_energy
    # ... where every start is polished without the certificate, to the same energy
    assert every.stats["polished_starts"] > 1
    assert every.stats["certificate"] == {"computed": False, "certified": False, "why": "off",
                                          "summary": "not certified: off", "seconds": 0.0}
    assert abs(res.final_energy - every.final_energy) <= SAME * every.final_energy
    # the eigenvalue the certificate found, against a dense decomposition of S
    exact, norm = _dense_lambda_min(graph, res.rotations)
    assert cert["lambda_min"] == pytest.approx(exact, abs=1e-9 * norm)
    assert res.timings["certificate"] == cert["seconds"] > 0.0
    assert "certified global optimum" in res.stats["reason"]


def _trapped(poses: int, rot_sigma: float) -> tuple[PoseGraph, float, np.ndarray]:
    """A grid whose file vertices are a local minimum of E (LM from scrambled yaws), the
    optimum's energy (LM from the truth) and the local minimum's rotations."""
    made = generate_grid("m3500", seed=0, num_poses=poses, rot_sigma_rad=rot_sigma)
    graph = made.graph
    rot = made.truth_rotations.copy()
    rot[1:] = planar_rotations(np.random.default_rng(5).uniform(-np.pi, np.pi, graph.num_nodes))[1:]
    local = solve_exact(graph, rot, made.truth_translations)
    best = solve_exact(graph, made.truth_rotations, made.truth_translations)
    assert local.final_energy > 1.5 * best.final_energy  # a local minimum indeed
    return graph.with_poses(local.rotations, local.translations), best.final_energy, \
        local.rotations


def _no_sweeps(*inits: str) -> AutoConfig:
    base = AutoConfig(inits=inits)  # type: ignore[arg-type]
    return dataclasses.replace(base, sweeps=dataclasses.replace(base.sweeps, sweeps=0))


def test_a_start_in_a_local_minimum_is_not_certified_and_the_others_run() -> None:
    """The file's vertices (a local minimum, lower than the tree start without sweeps) rank
    first; F refined from there is not F's minimum: its certificate fails (Newton's method
    stops at its cap short of a stationary point of F), the tree start is polished too and
    the winner is certified."""
    trapped, optimum, local = _trapped(120, 0.15)
    late = dataclasses.replace(_no_sweeps("file", "tree"), certify_first=False)
    res = solve_auto(trapped, late)
    cert = res.stats["certificate"]
    assert res.stats["finalists"] == ["file", "tree"]  # the trapped start ranks first
    assert cert["first"]["start"] == "file"
    assert cert["first"]["summary"].startswith("not certified: Newton's method on F stopped")
    assert res.stats["polished_starts"] == 2
    assert cert["certified"] and cert["start"] == "tree" and res.stats["start"] == "tree"
    assert abs(res.final_energy - optimum) <= SAME * optimum
    exact, norm = _dense_lambda_min(trapped, local)
    assert exact < -1e-6 * norm  # the dense decomposition agrees: S is indefinite there
    # the early try from the same start: the staircase escapes F's local minimum
    early = solve_auto(trapped, _no_sweeps("file", "tree"))
    assert early.stats["start"] == "certified start"
    assert early.stats["certificate"]["staircase"]["certified"]
    assert abs(early.final_energy - optimum) <= SAME * optimum


def test_a_certified_start_whose_polish_ends_lower_is_the_solution() -> None:
    """From the trapped file vertices Newton's method on F reaches F's certified minimum,
    and LM from there ends below the file's polish: that polish is the result, certified,
    and no other start is polished."""
    trapped, optimum, _ = _trapped(60, 0.2)
    late = dataclasses.replace(_no_sweeps("file", "chordal", "tree"), certify_first=False)
    res = solve_auto(trapped, late)
    cert = res.stats["certificate"]
    assert res.stats["finalists"] == ["file"] and res.stats["polished_starts"] == 1
    assert cert["certified"] and cert["start"] == "certified start"
    assert res.stats["start"] == "certified start" and "certified start" in res.stats["reason"]
    assert abs(res.final_energy - optimum) <= SAME * optimum
    assert res.stats["candidates"]["file"]["final_energy"] > 1.5 * optimum
    # the early try reaches the same certified start first: the file's poses never polished
    early = solve_auto(trapped, _no_sweeps("file", "chordal", "tree"))
    assert early.stats["start"] == "certified start" and early.stats["certificate"]["certified"]
    assert early.final_energy == pytest.approx(res.final_energy, rel=SAME)
    assert "final_energy" not in early.stats["candidates"]["file"]


def test_the_large_graph_policy_and_other_models_say_why_not() -> None:
    graph = _grid2d()
    large = solve_auto(graph, AutoConfig(large_poses=10, certify_first=False))
    assert large.stats["certificate"]["why"] == "large-graph policy"
    assert large.stats["polished_starts"] == 1
    # no early try under the large-graph policy either (its memory at 1M poses)
    default = solve_auto(graph, AutoConfig(large_poses=10))
    assert default.stats["certificate"]["why"] == "large-graph policy"
    assert "early" not in default.stats["certificate"]
    # a 3D graph with GPS: certified with the earth frame's rotation held, one start
    gps = solve_auto(generate_city(None, seed=0, gps_every=20, num_poses=200).graph)
    assert gps.stats["certificate"]["certified"]
    assert gps.stats["polished_starts"] == 1
    fixed = dataclasses.replace(with_gps(graph, every=10), fixed_nodes=np.zeros(1, np.int32))
    assert solve_auto(fixed).stats["certificate"]["why"] == (
        "GPS constraints and a fixed pose (not in SE-Sync's model)")


def test_the_cli_summary_says_whether_it_is_certified(capsys, data_dir: Path,
                                                      tmp_path: Path) -> None:
    code = main(["optimize", str(data_dir / "smallGrid3D.g2o"), "-o", str(tmp_path / "o.g2o")])
    out, err = capsys.readouterr()
    assert code == 0, err
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("certificate"))
    assert "certified global optimum (gap ≤ " in line


def test_a_city_with_little_noise_is_certified_at_the_smallest_shift() -> None:
    """A generated city: F is small next to M's entries (F/(d n) ~ 0.03, information ~1e6),
    so no shift the factorization resolves bounds the gap within 1e-6 of F; the smallest one
    certifies within FLOOR_GAP_TOLERANCE (the gap the summary reports), the early try's polish
    is the answer and a dense decomposition agrees that S has no negative eigenvalue."""
    from hybridpgo.certificate import FLOOR_GAP_TOLERANCE, GAP_TOLERANCE

    graph = generate_city(None, seed=0, gps_every=0, num_poses=800).graph
    assert graph.num_edges > graph.num_nodes  # loops: F is not 0
    res = solve_auto(graph)
    cert = res.stats["certificate"]
    assert cert["certified"] and res.stats["start"] == "certified start", cert["summary"]
    assert GAP_TOLERANCE < cert["relative_gap"] <= FLOOR_GAP_TOLERANCE
    every = solve_auto(graph, AutoConfig(certify=False))
    assert abs(res.final_energy - every.final_energy) <= SAME * every.final_energy
    exact, norm = _dense_lambda_min(graph, res.rotations)
    assert exact >= -1e-12 * norm


def test_a_graph_without_loops_says_why_it_is_not_certified() -> None:
    """A tree of constraints: F's minimum is 0 up to rounding, so no gap relative to it."""
    graph = generate_city(None, seed=0, gps_every=0, num_poses=200).graph
    assert graph.num_edges == graph.num_nodes - 1
    cert = solve_auto(graph).stats["certificate"]
    assert not cert["certified"]
    assert "positive semidefinite as far as float64 resolves" in cert["summary"]


def test_the_staircase_certifies_a_start_that_newton_leaves_in_a_local_minimum() -> None:
    """Large rotation noise: Newton's method on F from the chordal start stops at its cap
    short of a stationary point; the staircase's Newton steps go on from there to a local
    minimum of F at rank d (a negative eigenvalue), SE-Sync's staircase escapes it at rank 2
    and its certified rounding is the certified start, reaching what every start polished
    reaches."""
    graph = generate_grid("m3500b", seed=1, num_poses=300).graph
    res = solve_auto(graph)
    cert = res.stats["certificate"]
    assert cert["certified"] and res.stats["start"] == "certified start", cert["summary"]
    stair = cert["staircase"]
    assert stair["certified"] and stair["rank"] == 2
    assert stair["rank_d"].startswith("not certified: Newton's method on F stopped")
    assert stair["ranks"][0]["rank"] == 1 and stair["ranks"][0]["lambda_min"] < 0  # F's local min
    assert "Riemannian staircase to rank 2" in res.stats["reason"]
    every = solve_auto(graph, AutoConfig(certify=False))
    assert res.final_energy <= every.final_energy * (1.0 + SAME)


def test_the_staircase_goes_on_from_the_certificates_point_on_its_problem(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The early try builds SE-Sync's problem once: the certificate and the staircase share it,
    the staircase goes on from the failed certificate (its refined rotations), its certified
    rounding's certificate is the answer's (no second certificate call), and the problem's
    set-up counts in the certificate's seconds, not in the polish's (a clock that jumps by
    SETUP while the problem is built: no wall time involved)."""
    import types

    import hybridpgo.certificate as certificate
    import hybridpgo.solvers.auto as auto_module

    setup = 1e6
    shift = [0.0]
    clock = types.SimpleNamespace(perf_counter=lambda: time.perf_counter() + shift[0])
    monkeypatch.setattr(certificate, "time", clock)
    monkeypatch.setattr(auto_module, "time", clock)
    graph = generate_grid("m3500b", seed=1, num_poses=300).graph
    problems: list[certificate.SyncProblem] = []
    certificates: list[certificate.Certificate] = []
    stairs: list[tuple[object, object]] = []
    init = certificate.SyncProblem.__init__
    sesync = certificate.sesync_certificate
    staircase = certificate.staircase_start

    def counted(self: certificate.SyncProblem, *args: object, **kwargs: object) -> None:
        init(self, *args, **kwargs)
        if args[0] is graph:  # not the kernels' warm-up problem
            problems.append(self)
            shift[0] += setup

    def seen_certificate(*args: object, **kwargs: object) -> certificate.Certificate:
        out = sesync(*args, **kwargs)
        if args[0] is graph:
            certificates.append(out)
        return out

    def seen_staircase(*args: object, **kwargs: object) -> object:
        stairs.append((args[1], kwargs.get("problem")))
        return staircase(*args, **kwargs)

    monkeypatch.setattr(certificate.SyncProblem, "__init__", counted)
    monkeypatch.setattr(certificate, "sesync_certificate", seen_certificate)
    monkeypatch.setattr(certificate, "staircase_start", seen_staircase)
    res = solve_auto(graph)
    cert = res.stats["certificate"]
    assert cert["certified"] and "staircase" in cert
    # one problem, one staircase, one certificate call: the certificate of the staircase's
    # certified rounding comes with it
    assert len(problems) == 1 and len(stairs) == 1 and len(certificates) == 1
    rotations, problem = stairs[0]
    assert problem is problems[0] and rotations is certificates[0].rotations
    assert setup + cert["staircase"]["seconds"] <= cert["seconds"] < 2 * setup
    assert 0.0 <= res.timings["polish"] < setup


def test_a_failed_staircase_leaves_the_pipeline_to_the_starts() -> None:
    graph = generate_grid("m3500c", seed=1, num_poses=400).graph
    res = solve_auto(graph)
    early = res.stats["certificate"]["early"]
    assert early["summary"].startswith("not certified: Newton's method on F stopped")
    assert early["staircase"]["certified"] is False and early["staircase"]["rank"] > 2
    assert res.stats["start"] != "certified start" and res.stats["polished_starts"] > 1
    every = solve_auto(graph, AutoConfig(certify=False))
    assert abs(res.final_energy - every.final_energy) <= SAME * every.final_energy


def test_an_early_try_that_fails_leaves_the_pipeline_to_the_starts(monkeypatch) -> None:
    """A certificate that raises, or a first start that cannot be computed: the early try says
    why and the starts run; the answer is the every-start pipeline's."""
    import hybridpgo.certificate as certificate
    import hybridpgo.solvers.auto as auto

    graph = _grid2d()
    every = solve_auto(graph, AutoConfig(certify=False))

    def broken(*args, **kwargs):
        raise ValueError("no factorization today")

    certificate.ensure_compiled(graph.is_2d)  # its warm-up certifies a tiny graph
    with monkeypatch.context() as m:
        m.setattr(certificate, "sesync_certificate", broken)
        res = solve_auto(graph)
    assert res.stats["certificate"]["early"]["summary"] == (
        "not certified: the certificate failed: no factorization today")
    assert res.stats["start"] != "certified start" and res.stats["polished_starts"] >= 1
    assert abs(res.final_energy - every.final_energy) <= SAME * every.final_energy

    real = auto.initial_locals

    def no_chordal(graph, tree, init="tree"):
        if init == "chordal":
            raise np.linalg.LinAlgError("singular")
        return real(graph, tree, init)

    monkeypatch.setattr(auto, "initial_locals", no_chordal)
    res = solve_auto(graph)
    early = res.stats["certificate"]["early"]
    assert early["start"] == "chordal" and "the start chordal failed: singular" in early["summary"]
    assert res.stats["init"] != "chordal"
    assert "start: singular" in res.stats["candidates"]["chordal"]["error"]


def test_the_early_newton_cap_shrinks_with_the_graph() -> None:
    from hybridpgo.certificate import NEWTON_FACTORIZATIONS
    from hybridpgo.solvers.auto import EARLY_NEWTON_MIN, EARLY_NEWTON_WORK, _early_newton_cap

    assert _early_newton_cap(3500) == NEWTON_FACTORIZATIONS
    assert _early_newton_cap(EARLY_NEWTON_WORK // NEWTON_FACTORIZATIONS) == NEWTON_FACTORIZATIONS
    assert _early_newton_cap(100_000) == EARLY_NEWTON_WORK // 100_000 < NEWTON_FACTORIZATIONS
    assert _early_newton_cap(10**7) == EARLY_NEWTON_MIN


def test_a_capped_early_newton_polishes_the_start_first_and_certifies_there(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the early try's Newton method stops at its cap short of F's minimum (here a cap
    of 4 on a grid whose Newton method needs 16 from the chordal start), LM polishes the start
    and the certificate is computed at that optimum: certified, one start, the every-start
    pipeline's energy; without the cap the same answer comes through Newton's method."""
    import hybridpgo.solvers.auto as auto

    graph = generate_grid("m3500a", seed=1, num_poses=1000).graph
    every = solve_auto(graph, AutoConfig(certify=False))
    plain = solve_auto(graph)
    assert "polished_first" not in plain.stats["certificate"]
    monkeypatch.setattr(auto, "EARLY_NEWTON_WORK", 4 * graph.num_nodes)
    res = solve_auto(graph)
    cert = res.stats["certificate"]
    first = cert["polished_first"]
    assert first["newton_cap"] == 4 and first["newton_capped"].startswith("not certified")
    assert cert["certified"] and res.stats["start"] == "certified start"
    assert cert["newton_iterations"] < 16  # refined from LM's optimum, not from the start
    assert "LM polished the start first" in res.stats["reason"]
    assert cert["refine_converged"] is True and res.stats["polished_starts"] == 1
    assert abs(first["energy"] - every.final_energy) <= SAME * every.final_energy
    for r in (res, plain):
        assert abs(r.final_energy - every.final_energy) <= SAME * every.final_energy


def test_a_polished_first_certificate_that_raises_leaves_the_capped_try_to_the_staircase(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The polished start's certificate raises: the early try goes on from the capped try's
    certificate (the staircase's Newton method continues from its point and certifies here),
    says why in ``polished_first``, and the answer is the every-start pipeline's."""
    import hybridpgo.certificate as certificate
    import hybridpgo.solvers.auto as auto

    graph = generate_grid("m3500a", seed=1, num_poses=1000).graph
    every = solve_auto(graph, AutoConfig(certify=False))
    monkeypatch.setattr(auto, "EARLY_NEWTON_WORK", 4 * graph.num_nodes)
    real = certificate.sesync_certificate
    calls = []

    def second_raises(*args, **kwargs):
        if args[0] is graph:  # not the kernels' warm-up
            calls.append(kwargs.get("max_factorizations"))
            if len(calls) == 2:
                raise ValueError("no factorization today")
        return real(*args, **kwargs)

    monkeypatch.setattr(certificate, "sesync_certificate", second_raises)
    res = solve_auto(graph)
    cert = res.stats["certificate"]
    assert calls == [4, None]
    assert "no factorization today" in cert["polished_first"]["error"]
    assert cert["certified"] and cert["staircase"]["certified"]
    assert abs(res.final_energy - every.final_energy) <= SAME * every.final_energy


def test_a_winner_at_the_first_finalists_optimum_is_not_certified_again(monkeypatch) -> None:
    """A 3D city with GPS that the certificate does not hold for: every start is polished to
    the same optimum, and the winner (another start, at the first polished finalist's
    energy within the tie) keeps the first finalist's verdict instead of a certificate of its
    own (the same rotations refine to the same point of F)."""
    import hybridpgo.certificate as certificate

    calls: list[str] = []
    real = certificate.certify

    def counted(*args, **kwargs):
        calls.append("certify")
        return real(*args, **kwargs)

    monkeypatch.setattr(certificate, "certify", counted)
    res = solve_auto(generate_city(None, seed=0, gps_every=10, num_poses=100).graph)
    cert = res.stats["certificate"]
    assert not cert["certified"] and cert["lambda_min"] < 0
    energies = [c["final_energy"] for c in res.stats["candidates"].values()]
    assert max(energies) - min(energies) <= 1e-9 * min(energies)
    assert calls == ["certify"] and "first" not in cert


def test_the_same_optimum_is_the_first_finalists_energy_within_the_tie() -> None:
    from hybridpgo.solvers.auto import _Candidate, _same_optimum

    def cand(label: str, energy: float) -> _Candidate:
        c = _Candidate("chordal", label)
        c.history.append(energy)
        return c

    first = {"computed": True, "certified": False, "start": "tree"}
    tree, file_ = cand("tree", 100.0), cand("file", 100.0 * (1 - 5e-10))
    assert tree.energy == 100.0 and file_.energy < tree.energy
    assert _same_optimum(first, [tree, file_], file_)
    lower = cand("file", 100.0 * (1 - 2e-9))
    assert not _same_optimum(first, [tree, lower], lower)
    assert not _same_optimum({"computed": False, "why": "large-graph policy"}, [tree], tree)
