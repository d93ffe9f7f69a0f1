"""Micro-benchmark of valencia's longest update (Table I's steady max).

Run: ``PYTHONPATH=src python -m benchmarks.long_update [--dmax 200] [--repeat 300]
[--sweeps 10] [--phases]`` (a script, not a registered workload: it prints, writes nothing).

* ``repeat``: the best (least) cycle count, over ``--repeat`` calls of
  ``HybridSolver.step([c], tau=1e-9)``, of the update of the constraint c with the longest
  domain (d = 2368 on valencia seed 0), as the sweep kernel books it (``cycles[c]``).  The
  path's data stay in cache between calls: a lower bound of the sweep's cost.
* ``sweep``: ``--sweeps`` sweeps from the tree initialization (as Table I): the steady max
  (largest over constraints of each one's cheapest update) and the longest constraint's own
  steady time, plus the mean per update.
* ``--phases``: best-of cycle counts of the update's phases (path products and residual,
  Jacobian blocks with 𝔅(H), reduced factors with the merged chains, solve, distribution) from
  a kernel of this script that calls them one by one on a copy of the state.
* ``checksum``: SHA-256 of the local transforms after the sweeps: two code versions whose
  checksums agree computed bit-identical results.
"""

from __future__ import annotations

import argparse
import hashlib
import time

import numpy as np

from hybridpgo._numba import cycle_counter, cycles_per_second, kernel
from hybridpgo.generate import generate_city
from hybridpgo.solvers.hybrid import HybridConfig, HybridSolver
from hybridpgo.solvers.hybrid import _interpolate as ip
from hybridpgo.solvers.hybrid import _linearize as lin
from hybridpgo.solvers.hybrid import _step as stp
from hybridpgo.solvers.hybrid.problem import Problem, State, new_workspace


@kernel
def _phases(prob: Problem, state: State, c: int, d_max: int, repeat: int,
            out: np.ndarray) -> None:  # pragma: no cover - benchmark
    """Best-of cycle counts of the phases of ``relax_interpolated`` (copies of the state are
    restored before every repetition, so each one does the same work)."""
    s = prob.path_ptr[c]
    d = prob.path_ptr[c + 1] - s
    wk = new_workspace(d)
    sub = new_workspace(d_max)
    keep = np.empty(d_max, np.int64)
    rot0 = state.rot.copy()
    trans0 = state.trans.copy()
    bd0 = state.bdiag.copy()
    co0 = state.contrib.copy()
    for q in range(out.shape[0]):
        out[q] = np.iinfo(np.uint64).max
    for _ in range(repeat):
        state.rot[:] = rot0
        state.trans[:] = trans0
        state.bdiag[:] = bd0
        state.contrib[:] = co0
        t0 = cycle_counter()
        na = lin.relative_setup(
            prob.path_node, prob.path_sign, s, d, prob.edge_rot[c], prob.edge_trans[c],
            prob.edge_lt[c], prob.robust_kind, prob.robust_scale, state.rot, state.trans,
            wk.path_rot, wk.path_trans, wk.iws, wk.ws, wk.e, wk.r, wk.jri, wk.a)
        t1 = cycle_counter()
        nk = ip.kept_positions(d, na, d_max, keep)
        stp.linearize_accumulate(prob.path_node, prob.path_sign, s, d, na, wk.path_rot,
                                 wk.path_trans, wk.a, wk.jac, False, keep, nk, state.bdiag,
                                 state.contrib, 0.0, wk.lfac, wk.bc, False)
        t2 = cycle_counter()
        nk = ip.kept_positions(d, na, d_max, keep)
        ip.reduced_factors(prob, state, c, d, na, 6, wk, keep, nk, 0.0, sub)
        t3 = cycle_counter()
        for i in range(6):
            sub.r[i] = wk.r[i]
        stp.solve_single(nk, 6, 0, sub)
        tt, _st = stp.step_temperature(sub.x, nk, 1e-9)
        t4 = cycle_counter()
        ip.distribute(prob, state, c, d, na, keep, nk, sub.x, tt, wk)
        t5 = cycle_counter()
        ts = (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t5 - t0)
        for q in range(6):
            if ts[q] < out[q]:
                out[q] = ts[q]
    state.rot[:] = rot0
    state.trans[:] = trans0
    state.bdiag[:] = bd0
    state.contrib[:] = co0


def main() -> None:  # pragma: no cover - benchmark
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dmax", type=int, default=200, help="D_max (0: the whole path)")
    ap.add_argument("--repeat", type=int, default=300)
    ap.add_argument("--sweeps", type=int, default=10)
    ap.add_argument("--phases", action="store_true")
    args = ap.parse_args()
    dmax = args.dmax or None
    g = generate_city("valencia", seed=0).graph
    freq = cycles_per_second()
    us = 1e6 / freq
    HybridSolver(g, HybridConfig(sweeps=1, dmax=dmax)).run()  # compile / load the cache
    solver = HybridSolver(g, HybridConfig(sweeps=args.sweeps, dmax=dmax))
    c = int(np.argmax(solver.tree.path_lengths()))
    res = solver.run()
    st = res.stats
    digest = hashlib.sha256(solver.state.rot.tobytes() + solver.state.trans.tobytes())
    print(f"longest constraint {c}: d = {int(solver.tree.path_lengths()[c])}, D_max = {dmax}")
    print(f"sweep x{args.sweeps}: mean {st['us_per_constraint_mean']:.2f} us, steady max "
          f"{st['us_per_constraint_max_steady']:.0f} us, E/c "
          f"{res.final_energy / res.num_constraints:.6g}")
    print(f"checksum {digest.hexdigest()[:16]}")
    best = np.iinfo(np.uint64).max
    t0 = time.perf_counter()
    for _ in range(args.repeat):
        solver.step([c], tau=1e-9)
        best = min(best, int(solver._cycles[c]))
    print(f"repeat x{args.repeat}: best {best * us:.1f} us ({time.perf_counter() - t0:.1f} s)")
    if args.phases and dmax:
        out = np.zeros(6, np.uint64)
        _phases(solver.problem, solver.state, c, dmax, args.repeat, out)
        names = ("path products+residual", "blocks+B(H)", "reduced+merge", "solve",
                 "distribute", "total")
        print("phases (best-of, us): " + ", ".join(
            f"{n} {float(v) * us:.1f}" for n, v in zip(names, out, strict=True)))


if __name__ == "__main__":  # pragma: no cover
    main()
