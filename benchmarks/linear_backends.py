"""Sparse direct solvers with permissive licences and wheels, against CHOLMOD.

The exact solver's Levenberg-Marquardt system (H + mu diag(H), mu = 1e-8, at the file's
vertices / the city's dead reckoning; the (x, y, yaw) system of a planar graph) of each case of
:mod:`benchmarks.linear` is factored and solved by each backend, each in its own subprocess
(peak memory per backend).  Times: the analysis (ordering + symbolic, once per solve), the
numeric factorization and the solve (median of ``REPEATS``, the per-iteration cost of LM);
residual ``|H x - b| / |b|`` checks each.

Backends: ``cholmod`` (CHOLMOD through cvxopt, GPL-2.0+ supernodal module: the default),
``splu`` (SciPy's SuperLU, BSD), ``block`` (the package's block Cholesky, 3D systems only),
``pardiso`` (pypardiso, BSD-3, on Intel MKL's PARDISO: Intel Simplified Software License),
``qdldl`` (qdldl, Apache-2.0, with SuiteSparse AMD, BSD-3).  All but ``cholmod`` and ``block``
factor in their own ordering; ``cholmod``, ``splu`` and ``block`` take the solver's
fill-reducing order (cvxopt's AMD on the block graph).  Orderings, with CHOLMOD's numeric
factorization as the yardstick of their fill: cvxopt AMD (the default), METIS nested
dissection (pymetis: MIT, METIS Apache-2.0), SuperLU's MMD (the fallback without cvxopt).

Run one by hand: ``python -m benchmarks.linear_backends DATA_DIR CASE BACKEND``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from typing import Any

import numpy as np
import scipy.sparse as sp

from .linear import CASES, _load, _peak_mb, _rss_mb
from .metrics import Metric, info, markdown_table

REPEATS = 3
BACKENDS = ("cholmod", "splu", "block", "pardiso", "qdldl")
ORDERINGS = ("amd", "metis", "mmd")
#: The licence of each backend as installed from its wheel (what ships in it).
LICENCES = {
    "cholmod": "cvxopt GPL-3.0; CHOLMOD Supernodal GPL-2.0+",
    "splu": "SciPy BSD-3 (SuperLU BSD)",
    "block": "this package (MIT)",
    "pardiso": "pypardiso BSD-3; MKL Intel Simplified Software License (x86-64 wheels only)",
    "qdldl": "qdldl Apache-2.0 (bundles SuiteSparse AMD, BSD-3)",
}
#: Seconds allowed for one (case, backend) subprocess.
_TIME_LIMIT = 900.0


def _system(graph: Any) -> tuple[sp.csc_matrix, Any, Any]:
    """The damped LM system the exact solver factors first: its lower triangle in the
    solver's fill-reducing order (CSC), the pattern and the run (for the block backend)."""
    from hybridpgo.solvers.config import GaussNewtonConfig
    from hybridpgo.solvers.gauss_newton import _ensure_compiled, _Run

    _ensure_compiled()
    run = _Run.analyze(graph, None, None, GaussNewtonConfig(linear_solver="splu"))
    run.assemble()
    system = run.system
    values = np.array(system.values(run.data, None), np.float64)
    diag = values[system.diag_index]
    values[system.diag_index] = diag + 1e-8 * np.maximum(diag, 1e-12 * diag.max())
    low = sp.csc_matrix((values, system.indices, system.indptr), shape=(system.dim, system.dim))
    return low, system, run


def _full(low: sp.csc_matrix) -> sp.csr_matrix:
    full = (low + low.T - sp.diags(low.diagonal())).tocsr()
    full.sort_indices()
    return full


def _time(fn: Any, repeats: int = REPEATS) -> tuple[float, Any]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def _order(low: sp.csc_matrix, kind: str, block: int) -> np.ndarray:
    """A fill-reducing permutation (new position of each unknown) of the block graph."""
    from hybridpgo.solvers import _linear

    coo = sp.coo_matrix(low)
    nb = low.shape[0] // block
    br, bc = coo.row // block, coo.col // block
    key = np.unique(bc[br > bc] * nb + br[br > bc])
    rows, cols = key % nb, key // nb
    if kind == "metis":
        import pymetis

        adj = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(nb, nb))
        adj = (adj + adj.T).tocsr()
        adj.sort_indices()
        order = np.asarray(pymetis.nested_dissection(
            pymetis.CSRAdjacency(adj.indptr.astype(np.int32), adj.indices.astype(np.int32)))[0])
        new_block = np.empty(nb, np.int64)
        new_block[order] = np.arange(nb)
    elif kind == "mmd":
        saved = _linear._cvxopt_available
        _linear._cvxopt_available = lambda: False  # type: ignore[assignment]
        try:
            new_block = _linear._fill_reducing_order(nb, rows, cols)
        finally:
            _linear._cvxopt_available = saved  # type: ignore[assignment]
    else:
        new_block = np.arange(nb)  # the solver's matrix is already in AMD order
    return (block * new_block[:, None] + np.arange(block)[None, :]).ravel()


def worker(data_dir: str, case: str, backend: str) -> dict[str, Any]:
    """One (case, backend): analysis, numeric factorization and solve times; or an ordering
    (``order:amd|metis|mmd``) timed by CHOLMOD's numeric factorization."""
    from hybridpgo.solvers import _linear

    graph = _load(data_dir, case)
    low, system, run = _system(graph)
    dim = low.shape[0]
    block = 3 if run.planar else 6
    rng = np.random.default_rng(0)
    b = rng.standard_normal(dim)
    out: dict[str, Any] = {"case": case, "backend": backend, "unknowns": dim,
                           "nnz_lower": int(low.nnz)}
    rss0 = _rss_mb()
    full = _full(low)

    def residual(x: np.ndarray) -> float:
        return float(np.linalg.norm(full @ x - b) / np.linalg.norm(b))

    if backend.startswith("order:"):
        kind = backend.split(":", 1)[1]
        t0 = time.perf_counter()
        new_pos = _order(low, kind, block)
        out["order_s"] = time.perf_counter() - t0
        old_at = np.empty(dim, np.int64)
        old_at[new_pos] = np.arange(dim)
        perm = sp.tril(full[old_at][:, old_at], format="csc")
        perm.sort_indices()
        fac = _linear._Cholmod(_linear._CscPattern(perm))
        out["numeric_s"], _ = _time(lambda: fac.factor(np.asarray(perm.data, np.float64)))
        import cvxopt.cholmod as cm

        with _linear._cholmod_options(**_linear._CHOLMOD_OPTIONS):
            lfac = cm.getfactor(fac._factor)
        out["nnz_factor"] = len(lfac.V)
    elif backend in ("cholmod", "splu"):
        t0 = time.perf_counter()
        fac = _linear._Cholmod(system) if backend == "cholmod" else _linear._SuperLU(system)
        out["analyze_s"] = time.perf_counter() - t0
        vals = np.asarray(low.data, np.float64)
        out["numeric_s"], _ = _time(lambda: fac.factor(vals))
        out["solve_s"], x = _time(lambda: fac.solve_factored(b))
        out["residual"] = residual(np.asarray(x))
    elif backend == "block":
        if run.planar:
            return {**out, "skipped": "planar (x, y, yaw) system: the block Cholesky is 6x6"}
        from hybridpgo.solvers._block_cholesky import BlockCholesky

        pat = run.pat
        t0 = time.perf_counter()
        fac = BlockCholesky(pat.num_vars, pat.block_ptr, pat.block_row, pat.indptr)
        out["analyze_s"] = time.perf_counter() - t0
        vals = np.asarray(low.data, np.float64)  # the same layout as the solver's values
        fac.factor(vals)  # compile / load the kernels outside the timing
        out["numeric_s"], _ = _time(lambda: fac.factor(vals))
        out["solve_s"], x = _time(lambda: fac.solve_factored(b))
        out["residual"] = residual(np.asarray(x))
    elif backend == "pardiso":
        import pypardiso

        upper = sp.triu(full, format="csr")
        upper.sort_indices()
        solver = pypardiso.PyPardisoSolver(mtype=2)  # real symmetric positive definite
        solver.set_statistical_info_off()
        rhs = b.reshape(-1, 1)
        t0 = time.perf_counter()
        solver.set_phase(11)
        solver._call_pardiso(upper, rhs)
        out["analyze_s"] = time.perf_counter() - t0

        def numeric() -> None:
            solver.set_phase(22)
            solver._call_pardiso(upper, rhs)

        def solve() -> np.ndarray:
            solver.set_phase(33)
            return np.asarray(solver._call_pardiso(upper, rhs)).ravel()

        out["numeric_s"], _ = _time(numeric)
        out["solve_s"], x = _time(solve)
        out["residual"] = residual(x)
        out["threads"] = os.environ.get("MKL_NUM_THREADS", "default")
    elif backend == "qdldl":
        import qdldl

        upper = sp.triu(full, format="csc")
        t0 = time.perf_counter()
        solver = qdldl.Solver(upper, upper=True)  # AMD + symbolic + numeric
        out["analyze_s"] = time.perf_counter() - t0  # includes one numeric factorization
        out["numeric_s"], _ = _time(lambda: solver.update(upper, upper=True))
        out["solve_s"], x = _time(lambda: solver.solve(b))
        out["residual"] = residual(np.asarray(x))
    else:
        raise ValueError(backend)
    out["rss_before_mb"] = rss0
    out["peak_mb"] = _peak_mb()
    return out


def _run_case(data_dir: str, case: str, backend: str) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "benchmarks.linear_backends", data_dir, case, backend]
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        proc = subprocess.run(cmd, cwd=here, capture_output=True, text=True,
                              timeout=_TIME_LIMIT, check=False)
    except subprocess.TimeoutExpired:
        return {"case": case, "backend": backend, "timeout": _TIME_LIMIT}
    if proc.returncode != 0:
        return {"case": case, "backend": backend, "error": proc.stderr.strip()[-300:]}
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return result


def _cell(r: dict[str, Any], key: str, fmt: str = "{:.3f}") -> str:
    if "timeout" in r:
        return f"> {r['timeout']:.0f} s"
    if "error" in r or "skipped" in r:
        return "-"
    return fmt.format(r[key]) if key in r else "-"


def run(ctx: Any) -> tuple[list[Metric], list[str]]:
    data_dir = str(ctx.data_dir)
    cases = [c for c, _, _ in CASES]
    if ctx.quick:
        cases = ["M3500", "paris2_gps"]
    metrics: list[Metric] = []
    rows: list[list[Any]] = []
    order_rows: list[list[Any]] = []
    notes: list[str] = []
    for case in cases:
        res = {bk: _run_case(data_dir, case, bk) for bk in BACKENDS}
        for bk, r in res.items():
            print(f"  {case} {bk}: {r}", file=sys.stderr, flush=True)
            if "error" in r:
                notes.append(f"{case} {bk}: {r['error']}")
        ref = res["cholmod"]
        base = ref["numeric_s"] + ref["solve_s"]
        for bk, r in res.items():
            per_it = (r["numeric_s"] + r["solve_s"]) if "numeric_s" in r else float("nan")
            ratio = per_it / base
            if np.isfinite(ratio):
                metrics.append(info(f"linear_backends.{case}.{bk}.over_cholmod", ratio, "x"))
            rows.append([case, bk, ref["unknowns"], _cell(r, "analyze_s"),
                         _cell(r, "numeric_s"), _cell(r, "solve_s"),
                         f"{ratio:.2f}" if np.isfinite(ratio) else "-",
                         _cell(r, "residual", "{:.1e}"),
                         _cell(r, "peak_mb", "{:.0f}"), LICENCES[bk]])
        for kind in ORDERINGS:
            r = _run_case(data_dir, case, f"order:{kind}")
            print(f"  {case} order {kind}: {r}", file=sys.stderr, flush=True)
            order_rows.append([case, kind, _cell(r, "order_s"), _cell(r, "numeric_s"),
                               _cell(r, "nnz_factor", "{:d}")])
    tables = [markdown_table(
        f"LM system factored and solved by each backend (median of {REPEATS}; per LM "
        "iteration: numeric + solve); ratio to CHOLMOD; qualifies at <= 1.5 on paris2_gps",
        ["case", "backend", "unknowns", "analysis s", "numeric s", "solve s",
         "(numeric + solve) / CHOLMOD's", "residual", "peak MB", "licence (wheel)"], rows),
        markdown_table(
        "Fill-reducing orderings of the block graph, CHOLMOD's numeric factorization on each",
        ["case", "ordering", "ordering s", "CHOLMOD numeric s", "nnz(L)"], order_rows)]
    if notes:
        tables.append("Errors:\n\n" + "\n".join(f"- {n}" for n in notes))
    return metrics, tables


if __name__ == "__main__":
    print(json.dumps(worker(sys.argv[1], sys.argv[2], sys.argv[3])))
