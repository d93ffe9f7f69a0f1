"""A solve compiles only the kernels it uses, each for one signature (issue 11: the first run).

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
import pytest

import hybridpgo

SRC = pathlib.Path(hybridpgo.__file__).resolve().parent.parent
TESTS = pathlib.Path(__file__).resolve().parent

SCRIPT = """
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from graphs import random_graph
from hybridpgo.solvers.hybrid import HybridConfig, HybridSolver
from hybridpgo.solvers.hybrid import _batch, _interpolate, _sweep

graph = random_graph(np.random.default_rng(0), 12, 8, gps=int(sys.argv[2]))[0]
solver = HybridSolver(graph, HybridConfig(sweeps=2))
solver.run()
solver.step(np.arange(solver.num_constraints)[::-1].copy())  # a writable order, numpy ints
solver.rebuild_blocks()
print(json.dumps({
    "gps": int(graph.num_gps),
    "sweeps": {f"{g:d}{i:d}": len(k.signatures) for (g, i), k in _sweep.SWEEPS.items()},
    "flush": len(_sweep._flush.signatures),
    "batch_relax": len(_batch.batch_relax.signatures),
    "relax_interpolated": len(_interpolate.relax_interpolated.signatures),
}))
"""


def _compiled(gps: int) -> dict[str, object]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")]))
    env.pop("NUMBA_DISABLE_JIT", None)
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(TESTS), str(gps)], env=env,
                         check=True, capture_output=True, text=True).stdout
    result: dict[str, object] = json.loads(out.strip().splitlines()[-1])
    return result


@pytest.mark.parametrize("gps", [0, 3])
def test_a_solve_compiles_only_the_sweep_variant_it_uses(gps: int) -> None:
    got = _compiled(gps)
    assert got["gps"] == gps
    if gps:
        # the plain variant builds the blocks, the GPS variant sweeps; no interpolation
        assert got["sweeps"] == {"00": 1, "01": 0, "10": 1, "11": 0}
        assert got["flush"] == 1 and got["batch_relax"] == 1
    else:
        # one plain sweep kernel for run(), step() and rebuild_blocks(): one signature only
        assert got["sweeps"] == {"00": 1, "01": 0, "10": 0, "11": 0}
        assert got["flush"] == 0 and got["batch_relax"] == 0
    assert got["relax_interpolated"] == 0


def test_every_sweep_variant_gives_the_plain_sweeps_result_without_gps_and_dmax() -> None:
    """Pruning a variant's branches changes no arithmetic: on a graph without GPS and with
    ``d_max`` = 0 the plain and the interpolating variant give bit-identical poses."""
    from graphs import random_graph

    from hybridpgo.solvers.hybrid import HybridConfig, HybridSolver, _sweep
    from hybridpgo.solvers.hybrid.problem import NUM_COUNTS

    graph = random_graph(np.random.default_rng(1), 12, 8)[0]
    assert graph.num_gps == 0
    results = []
    for variant in ((False, False), (False, True)):
        solver = HybridSolver(graph, HybridConfig())
        nc = solver.num_constraints
        counts = np.zeros(NUM_COUNTS, np.int64)
        for _ in range(3):
            _sweep._run(_sweep.sweep_kernel(*variant), solver.problem, solver.state,
                        solver.tree.sweep_order, 0.5, 1e-4, 0, 1, solver.dmax, 0,
                        np.iinfo(np.uint64).max, np.zeros(nc, np.uint64),
                        np.zeros(nc, np.uint64), counts, True)
        results.append((solver.state.rot.copy(), solver.state.trans.copy(),
                        solver.state.bdiag.copy()))
    for a, b in zip(results[0], results[1], strict=True):
        assert np.array_equal(a, b)
