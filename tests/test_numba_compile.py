"""A solve compiles only the kernels it uses, each for one signature (the first run).

The sweep of a graph without GPS readings and without interpolated solving must not compile the
GPS batches (``_flush`` -> ``batch_relax``) or ``relax_interpolated``: together they were about
two thirds of the hybrid solver's compile time.  Checked in a fresh interpreter, since this
test process may have compiled every variant already (a kernel loaded from the on-disk cache
counts as well: its signature is listed, its callees are not loaded).
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import numpy as np

import hybridpgo

SRC = pathlib.Path(hybridpgo.__file__).resolve().parent.parent
TESTS = pathlib.Path(__file__).resolve().parent

SCRIPT = """
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from graphs import random_graph
from hybridpgo.solvers.hybrid import HybridConfig, HybridSolver, _init_blocks, _step, _sweep

def signatures():
    out = {f"{g:d}{i:d}{v:d}{a:d}": len(k.signatures)
           for (g, i, v, a), k in _sweep.LOOPS.items()}
    out["init"] = len(_init_blocks.init_blocks.signatures)
    out["relax"] = len(_step.relax.signatures)  # the generic one: every branch compiled in
    return {key: n for key, n in out.items() if n}

out = []
for gps in (0, 3):
    graph = random_graph(np.random.default_rng(0), 12, 8, gps=gps)[0]
    solver = HybridSolver(graph, HybridConfig(sweeps=2))
    solver.run()
    solver.step(np.arange(solver.num_constraints)[::-1].copy())  # a writable order
    solver.rebuild_blocks()
    out.append(signatures())
print(json.dumps(out))
"""


def _referenced_globals(kern: object) -> set[str]:
    """Globals a kernel's reachable code uses after Numba's dead-branch pruning (the pass that
    runs before typing: a callee named only in a pruned branch is never compiled)."""
    from numba.core import analysis, compiler, ir, types

    fir = compiler.run_frontend(kern.py_func)  # type: ignore[attr-defined]
    analysis.dead_branch_prune(fir, [types.unknown] * fir.arg_count)
    dead = set(analysis.compute_cfg_from_blocks(fir.blocks).dead_nodes())
    return {stmt.value.name for label, blk in fir.blocks.items() if label not in dead
            for stmt in blk.find_insts(ir.Assign)
            if isinstance(stmt.value, ir.Global | ir.FreeVar)}


def test_each_sweep_variant_calls_only_what_it_needs() -> None:
    """The plain sweep never reaches the GPS batches (``_flush*`` -> ``batch_relax*``) or
    ``relax_interpolated``, together about two thirds of the hybrid compile time; a GPS sweep
    without ``d_max`` never the interpolated batch (``reduced_batch``)."""
    from hybridpgo.solvers.hybrid import _batch, _step, _sweep
    from hybridpgo.solvers.hybrid.problem import StepKind

    heavy = {"_flush", "_flush_exact", "relax_interpolated", "_relax_group"}
    for (gps, interp, givens, admission), kern in _sweep.LOOPS.items():
        used = _referenced_globals(kern)
        assert "relax" in used
        relax = kern.py_func.__closure__[kern.py_func.__code__.co_freevars.index("relax")]
        step = _step.BY_ARGUMENT if admission else (
            StepKind.GIVENS if givens else StepKind.WOODBURY)
        assert relax.cell_contents is _step.RELAX[gps, step]
        flush = ("_flush" if interp else "_flush_exact") if gps else None
        expected = {name for name in (flush, "relax_interpolated" if interp else None,
                                      "_relax_group" if admission else None) if name}
        assert used & heavy == expected, (gps, interp, admission)
    for (gps, step), kern in _step.RELAX.items():  # one solve, the GPS linearization if asked
        used = _referenced_globals(kern)
        assert ("givens_solve" in used, "woodbury_solve" in used) == {
            StepKind.GIVENS: (True, False), StepKind.WOODBURY: (False, True)}.get(
            step, (True, True))  # type: ignore[call-overload]
        assert ("linearize" in used) == gps
    assert "batch_relax_exact" in _referenced_globals(_sweep._flush_exact)
    assert "reduced_batch" not in _referenced_globals(_batch.batch_relax_exact)
    assert "reduced_batch" in _referenced_globals(_batch.batch_relax)


def test_a_solve_compiles_only_the_sweep_variant_it_uses() -> None:
    """Checked in a fresh interpreter (this one may have compiled every variant): a graph
    without GPS runs one plain sweep kernel with one signature for run(), step() and
    rebuild_blocks(); a GPS graph adds the GPS variant; neither the interpolating ones, nor
    the large graphs' own 𝔅(H) kernel (the solve's sweep variant builds 𝔅(H))."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")]))
    env.pop("NUMBA_DISABLE_JIT", None)
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(TESTS)], env=env, check=True,
                         capture_output=True, text=True).stdout
    no_gps, with_gps = json.loads(out.strip().splitlines()[-1])
    assert no_gps == {"0000": 1}
    assert with_gps == {"0000": 1, "1000": 1}


def test_every_sweep_variant_gives_the_plain_sweeps_result_without_gps_and_dmax() -> None:
    """Pruning a variant's branches changes no arithmetic: on a graph without GPS and with
    ``d_max`` = 0 the plain and the interpolating variant give bit-identical poses (the GPS
    variants against each other: tests/test_interpolate_batch.py, d_max >= the union)."""
    from graphs import random_graph

    from hybridpgo.solvers.hybrid import HybridConfig, HybridSolver, _sweep
    from hybridpgo.solvers.hybrid.problem import NUM_COUNTS

    graph = random_graph(np.random.default_rng(1), 12, 8)[0]
    assert graph.num_gps == 0
    results = []
    for variant in ((False, False), (False, True)):  # Woodbury
        solver = HybridSolver(graph, HybridConfig())
        counts = np.zeros(NUM_COUNTS, np.int64)
        for _ in range(3):
            _sweep.run_loop(_sweep.loop_kernel(*variant), solver.problem, solver.state,
                            solver.scratch, solver.tree.sweep_order, 0.5, 1e-4, 0, 1, 0,
                            np.iinfo(np.uint64).max, counts)
        results.append((solver.state.rot.copy(), solver.state.trans.copy(),
                        solver.state.bdiag.copy()))
    for a, b in zip(results[0], results[1], strict=True):
        assert np.array_equal(a, b)
