"""The default pipeline: a certified start when there is one, else choose a start, sweep while
it pays, polish to convergence.

:func:`solve_auto` is what ``hybridpgo optimize`` and :func:`hybridpgo.optimize` run when no
solver is named (``--solver auto``).  The paper's pure method stays ``--solver hybrid``.

0. **Early try** (``AutoConfig.certify_first``, where the certificate (5) applies): the first
   start of ``inits`` (the chordal one by default) alone; Newton's method on SE-Sync's
   objective F refines its rotations (:func:`hybridpgo.certificate.sesync_certificate`), the
   certificate tests F's global minimum there and, when it holds, LM from that certified start
   is the answer: no sweep, no other start, no relaxation check (``stats["start"]`` is
   ``"certified start"``; certified by construction: the polish from F's certified minimum).
   When Newton's method ends in a local minimum of F (the certificate matrix has a negative
   eigenvalue: generated grids with large rotation noise), or stops at its cap short of a
   stationary point (no eigenvalue is computed there), SE-Sync's Riemannian staircase
   (:func:`hybridpgo.certificate.staircase_start`) escapes it through ranks d+1.. d+3 and a
   certified rounding is the certified start (``stats["certificate"]["staircase"]``); on a 3D
   graph with GPS it stays at rank d (above it the earth frame's rotation is lifted, where
   the certificate matrix is ill-conditioned).
   Newton's method there makes at most ``EARLY_NEWTON_WORK / N`` factorizations on N poses
   (:func:`_early_newton_cap`); on a graph where that is below the certificate's own cap and
   Newton stops without converging and uncertified, LM polishes the start first and the
   certificate is computed at that optimum (``stats["certificate"]["polished_first"]``).
   On every benchmark file this is the whole solve (one factorization of F's Newton system on
   most, then LM's usual iterations).  When the certificate fails (or the polish from the
   certified start does not converge), 1-5 run, the start already computed is reused, and
   ``stats["certificate"]["early"]`` keeps the try's verdict and seconds.
1. **Starts.**  Every start of ``AutoConfig.inits`` that applies is computed: the chordal
   relaxation (one sparse factorization for the rotations, one for the positions), the tree
   concatenation (the paper's, free) and the file's vertices (when the file has them).
2. **Sweeps while they pay.**  From each start, hybrid sweeps (paper Algorithm 1, the paper's
   temperature schedule) until one lowers the energy by less than ``sweep_tolerance``
   (relative) or raises it, at most ``max_sweeps``.  The best poses seen are kept, so a start
   the sweeps cannot improve (typically the chordal one: the optimum is not a fixed point of
   the sweeps) keeps its own poses.
3. **Polish.**  The candidates are ranked: the starts after their sweeps (lowest energy
   first), then each swept start as it was (``polish_unswept``: sweeps that pay can still carry
   a start out of the optimum's basin).  The first ``finalists`` (default: all) are polished
   with Levenberg-Marquardt to convergence (``energy_tolerance``); the lowest polished energy
   wins (ties: the earlier candidate); a certified first finalist (5) stops the polish
   there.  Polishing more than one start is the guard against
   local minima (benchmarks/auto.py measures every case: on ``sphere_bignoise`` the tree
   start's sweeps and polish end 13% above the minimum the chordal start reaches; on M3500
   with 20 degrees of added yaw noise only LM from the file's own vertices reaches the
   optimum).  Cost
   guard: a runner-up's polish gets at most ``finalist_budget`` times the iterations the best
   polish took (at least :data:`MIN_FINALIST_ITERATIONS`); it goes on to convergence only if
   it is then below the best, else it is reported as cut.

4. **Planar relaxation check** (``AutoConfig.relaxation``; 2D graphs without GPS): the
   rank-2 relaxation of the chordal cost (SE-Sync's, complex form) is minimized from the
   winner's poses.  Where the winner is the global optimum the relaxation stays by it (its
   rounded rotations move <= 0.01 rad on every such benchmark graph) and nothing more runs;
   where the polish ended in a local minimum the extra rank opens a path down and the rounded
   rotations differ by radians somewhere (m3500c: 3.1 rad): that start is polished too and the
   lower energy wins (``stats["relaxation"]``).  It is a check of the chordal cost, not a
   certificate of E's global optimum.

5. **Certificate** (``AutoConfig.certify``; graphs SE-Sync's model describes: no robust
   kernel, at most one FIX node and none with GPS; GPS readings are constraints from an
   earth frame, :mod:`hybridpgo.certificate`): the first polished
   finalist is certified (:func:`hybridpgo.certificate.certify`: SE-Sync's objective refined
   from its rotations by Newton's method, its global minimum certified by the smallest
   eigenvalue of the certificate matrix, and LM from that certified start ends at the same
   energy).  When it is,
   the other finalists are not polished and the relaxation check (4) is skipped; when LM from
   the certified start converges lower, that polish is the result.  Otherwise the other
   finalists are polished as in 3 and the winner is certified (a winner at the first
   finalist's energy, within the tie, keeps the first finalist's verdict: the same rotations
   refine to the same point of F; ``stats["certificate"]["start"]`` names the finalist
   certified).  ``stats["certificate"]``:
   ``certified``, ``summary`` ("certified global optimum (gap ≤ ...)" or "not certified ..."),
   ``lambda_min``, ``relative_gap``, ``objective`` (SE-Sync's), ``seconds``, or ``why`` it
   was not computed; ``stats["polished_starts"]`` counts the finalists polished.

**Large graphs** (``AutoConfig.large_poses``, default 200 000 poses and more): every start,
sweep and polish costs seconds to minutes, so only the first start of ``large_inits`` that can
be computed is used, with at most ``large_max_sweeps`` sweeps and one polish (no runner-up, no
unswept twin, no certificate, no early try: measured on a 1M-pose city, the early try did not
certify and cost two more minutes and a peak of 12 GB);
``stats["policy"]`` is ``"large"`` (else ``"full"``) and the
reason says so.
benchmarks/scale.py measures what this costs against the full policy on a 100k-pose city.

5. **Outliers** (``AutoConfig.robust="auto"``, the default): the winner is tested for false
   loop closures and false GPS fixes and, when the graph is inconsistent, solved again
   without them (:mod:`hybridpgo.solvers.robust`; ``stats["outliers"]``).  When a polished
   candidate's fit is inconsistent as a whole (the test's scale beyond its level: the map
   is folded), the remaining polishes and the relaxation check are skipped, since the
   re-solve replaces their answer.

The result's ``status`` is the winning polish's; ``stats`` name the start (``init``), the
sweeps and polish iterations it took (``sweeps``, ``polish_iterations``, ``polish_status``),
every candidate's energies (``candidates``) and a one-line ``reason``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import HybridPGOError, SolverError
from ..graph import FloatArray, PoseGraph
from ..initialization import initial_locals
from ..linalg import shared_patterns
from ..tree import PoseTree, build_tree, global_poses
from .config import AutoConfig, InitName, Progress, ProgressCallback
from .gauss_newton import ExactSolver, IterateCallback
from .result import SolveResult, Status

if TYPE_CHECKING:
    from ..certificate import SyncProblem

__all__ = ["MIN_FINALIST_ITERATIONS", "solve_auto"]

#: Polished energies within this fraction are the same minimum: the earlier finalist stays.
_TIE = 1e-9
#: A runner-up's polish may always take this many iterations (``AutoConfig.finalist_budget``).
MIN_FINALIST_ITERATIONS = 20


class _Candidate:
    """One start's trajectory: its energies, sweeps and (maybe) polish."""

    def __init__(self, init: str, label: str | None = None) -> None:
        self.init = init
        self.label = label or init
        """Key in ``stats["candidates"]``: the start, or ``"<start>, no sweeps"``."""
        self.history: list[float] = []
        self.times: list[float] = []
        self.rot: FloatArray | None = None
        self.trans: FloatArray | None = None
        self.sweeps = 0
        self.sweeps_run = 0
        self.start_seconds = 0.0
        self.sweep_seconds = 0.0
        self.capped = 0
        self.rejected = 0
        self.start: tuple[FloatArray, FloatArray] = (np.zeros((0, 3, 3)), np.zeros((0, 3)))
        """The start's poses (before any sweep)."""
        self.locals: tuple[FloatArray, FloatArray] | None = None
        """The start's local transforms, when computed before the sweeps (the early try)."""
        self.polished: SolveResult | None = None
        self.cut = False
        """A runner-up whose polish stopped at its budget, above the best."""
        self.error = ""

    @property
    def energy(self) -> float:
        """Energy of the kept poses (after the sweeps, or polished)."""
        if self.polished is not None:
            return self.polished.final_energy
        return min(self.history) if self.history else float("inf")

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "initial_energy": self.history[0] if self.history else None,
            "sweeps": self.sweeps, "sweeps_run": self.sweeps_run,
            "energy_after_sweeps": min(self.history) if self.history else None,
            "start_seconds": self.start_seconds, "sweep_seconds": self.sweep_seconds,
            "capped_steps": self.capped, "rejected_steps": self.rejected,
        }
        if self.polished is not None:
            out.update(final_energy=self.polished.final_energy,
                       polish_iterations=self.polished.iterations,
                       polish_status=self.polished.status.value,
                       polish_seconds=float(self.polished.timings.get("total", 0.0)),
                       polish_cut_at_budget=self.cut)
        if self.error:
            out["error"] = self.error
        return out


def _sweep_candidate(graph: PoseGraph, cfg: AutoConfig, cand: _Candidate, tree: Any,
                     locals0: tuple[FloatArray, FloatArray], t_origin: float,
                     progress: ProgressCallback | None,
                     iterate: IterateCallback | None = None) -> None:
    """Sweeps from one start while they pay; keeps the best poses in ``cand``."""
    t0 = time.perf_counter()
    max_sweeps = cfg.sweeps.sweeps
    if max_sweeps == 0:  # no hybrid solver (its per-path blocks cost memory): poses, E
        from ..energy import robust_energy

        cand.rot, cand.trans = cand.start = global_poses(tree, *locals0)
        e0 = robust_energy(graph, cand.rot, cand.trans, cfg.robust, cfg.robust_delta)[0]
        cand.history.append(e0)
        cand.times.append(time.perf_counter() - t_origin)
        if progress is not None:
            progress(Progress("start", 0, 0, e0, detail=cand.init))
        if iterate is not None:
            iterate(Progress("start", 0, 0, e0, detail=cand.init), cand.rot, cand.trans)
        cand.sweep_seconds = time.perf_counter() - t0
        return
    from .hybrid.solver import HybridSolver  # not imported by a certified early try

    solver = HybridSolver(graph, cfg.hybrid_config(cand.init, max_sweeps), tree=tree,
                          locals0=locals0)
    e0 = solver.energy()
    cand.rot, cand.trans = cand.start = solver.poses()
    cand.history.append(e0)
    cand.times.append(time.perf_counter() - t_origin)
    if progress is not None:
        progress(Progress("start", 0, 0, e0, detail=cand.init))
        if max_sweeps:
            progress(Progress("sweeps", 0, max_sweeps, e0, solver.tau, cand.init))
    if iterate is not None:
        iterate(Progress("start", 0, 0, e0, detail=cand.init), cand.rot, cand.trans)
    best = e0
    for k in range(max_sweeps):
        if not np.isfinite(best) or best == 0.0:
            break
        try:
            res = solver.run(1)
        except SolverError as exc:  # every update non-finite / E non-finite: keep the best
            cand.error = f"sweep {k + 1}: {exc}"
            break
        cand.sweeps_run += 1
        e = res.final_energy
        cand.capped += int(res.stats["capped_steps"])
        cand.rejected += int(res.stats["rejected_steps"])
        if progress is not None:
            progress(Progress("sweeps", k + 1, max_sweeps, e, solver.tau, cand.init))
        if iterate is not None:
            iterate(Progress("sweeps", k + 1, max_sweeps, e, solver.tau, cand.init),
                    res.rotations, res.translations)
        if e < best:
            cand.rot, cand.trans = res.rotations, res.translations
            cand.sweeps = cand.sweeps_run
            cand.history.append(e)
            cand.times.append(time.perf_counter() - t_origin)
        if not e <= best * (1.0 - cfg.sweep_tolerance):
            break
        best = e
    cand.sweep_seconds = time.perf_counter() - t0


def _polish(exact: ExactSolver, cand: _Candidate, progress: ProgressCallback | None,
            limit: int, iterate: IterateCallback | None = None) -> None:
    """LM from the candidate's kept poses, at most ``limit`` iterations (more when it is
    continued: :func:`_continue`), with the pipeline's one analyzed exact solver."""
    report = None if progress is None else (
        lambda p: progress(p._replace(phase="polish", detail=cand.label)))
    done = cand.polished
    rot, trans = (cand.rot, cand.trans) if done is None else (done.rotations, done.translations)
    each = None if iterate is None else (
        lambda p, r, t: iterate(p._replace(phase="polish", detail=cand.label), r, t))
    try:
        more = exact.solve(rot, trans, progress=report, iterate=each, max_iterations=limit)
    except SolverError as exc:
        cand.error = f"polish: {exc}"
        return
    cand.polished = more if done is None else _continue(done, more)


def _failure(cand: _Candidate) -> str:
    """Why a candidate is out: its error, else its energy (never an empty reason)."""
    if cand.error:
        return cand.error
    if cand.polished is not None and cand.cut:
        return "its polish was cut at the finalists' budget"
    overflow = "" if math.isfinite(cand.energy) else " (the numbers overflow float64)"
    return f"energy {cand.energy:.6g}{overflow} at its best poses"


def _polished_at(exact: ExactSolver, cfg: AutoConfig, init: str, label: str,
                 rot: FloatArray, trans: FloatArray, energy: float, at: float,
                 progress: ProgressCallback | None,
                 iterate: IterateCallback | None) -> _Candidate:
    """A candidate started at the given poses (E ``energy`` there, ``at`` seconds into the
    solve), polished by LM (:func:`_polish`)."""
    cand = _Candidate(init, label)
    cand.rot, cand.trans = cand.start = rot, trans
    cand.history = [energy]
    cand.times = [at]
    _polish(exact, cand, progress, cfg.polish.max_iterations, iterate)
    return cand


def _unswept(cand: _Candidate) -> _Candidate:
    """The start of a swept candidate, as a candidate of its own (no sweeps)."""
    raw = _Candidate(cand.init, f"{cand.init}, no sweeps")
    raw.history, raw.times = cand.history[:1], cand.times[:1]
    raw.rot, raw.trans = cand.start
    raw.start_seconds = cand.start_seconds
    return raw


def _continue(first: SolveResult, second: SolveResult) -> SolveResult:
    """One polish from two LM runs, the second started where the first stopped."""
    return dataclasses.replace(
        second, iterations=first.iterations + second.iterations,
        energy_history=np.concatenate([first.energy_history, second.energy_history[1:]]),
        times=np.concatenate([first.times, first.times[-1] + np.asarray(second.times[1:])]),
        timings={k: first.timings.get(k, 0.0) + v for k, v in second.timings.items()})


def _misfit(graph: PoseGraph, cand: _Candidate) -> bool:
    """``robust="auto"``: the polished candidate's least-squares fit is inconsistent as a whole
    (:attr:`hybridpgo.solvers.robust.Consistency.misfit`): false constraints have folded the
    map, and the outlier re-solve will replace whatever least squares reaches."""
    from .robust import check_consistency

    assert cand.polished is not None
    return check_consistency(graph, cand.polished.rotations, cand.polished.translations).misfit


def _least_squares(cfg: AutoConfig) -> AutoConfig:
    """``cfg`` with plain least squares in the sweeps and the polish (``robust="auto"``'s
    first solve)."""
    return dataclasses.replace(
        cfg, sweeps=dataclasses.replace(cfg.sweeps, robust="none", robust_scale=None),
        polish=dataclasses.replace(cfg.polish, robust="none", robust_scale=None))


def _relaxation_applies(graph: PoseGraph, cfg: AutoConfig, large: bool) -> str:
    """Why the planar relaxation does not apply ("" when it does)."""
    if not cfg.relaxation:
        return "off"
    if large:
        return "large-graph policy"
    if not graph.is_2d:
        return "not a 2D graph"
    if graph.num_gps:
        return "GPS constraints"
    if cfg.robust not in ("none", "auto"):  # "auto": checks the least-squares fit
        return "robust kernel"
    if graph.fixed_nodes.size > 1:
        return "several fixed poses"
    if graph.num_nodes < 3:
        return "fewer than 3 poses"
    return ""


def _relaxation_check(exact: ExactSolver, cfg: AutoConfig, large: bool, win: _Candidate,
                      t_origin: float, progress: ProgressCallback | None,
                      iterate: IterateCallback | None) -> dict[str, Any]:
    """The planar relaxation from the winner's poses (``AutoConfig.relaxation``); its start is
    polished (returned as ``"candidate"``) when its rotations leave the winner's basin."""
    from ..energy import robust_energy
    from ..initialization import planar_relaxation_start

    graph = exact.graph
    why = _relaxation_applies(graph, cfg, large)
    if why:
        return {"ran": False, "why": why}
    assert win.polished is not None
    t0 = time.perf_counter()
    try:
        rot, trans, info = planar_relaxation_start(
            graph, win.polished.rotations, win.polished.translations,
            max_iterations=cfg.relaxation_iterations)
    except (HybridPGOError, ValueError, np.linalg.LinAlgError, RuntimeError) as exc:
        return {"ran": False, "why": f"failed: {exc}"}
    out: dict[str, Any] = {"ran": True, **info, "seconds": time.perf_counter() - t0,
                           "polished": False}
    if info["max_angle"] <= cfg.relaxation_angle:
        out["summary"] = (f"planar relaxation agrees with the winner (rotations within "
                          f"{info['max_angle']:.2g} rad)")
        return out
    cand = _Candidate("relaxation")
    cand.rot, cand.trans = cand.start = rot, trans
    e0 = robust_energy(graph, rot, trans)[0]
    cand.history.append(e0)
    cand.times.append(time.perf_counter() - t_origin)
    cand.start_seconds = out["seconds"]
    if progress is not None:
        progress(Progress("start", 0, 0, e0, detail=cand.init))
    if iterate is not None:
        iterate(Progress("start", 0, 0, e0, detail=cand.init), rot, trans)
    _polish(exact, cand, progress, cfg.polish.max_iterations, iterate)
    out["polished"] = cand.polished is not None
    out["candidate"] = cand
    if cand.polished is not None:
        out["final_energy"] = cand.polished.final_energy
        better = cand.polished.final_energy < win.energy * (1.0 - _TIE)
        out["summary"] = (f"planar relaxation left the winner's basin (rotations up to "
                          f"{info['max_angle']:.2g} rad apart): its start polished to "
                          f"{cand.polished.final_energy:.6g}, "
                          + ("lower: it wins" if better else "not lower"))
    else:
        out["summary"] = f"planar relaxation: its polish failed ({cand.error})"
    return out


def _certificate_applies(graph: PoseGraph, cfg: AutoConfig, large: bool) -> str:
    """Why the certificate is not computed ("" when it is)."""
    if not cfg.certify:
        return "off"
    if large:
        return "large-graph policy"
    from ..certificate import not_applicable

    # "auto" certifies the least-squares fit (withdrawn when the outlier test rejects any)
    return not_applicable(graph, "none" if cfg.robust == "auto" else cfg.robust)


def _not_computed(why: str) -> dict[str, Any]:
    """``stats["certificate"]`` when no certificate was computed."""
    return {"computed": False, "certified": False, "summary": f"not certified: {why}",
            "why": why, "seconds": 0.0}


def _certificate_info(cert: Any, start: str) -> dict[str, Any]:
    """``stats["certificate"]`` of a :class:`hybridpgo.certificate.Certificate` computed at
    the candidate labelled ``start``."""
    return {
        "computed": True, "certified": bool(cert.certified), "summary": cert.summary(),
        "start": start, "lambda_min": float(cert.lambda_min), "gap": float(cert.gap),
        "relative_gap": float(cert.relative_gap), "objective": float(cert.objective),
        "seconds": float(cert.seconds), "reason": cert.reason,
        **{k: (v if isinstance(v, bool) else float(v)) for k, v in cert.stats.items()}}


def _staircase(graph: PoseGraph, prob: SyncProblem | None, init: str, cert: Any,
               info: dict[str, Any], max_rank: int | None = None
               ) -> tuple[Any, dict[str, Any]]:
    """The early try's second chance: :func:`hybridpgo.certificate.staircase_start` going on
    from the failed certificate ``cert`` on the same
    :class:`~hybridpgo.certificate.SyncProblem` ``prob`` (rank d from its refined rotations;
    its spectrum reused when its Newton's method converged); the certificate of the poses
    where the staircase certifies is the answer's (``max_rank``: the staircase's).  Returns
    the certificate
    and ``stats["certificate"]`` (with ``staircase``: its ranks, seconds, verdict;
    ``seconds`` counts the staircase)."""
    from ..certificate import staircase_start

    t0 = time.perf_counter()
    try:
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            _, _, stair = staircase_start(graph, cert.rotations, cert.translations,
                                          problem=prob, start=cert, max_rank=max_rank)
    except (HybridPGOError, ValueError, np.linalg.LinAlgError, RuntimeError,
            FloatingPointError) as exc:
        info["staircase"] = {"certified": False, "error": str(exc),
                             "seconds": time.perf_counter() - t0}
        info["seconds"] += info["staircase"]["seconds"]
        return cert, info
    summary = {"certified": bool(stair["certified"]), "rank": int(stair["rank"]),
               "objective": float(stair["objective"]),
               "rank_d_objective": float(info["objective"]),  # where the certificate failed
               "ranks": [{k: float(v) for k, v in r.items()} for r in stair["ranks"]]}
    if stair["certified"]:
        rounded = stair["certificate"]  # of the staircase's poses, where it certified
        took = time.perf_counter() - t0
        out = _certificate_info(rounded, init)
        out["seconds"] = info["seconds"] + took
        # the shared problem's set-up, made once before the first certificate
        out["seconds_setup"] = out.get("seconds_setup", 0.0) + info.get("seconds_setup", 0.0)
        out["staircase"] = {**summary, "seconds": took, "rank_d": info["summary"]}
        if "polished_first" in info:  # the rank-d certificate was the polished start's
            out["polished_first"] = info["polished_first"]
        return rounded, out
    info["staircase"] = {**summary, "seconds": time.perf_counter() - t0}
    info["seconds"] += info["staircase"]["seconds"]
    return cert, info


#: The early try's Newton method on F makes at most ``EARLY_NEWTON_WORK // N`` factorizations
#: on a graph of N poses, clipped to :data:`EARLY_NEWTON_MIN` ..
#: :data:`hybridpgo.certificate.NEWTON_FACTORIZATIONS` (:func:`_early_newton_cap`).  Each
#: factorization costs in proportion to the graph, and from a start far from F's minimum the
#: steps are damped and slow (a 100 000-pose city from the chordal start: 30 factorizations in
#: 15 s, short of the minimum; from LM's optimum of the same start, 2 in 2.2 s).  Where Newton
#: stops uncertified at a cap below the certificate's own, the start is polished first and
#: certified there (:func:`_polished_first`).
EARLY_NEWTON_WORK = 600_000
#: The early try's fewest Newton factorizations (:data:`EARLY_NEWTON_WORK`).
EARLY_NEWTON_MIN = 4


def _early_newton_cap(poses: int) -> int:
    """Newton's factorizations in the early try on a graph of ``poses`` poses."""
    from ..certificate import NEWTON_FACTORIZATIONS

    return min(NEWTON_FACTORIZATIONS, max(EARLY_NEWTON_MIN, EARLY_NEWTON_WORK // max(poses, 1)))


def _polished_first(exact: ExactSolver, cfg: AutoConfig, prob: SyncProblem | None,
                    cand: _Candidate, cert: Any, info: dict[str, Any], cap: int,
                    t_origin: float, progress: ProgressCallback | None,
                    iterate: IterateCallback | None) -> tuple[Any, dict[str, Any]]:
    """The early try where Newton's method stopped at its cap (:data:`EARLY_NEWTON_WORK`)
    short of F's minimum: LM polishes the start, and the certificate is computed at that
    optimum (its rotations are near F's minimum).  Returns that certificate and its
    ``stats["certificate"]`` (``polished_first``: the capped try's summary, the cap, the
    polish's seconds and energy; ``seconds`` counts both certificates), or ``cert`` and
    ``info`` as they were when the polish does not converge or the certificate raises."""
    from ..certificate import sesync_certificate

    graph = exact.graph
    assert cand.rot is not None and cand.trans is not None
    t0 = time.perf_counter()
    first = _polished_at(exact, cfg, cand.init, "polished start", cand.rot, cand.trans,
                         cand.history[0], t0 - t_origin, progress, iterate)
    pol = first.polished
    took = time.perf_counter() - t0
    note = {"newton_capped": info["summary"], "newton_cap": cap, "seconds_polish": took}
    if pol is None or pol.status is not Status.CONVERGED:
        info["polished_first"] = {**note, "error": first.error or "the polish did not converge"}
        return cert, info
    try:
        again = sesync_certificate(graph, pol.rotations, pol.translations, problem=prob)
    except (HybridPGOError, ValueError, np.linalg.LinAlgError, RuntimeError) as exc:
        info["polished_first"] = {**note, "error": f"the certificate failed: {exc}"}
        return cert, info
    out = _certificate_info(again, cand.init)
    out["seconds"] += info["seconds"]  # the capped try's, its problem's set-up included
    out["seconds_setup"] = out.get("seconds_setup", 0.0) + info.get("seconds_setup", 0.0)
    out["polished_first"] = {**note, "energy": pol.final_energy}
    return again, out


def _certified_start(exact: ExactSolver, cfg: AutoConfig, tree: PoseTree, init: InitName,
                     t_origin: float, progress: ProgressCallback | None,
                     iterate: IterateCallback | None
                     ) -> tuple[_Candidate, _Candidate | None, dict[str, Any]]:
    """The early try (``AutoConfig.certify_first``): start ``init``, its rotations refined by
    Newton's method on SE-Sync's objective and certified (when that finds a local minimum of
    the objective, or stops at its cap short of a stationary point:
    SE-Sync's Riemannian staircase from there, :func:`_staircase`), and, when certified, LM
    from the certified start.

    Returns the start's candidate (its poses, no sweeps; ``locals`` kept for the sweeps when
    the try fails), the certified start's candidate (None when the certificate failed) and
    the try's ``stats["certificate"]``; ``certified`` there means the polish converged too."""
    from ..certificate import NEWTON_FACTORIZATIONS, sesync_certificate, sync_problem
    from ..energy import robust_energy

    graph = exact.graph
    cand = _Candidate(init)
    t0 = time.perf_counter()
    try:
        cand.locals = initial_locals(graph, tree, init)
    except (HybridPGOError, ValueError, np.linalg.LinAlgError, RuntimeError) as exc:
        cand.error = f"start: {exc}"
        return cand, None, {**_not_computed(f"the start {init} failed: {exc}"), "start": init}
    cand.rot, cand.trans = cand.start = global_poses(tree, *cand.locals)
    cand.start_seconds = time.perf_counter() - t0
    cand.history.append(robust_energy(graph, cand.rot, cand.trans)[0])
    cand.times.append(time.perf_counter() - t_origin)
    if progress is not None:
        progress(Progress("start", 0, 0, cand.history[0], detail=init))
    if iterate is not None:
        iterate(Progress("start", 0, 0, cand.history[0], detail=init), cand.rot, cand.trans)
    cap = _early_newton_cap(graph.num_nodes)
    try:
        # one SyncProblem for the certificate and the staircase (set up once)
        prob, setup_s = sync_problem(graph)
        cert = sesync_certificate(graph, cand.rot, cand.trans, problem=prob,
                                  max_factorizations=cap)
    except (HybridPGOError, ValueError, np.linalg.LinAlgError, RuntimeError) as exc:
        return cand, None, {**_not_computed(f"the certificate failed: {exc}"), "start": init}
    info = _certificate_info(cert, init)
    info["seconds"] += setup_s  # the problem's set-up, made before the certificate's clock
    info["seconds_setup"] = info.get("seconds_setup", 0.0) + setup_s
    if (not cert.certified and not cert.stats.get("refine_converged", True)
            and cap < NEWTON_FACTORIZATIONS):
        # a large graph whose Newton steps from the start are slow: certified at LM's optimum
        cert, info = _polished_first(exact, cfg, prob, cand, cert, info, cap, t_origin,
                                     progress, iterate)
    floor = cert.stats.get("shift_floor", 0.0)
    # a 3D graph with GPS: the staircase stays at rank d (above it the earth frame's
    # rotation is lifted, where S is ill-conditioned, certificate.py; the escape did not
    # certify valencia + GPS), so it runs only to let Newton go on where it stopped short
    held = prob is not None and prob.holds_earth
    converged = cert.stats.get("refine_converged", True)
    if not cert.certified and ((cert.lambda_min < -floor and not held) or not converged):
        # F's local minimum (a negative eigenvalue), or Newton stopped short of one (where no
        # eigenvalue is computed): SE-Sync's Riemannian staircase (Newton goes on at rank d)
        # escapes it through higher ranks; a certified rounding is the certified start
        cert, info = _staircase(graph, prob, init, cert, info,
                                prob.d if prob is not None and held else None)
    if not cert.certified:
        return cand, None, info
    check = _polished_at(exact, cfg, init, "certified start", cert.rotations,
                         cert.translations,
                         robust_energy(graph, cert.rotations, cert.translations)[0],
                         time.perf_counter() - t_origin, progress, iterate)
    pol = check.polished
    if pol is None or pol.status is not Status.CONVERGED:
        why = check.error or f"its polish ended {pol.status.value if pol else 'nowhere'}"
        info.update(certified=False, summary=f"not certified: {why}",
                    reason=f"{cert.reason}; the polish from the certified start: {why}")
        return cand, check, info
    info.update(reason=f"{cert.reason}; the polish from there (LM) is the solution",
                polish_energy=pol.final_energy, polished_before=0)
    return cand, check, info


def _certify(exact: ExactSolver, cfg: AutoConfig, win: _Candidate,
             progress: ProgressCallback | None,
             iterate: IterateCallback | None) -> tuple[dict[str, Any], _Candidate]:
    """:func:`hybridpgo.certificate.certify` of a polished candidate, the check's polish run
    by the pipeline's exact solver.  Returns ``stats["certificate"]`` and the certified start's
    candidate (polished when the certificate of F held)."""
    from ..certificate import certify

    assert win.polished is not None
    check = _Candidate(win.init, "certified start")

    def polish(rot: FloatArray, trans: FloatArray) -> tuple[FloatArray, FloatArray, float]:
        from ..energy import robust_energy

        nonlocal check
        check = _polished_at(exact, cfg, win.init, "certified start", rot, trans,
                             robust_energy(exact.graph, rot, trans)[0], win.times[-1],
                             progress, iterate)
        if check.polished is None:
            raise SolverError(check.error)
        return check.polished.rotations, check.polished.translations, check.polished.final_energy

    cert = certify(exact.graph, win.polished.rotations, win.polished.translations,
                   energy=win.energy, polish=polish)
    info = _certificate_info(cert, win.label)
    if (not cert.certified and np.isfinite(cert.gap) and check.polished is not None
            and check.polished.status is Status.CONVERGED
            and check.energy < win.energy * (1.0 - _TIE)):
        # F's minimum is certified and LM from there converges lower: that polish is the
        # solution, certified by construction (the polish from the certified start)
        info.update(certified=True, start=check.label, summary=(
            f"certified global optimum (gap ≤ {cert.relative_gap:.1e} relative)"),
            reason=f"{cert.reason}; its polish ends below {win.label}'s and is the solution")
    return info, check


def _swept_starts(graph: PoseGraph, cfg: AutoConfig, tree: PoseTree, inits: list[InitName],
                  large: bool, t_origin: float, progress: ProgressCallback | None,
                  iterate: IterateCallback | None,
                  ready: _Candidate | None = None) -> list[_Candidate]:
    """Every start of ``inits`` computed and swept while the sweeps pay (the large-graph
    policy: only the first that could be computed).  ``ready``: a start already computed
    (the early try's), swept from its local transforms."""
    cands: list[_Candidate] = []
    for init in inits:
        cand = _Candidate(init)
        t0 = time.perf_counter()
        if ready is not None and ready.init == init and ready.error:
            cands.append(ready)
            continue
        try:
            if ready is not None and ready.init == init and ready.locals is not None:
                locals0, ready.locals = ready.locals, None
                t0 -= ready.start_seconds
            else:
                locals0 = initial_locals(graph, tree, init)
        except (HybridPGOError, ValueError, np.linalg.LinAlgError, RuntimeError) as exc:
            cand.error = f"start: {exc}"
            cands.append(cand)
            continue
        cand.start_seconds = time.perf_counter() - t0
        _sweep_candidate(graph, cfg, cand, tree, locals0, t_origin, progress, iterate)
        del locals0
        cands.append(cand)
        if large and cand.rot is not None and np.isfinite(cand.energy):
            break  # the large-graph policy: the first start that could be computed
    return cands


def _polish_finalists(exact: ExactSolver, cfg: AutoConfig, finalists: list[_Candidate],
                      certificate: dict[str, Any] | None, checks: list[_Candidate],
                      progress: ProgressCallback | None,
                      iterate: IterateCallback | None,
                      stop: Callable[[_Candidate], bool] | None = None,
                      ) -> tuple[list[_Candidate], dict[str, Any] | None]:
    """Polish the finalists in rank order: the first to convergence, each runner-up within its
    budget (``finalist_budget``), continued to convergence only if it is then the lowest.
    ``certificate`` None: the first polished finalist is certified (its check candidate goes
    to ``checks``), and when it is, no other is polished.  ``stop(best)`` after each polish:
    True ends the polishes (``robust="auto"``: the best fit is folded by outliers, and the
    re-solve replaces whatever a runner-up would reach).  Returns the finalists that were
    considered and ``stats["certificate"]`` (None when not computed yet)."""
    best: _Candidate | None = None
    for k, cand in enumerate(finalists):
        if best is not None and certificate is None:  # certify the first polished start
            certificate, check = _certify(exact, cfg, best, progress, iterate)
            certificate["polished_before"] = k
            checks.append(check)
            if certificate["certified"]:
                return finalists[:k], certificate
        if best is None or best.polished is None:
            _polish(exact, cand, progress, cfg.polish.max_iterations, iterate)
        else:  # a runner-up: a bounded polish, continued only if it is then the lowest
            budget = min(cfg.polish.max_iterations, max(
                math.ceil(cfg.finalist_budget * best.polished.iterations),
                MIN_FINALIST_ITERATIONS))
            _polish(exact, cand, progress, budget, iterate)
            pol = cand.polished
            if (pol is not None and pol.status is Status.MAX_ITERATIONS
                    and pol.final_energy < best.energy and budget < cfg.polish.max_iterations):
                _polish(exact, cand, progress, cfg.polish.max_iterations - budget, iterate)
            elif pol is not None and pol.status is Status.MAX_ITERATIONS:
                cand.cut = budget < cfg.polish.max_iterations
        if cand.polished is not None and (best is None or cand.energy < best.energy * (
                1.0 - _TIE)):
            best = cand
        if stop is not None and best is not None and stop(best):
            return finalists[:k + 1], certificate
    return finalists, certificate


def _stats(win: _Candidate, cands: list[_Candidate], ranked: list[_Candidate],
           finalists: list[_Candidate], polished: list[_Candidate], relax: dict[str, Any],
           skipped: list[InitName], policy: str, large: bool, certificate: dict[str, Any],
           checks: list[_Candidate]) -> dict[str, Any]:
    """The result's ``stats``: the winner, every candidate (``cands``) and the one-line
    ``reason``."""
    assert win.polished is not None
    pol = win.polished
    others = ", ".join(f"{c.label} {c.energy:.6g}" for c in polished if c is not win)
    cut = [c.label for c in finalists if c.cut]
    stair = certificate.get("staircase", {})
    lifted = bool(stair.get("ranks")) and stair["rank"] > stair["ranks"][0]["rank"]
    how = (f"SE-Sync's Riemannian staircase to rank {stair['rank']}, rounded and refined by "
           "Newton's method" if stair.get("certified") and lifted
           and win.label == "certified start"
           else "its rotations refined by Newton's method on SE-Sync's objective")
    if "polished_first" in certificate and win.label == "certified start":
        how = f"LM polished the start first, then {how}"
    swept = (f"{win.sweeps} sweep(s) kept of {win.sweeps_run} run" if win.label == win.init
             else f"its certified start ({how})" if win in checks
             else "its own poses, no sweeps")
    reason = (f"{policy}start {win.init}: {swept}, then "
              f"{pol.iterations} LM iteration(s), {pol.status.value}")
    if others:
        reason += f"; other polished start(s): {others}"
    if relax.get("ran"):
        reason += "; " + str(relax["summary"])
    reason += "; " + str(certificate["summary"])
    if certificate["certified"] and certificate["polished_before"] < len(ranked):
        reason += ": no other start polished"
    if cut:
        reason += (f"; polish of {', '.join(cut)} stopped at its budget above the best "
                   f"({', '.join(f'{c.energy:.6g}' for c in ranked if c.cut)})")
    return {
        "policy": "large" if large else "full",
        "init": win.init,
        "start": win.label,
        "sweeps": win.sweeps,
        "polish_iterations": pol.iterations,
        "polish_status": pol.status.value,
        "energy_after_sweeps": min(win.history),
        "reason": reason,
        "candidates": {c.label: c.summary() for c in cands},
        "skipped_inits": skipped,
        "finalists": [c.label for c in finalists],
        "polished_starts": sum(c.polished is not None for c in finalists),
        "linear_solver": pol.stats.get("linear_solver"),
        "relaxation": relax,
        "certificate": certificate,
        "capped_steps": win.capped,
        "rejected_steps": win.rejected,
    }


def _same_optimum(first: dict[str, Any], polished: list[_Candidate], win: _Candidate
                  ) -> bool:
    """Whether the winner ends at the energy of the first polished finalist, whose
    certificate is ``first`` (``first["start"]``: its label), within the tie: the same
    rotations, refined to the same point of F, get the same verdict, so the winner keeps
    that one (``stats["certificate"]["start"]`` then names the first finalist)."""
    return any(c.label == first.get("start")
               and abs(c.energy - win.energy) <= _TIE * abs(c.energy) for c in polished)


def _full_pipeline(graph: PoseGraph, exact: ExactSolver | None, cfg: AutoConfig,
                   tree: PoseTree, inits: list[InitName], why: str, large: bool,
                   early: tuple[_Candidate, _Candidate | None, dict[str, Any]] | None,
                   outliers: bool, t_origin: float, progress: ProgressCallback | None,
                   iterate: IterateCallback | None) -> tuple[Any, ...]:
    """Steps 2-5 of the module docstring: every start swept, the finalists polished and
    certified, the relaxation check.  ``early``: the early try that did not certify (its
    start is swept from its poses; its certified start's polish, when it converged, is a
    candidate like the certificate's own polishes).  Returns the winner, the candidate
    lists, ``stats["certificate"]``, ``stats["relaxation"]`` and the seconds of the polish,
    relaxation, outlier checks and hybrid kernels' compilation."""
    from .hybrid.solver import ensure_compiled as ensure_hybrid

    # the early try's cost: from its start's poses to here (certificate, staircase, polish)
    early_s = (time.perf_counter() - t_origin - early[0].times[0]
               if early is not None and early[0].times else 0.0)
    hybrid_s = ensure_hybrid()
    cands = _swept_starts(graph, cfg, tree, inits, large, t_origin, progress, iterate,
                          None if early is None else early[0])
    usable = [c for c in cands if c.rot is not None and np.isfinite(c.energy)]
    if not usable:
        raise SolverError("no start gave finite poses and a finite energy: "
                          + "; ".join(f"{c.init}: {_failure(c)}" for c in cands))
    ranked = sorted(usable, key=lambda c: c.energy)  # stable: ties keep the order of inits
    if cfg.polish_unswept:  # each swept start also as it was: the sweeps may leave its basin
        ranked += sorted((_unswept(c) for c in ranked if c.sweeps), key=lambda c: c.energy)
    finalists = ranked[:cfg.finalists] if cfg.finalists is not None else ranked
    t_polish = time.perf_counter()
    if exact is None:
        exact = ExactSolver(graph, cfg.polish)
    checks: list[_Candidate] = [] if early is None or early[1] is None else [early[1]]
    misfit_s: list[float] = []  # robust="auto": seconds of each misfit check

    def misfit(cand: _Candidate) -> bool:
        t_check = time.perf_counter()
        bad = _misfit(graph, cand)
        misfit_s.append(time.perf_counter() - t_check)
        return bad

    finalists, first = _polish_finalists(exact, cfg, finalists,
                                         _not_computed(why) if why else None, checks,
                                         progress, iterate, misfit if outliers else None)
    polished = [c for c in finalists if c.polished is not None and not c.cut]
    if not polished:
        raise SolverError("the polish failed from every start: "
                          + "; ".join(f"{c.label}: {_failure(c)}" for c in finalists))
    win = min(polished, key=lambda c: c.energy)
    if first is not None and (_same_optimum(first, polished, win) or not (
            first["computed"] and not first["certified"] and first["start"] != win.label)):
        certificate = first
    else:  # certify the winner
        certificate, check = _certify(exact, cfg, win, progress, iterate)
        certificate["polished_before"] = len(finalists)
        checks.append(check)
        if first is not None:
            certificate["first"] = {"start": first["start"], "summary": first["summary"]}
            certificate["seconds"] += first["seconds"]
    for check in checks:  # the certificate's own polish: a candidate only when it wins
        if check.polished is not None and check.polished.status is Status.CONVERGED and (
                check.energy < win.energy * (1.0 - _TIE)):
            cands.append(check)
            win = check
    polish_s = time.perf_counter() - t_polish - float(certificate["seconds"]) - sum(misfit_s)
    t_relax = time.perf_counter()
    folded = outliers and _misfit(graph, win)
    if certificate["certified"]:
        relax = {"ran": False, "why": "the winner is certified"}
    elif folded:
        relax = {"ran": False, "why": "outliers"}
    else:
        relax = _relaxation_check(exact, cfg, large, win, t_origin, progress, iterate)
    relax_cand = relax.pop("candidate", None)
    if isinstance(relax_cand, _Candidate):
        cands.append(relax_cand)
        if relax_cand.polished is not None:
            polished.append(relax_cand)
            if relax_cand.energy < win.energy * (1.0 - _TIE):
                win = relax_cand
    relax_s = time.perf_counter() - t_relax
    if win is relax_cand and certificate["computed"]:  # a new winner: certify it
        before = certificate
        certificate, check = _certify(exact, cfg, win, progress, iterate)
        certificate["polished_before"] = before["polished_before"]
        certificate["first"] = {"start": before["start"], "summary": before["summary"]}
        certificate["seconds"] += before["seconds"]
        checks.append(check)
        if check.polished is not None and check.polished.status is Status.CONVERGED and (
                check.energy < win.energy * (1.0 - _TIE)):
            cands.append(check)
            win = check
    if early is not None:  # the early try's cost and verdict
        certificate["early"] = {
            "start": early[2]["start"], "summary": early[2]["summary"], "seconds": early_s,
            **{k: early[2][k] for k in ("staircase", "polished_first") if k in early[2]}}
        certificate["seconds"] += early_s
    return (win, cands + ranked[len(usable):], ranked, finalists, polished, checks,
            certificate, relax, polish_s, relax_s, sum(misfit_s), hybrid_s)


def solve_auto(graph: PoseGraph, config: AutoConfig | None = None, *,
               progress: ProgressCallback | None = None,
               iterate: IterateCallback | None = None) -> SolveResult:
    """Optimize ``graph`` with the default pipeline (module docstring).

    Parameters
    ----------
    graph : PoseGraph
    config : AutoConfig, optional
    progress : callable, optional
        ``progress(Progress)``: ``phase`` ``"start"`` (a start computed), ``"sweeps"`` and
        ``"polish"``, with ``detail`` naming the start.
    iterate : callable, optional
        ``iterate(Progress, rotations, translations)``: the global poses at every start, sweep
        and polish iteration of every start tried, in the order they run (the ``Progress`` as
        ``progress`` gets it; e.g. :class:`hybridpgo.recording.RerunRecorder`).

    Returns
    -------
    SolveResult
        ``method`` ``"auto"``; ``energy_history``: the winning start, its kept sweeps, its
        polish (``iterations`` is the number of kept sweeps); ``status``: the polish's.

    Raises
    ------
    SolverError
        When no start could be computed and polished.
    """
    with shared_patterns():  # the certificate's Newton system and the polish share a pattern
        return _solve_auto(graph, config, progress=progress, iterate=iterate)


def _solve_auto(graph: PoseGraph, config: AutoConfig | None = None, *,
                progress: ProgressCallback | None = None,
                iterate: IterateCallback | None = None) -> SolveResult:
    """:func:`solve_auto` inside its pattern context."""
    cfg = config or AutoConfig()
    outliers = cfg.robust == "auto"
    if outliers:  # least squares first; the outlier test and re-solve close the pipeline
        cfg = _least_squares(cfg)
    large = cfg.is_large(graph.num_nodes)
    policy = ""
    if large:
        policy = (f"large-graph policy ({graph.num_nodes} poses >= {cfg.large_poses}): one "
                  f"start, at most {cfg.large_max_sweeps} sweeps, one polish; ")
        cfg = dataclasses.replace(
            cfg, inits=cfg.large_inits, finalists=1, polish_unswept=False,
            sweeps=dataclasses.replace(cfg.sweeps, sweeps=cfg.large_max_sweeps))
    from .gauss_newton import ensure_compiled as ensure_exact

    compile_s = ensure_exact()
    t_origin = time.perf_counter()
    tree = build_tree(graph, cfg.sweeps.tree)
    t_analyze = time.perf_counter() - t_origin
    inits = [i for i in cfg.inits if i != "file" or graph.has_estimates]
    skipped = [i for i in cfg.inits if i not in inits]
    if not inits:
        raise SolverError("no start applies: the file has no vertices; add 'tree' or 'chordal' "
                          "to the starts")
    why = _certificate_applies(graph, cfg, large)
    early: tuple[_Candidate, _Candidate | None, dict[str, Any]] | None = None
    exact = None  # built once, before the first polish (the sweeps' memory comes first)
    if cfg.certify_first and not why:
        from ..certificate import ensure_compiled as ensure_certificate

        t_compile = time.perf_counter()
        compile_s += ensure_certificate(graph.is_2d)
        t_polish = time.perf_counter()
        t_origin += t_polish - t_compile  # compilation is not the solve's time
        exact = ExactSolver(graph, cfg.polish)
        early = _certified_start(exact, cfg, tree, inits[0], t_origin, progress, iterate)
    if early is not None and early[2]["certified"]:
        ready, win, certificate = early
        assert win is not None
        cands = [ready, win]
        ranked = finalists = polished = checks = [win]
        relax: dict[str, Any] = {"ran": False, "why": "the winner is certified"}
        polish_s = time.perf_counter() - t_polish - certificate["seconds"] - ready.start_seconds
        relax_s = 0.0
        outliers_s = 0.0
    else:
        (win, cands, ranked, finalists, polished, checks, certificate, relax, polish_s,
         relax_s, outliers_s, hybrid_s) = _full_pipeline(
            graph, exact, cfg, tree, inits, why, large, early, outliers, t_origin, progress,
            iterate)
        compile_s += hybrid_s
    assert win.polished is not None
    pol = win.polished
    offset = win.times[-1]
    history = np.concatenate([win.history, pol.energy_history[1:]])
    times = np.concatenate([win.times, offset + np.asarray(pol.times[1:])])
    stats = _stats(win, cands, ranked, finalists, polished, relax,
                   skipped, policy, large, certificate, checks)
    for key in ("robust", "robust_scale", "plain_energy"):
        if key in pol.stats:
            stats[key] = pol.stats[key]
    result = SolveResult(
        rotations=pol.rotations, translations=pol.translations, status=pol.status,
        iterations=win.sweeps, energy_history=history, times=times, method="auto",
        num_constraints=graph.num_constraints,
        timings={"compile": compile_s, "analyze": t_analyze,
                 "start": sum(c.start_seconds for c in cands),
                 "sweeps": sum(c.sweep_seconds for c in cands), "polish": polish_s,
                 "certificate": float(certificate["seconds"]), "relaxation": relax_s,
                 "solve": time.perf_counter() - t_origin - t_analyze,
                 **({"outliers": outliers_s} if outliers else {})},
        stats=stats,
    )
    if outliers:  # robust="auto": the outlier test, and the re-solve when it fails
        from .robust import exact_resolver, resolve

        result = resolve(graph, result, exact_resolver(cfg.polish, progress, iterate))
        found = result.stats["outliers"]
        if found["rejected"] or found["rejected_gps"]:  # the answer is no longer the certified one
            result.stats["certificate"] = {
                **_not_computed("outliers rejected: the certificate covers the least-squares fit "
                                "of every constraint, not the re-solved map"),
                "least_squares": result.stats["certificate"]}
    return result

