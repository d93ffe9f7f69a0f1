"""The default pipeline: choose a start, sweep while it pays, polish to convergence.

:func:`solve_auto` is what ``hybridpgo optimize`` and :func:`hybridpgo.optimize` run when no
solver is named (``--solver auto``).  The paper's pure method stays ``--solver hybrid``.

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
   wins (ties: the earlier candidate).  Polishing more than one start is the guard against
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

**Large graphs** (``AutoConfig.large_poses``, default 200 000 poses and more): every start,
sweep and polish costs seconds to minutes, so only the first start of ``large_inits`` that can
be computed is used, with at most ``large_max_sweeps`` sweeps and one polish (no runner-up, no
unswept twin); ``stats["policy"]`` is ``"large"`` (else ``"full"``) and the reason says so.
benchmarks/scale.py measures what this costs against the full policy on a 100k-pose city.

The result's ``status`` is the winning polish's; ``stats`` name the start (``init``), the
sweeps and polish iterations it took (``sweeps``, ``polish_iterations``, ``polish_status``),
every candidate's energies (``candidates``) and a one-line ``reason``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import numpy as np

from ..errors import HybridPGOError, SolverError
from ..graph import FloatArray, PoseGraph
from ..initialization import initial_locals
from ..tree import PoseTree, build_tree, global_poses
from .config import AutoConfig, InitName, Progress, ProgressCallback
from .gauss_newton import ExactSolver, IterateCallback
from .hybrid.solver import HybridSolver
from .result import SolveResult, Status

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
    if cfg.robust != "none":
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


def _swept_starts(graph: PoseGraph, cfg: AutoConfig, tree: PoseTree, inits: list[InitName],
                  large: bool, t_origin: float, progress: ProgressCallback | None,
                  iterate: IterateCallback | None) -> list[_Candidate]:
    """Every start of ``inits`` computed and swept while the sweeps pay (the large-graph
    policy: only the first that could be computed)."""
    cands: list[_Candidate] = []
    for init in inits:
        cand = _Candidate(init)
        t0 = time.perf_counter()
        try:
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
                      progress: ProgressCallback | None,
                      iterate: IterateCallback | None) -> None:
    """Polish the finalists in rank order: the first to convergence, each runner-up within its
    budget (``finalist_budget``), continued to convergence only if it is then the lowest."""
    best: _Candidate | None = None
    for cand in finalists:
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


def _stats(win: _Candidate, cands: list[_Candidate], ranked: list[_Candidate],
           finalists: list[_Candidate], polished: list[_Candidate], relax: dict[str, Any],
           skipped: list[InitName], policy: str, large: bool) -> dict[str, Any]:
    """The result's ``stats``: the winner, every candidate (``cands``) and the one-line
    ``reason``."""
    assert win.polished is not None
    pol = win.polished
    others = ", ".join(f"{c.label} {c.energy:.6g}" for c in polished if c is not win)
    cut = [c.label for c in finalists if c.cut]
    swept = (f"{win.sweeps} sweep(s) kept of {win.sweeps_run} run" if win.label == win.init
             else "its own poses, no sweeps")
    reason = (f"{policy}start {win.init}: {swept}, then "
              f"{pol.iterations} LM iteration(s), {pol.status.value}")
    if others:
        reason += f"; other polished start(s): {others}"
    if relax.get("ran"):
        reason += "; " + str(relax["summary"])
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
        "linear_solver": pol.stats.get("linear_solver"),
        "relaxation": relax,
        "capped_steps": win.capped,
        "rejected_steps": win.rejected,
    }


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
    cfg = config or AutoConfig()
    large = cfg.is_large(graph.num_nodes)
    policy = ""
    if large:
        policy = (f"large-graph policy ({graph.num_nodes} poses >= {cfg.large_poses}): one "
                  f"start, at most {cfg.large_max_sweeps} sweeps, one polish; ")
        cfg = dataclasses.replace(
            cfg, inits=cfg.large_inits, finalists=1, polish_unswept=False,
            sweeps=dataclasses.replace(cfg.sweeps, sweeps=cfg.large_max_sweeps))
    from .gauss_newton import ensure_compiled as ensure_exact
    from .hybrid.solver import ensure_compiled as ensure_hybrid

    compile_s = ensure_hybrid() + ensure_exact()
    t_origin = time.perf_counter()
    tree = build_tree(graph, cfg.sweeps.tree)
    t_analyze = time.perf_counter() - t_origin
    inits = [i for i in cfg.inits if i != "file" or graph.has_estimates]
    skipped = [i for i in cfg.inits if i not in inits]
    if not inits:
        raise SolverError("no start applies: the file has no vertices; add 'tree' or 'chordal' "
                          "to the starts")
    cands = _swept_starts(graph, cfg, tree, inits, large, t_origin, progress, iterate)
    usable = [c for c in cands if c.rot is not None and np.isfinite(c.energy)]
    if not usable:
        raise SolverError("no start gave finite poses: "
                          + "; ".join(f"{c.init}: {c.error}" for c in cands))
    ranked = sorted(usable, key=lambda c: c.energy)  # stable: ties keep the order of inits
    if cfg.polish_unswept:  # each swept start also as it was: the sweeps may leave its basin
        ranked += sorted((_unswept(c) for c in ranked if c.sweeps), key=lambda c: c.energy)
    finalists = ranked[:cfg.finalists] if cfg.finalists is not None else ranked
    t_polish = time.perf_counter()
    exact = ExactSolver(graph, cfg.polish)
    _polish_finalists(exact, cfg, finalists, progress, iterate)
    polish_s = time.perf_counter() - t_polish
    polished = [c for c in finalists if c.polished is not None and not c.cut]
    if not polished:
        raise SolverError("the polish failed from every start: "
                          + "; ".join(f"{c.label}: {c.error}" for c in finalists))
    win = min(polished, key=lambda c: c.energy)
    t_relax = time.perf_counter()
    relax = _relaxation_check(exact, cfg, large, win, t_origin, progress, iterate)
    relax_cand = relax.pop("candidate", None)
    if isinstance(relax_cand, _Candidate):
        cands.append(relax_cand)
        if relax_cand.polished is not None:
            polished.append(relax_cand)
            if relax_cand.energy < win.energy * (1.0 - _TIE):
                win = relax_cand
    relax_s = time.perf_counter() - t_relax
    assert win.polished is not None
    pol = win.polished
    offset = win.times[-1]
    history = np.concatenate([win.history, pol.energy_history[1:]])
    times = np.concatenate([win.times, offset + np.asarray(pol.times[1:])])
    stats = _stats(win, cands + ranked[len(usable):], ranked, finalists, polished, relax,
                   skipped, policy, large)
    for key in ("robust", "robust_scale", "plain_energy"):
        if key in pol.stats:
            stats[key] = pol.stats[key]
    return SolveResult(
        rotations=pol.rotations, translations=pol.translations, status=pol.status,
        iterations=win.sweeps, energy_history=history, times=times, method="auto",
        num_constraints=graph.num_constraints,
        timings={"compile": compile_s, "analyze": t_analyze,
                 "start": sum(c.start_seconds for c in cands),
                 "sweeps": sum(c.sweep_seconds for c in cands), "polish": polish_s,
                 "relaxation": relax_s,
                 "solve": time.perf_counter() - t_origin - t_analyze},
        stats=stats,
    )

