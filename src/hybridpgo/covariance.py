"""Marginal covariances of selected poses at a solution (Laplace approximation).

Convention.  With measurement information ``Omega_c`` (inverse noise covariance) the energy
``E = sum_c e_c^T Omega_c e_c`` (no 1/2, DESIGN.md §1) is ``-2 log`` of the likelihood
``exp(-E / 2)``.  Linearized at the poses X with right perturbations ``X_i Exp(delta_i)`` (tangent
order (rho, phi): translation, then rotation, in the node's own frame), the poses are Gaussian in
delta with *information* ``H = J^T Omega J`` -- the matrix of the exact solver's normal equations
(:func:`hybridpgo.solvers.gauss_newton.normal_equations`), not the Hessian of E, which is 2H --
and covariance ``H^-1``.  This is GTSAM's ``Marginals`` with factors built from the same
``Omega`` (GTSAM's error is ``E / 2``), up to its (rotation, translation) tangent order.

Gauge: the same as the exact solver's (:func:`hybridpgo.solvers.gauss_newton.default_fixed_nodes`):
the ``FIX`` nodes, else pose 0, unless the graph has GPS constraints (then the earth frame and no
pose is fixed).  Covariances are relative to the gauge: a fixed pose has covariance 0.

Cost: one sparse Cholesky factorization of H (as one exact-solver iteration), then per requested
pose one triangular solve with 6 unit right-hand sides (``~12 nnz(L)`` flops; CHOLMOD:
``Y = L^-1 P E_i``, block ``= Y^T Y``) -- the inverse is never formed.  Suited to a selection of
poses; all N blocks would cost N such solves.

:func:`save_covariances` writes them as ``.npz`` (the layout of ``optimize --covariance``).
"""

from __future__ import annotations

import os
from typing import IO

import numpy as np
import numpy.typing as npt

from ._output import write_file
from .errors import SolverError
from .graph import FloatArray, PoseGraph
from .solvers._linear import _make_factorizer
from .solvers.gauss_newton import (
    _analyze,
    _assemble,
    _check_gauge,
    _full_system,
    _initial_poses,
    default_fixed_nodes,
)

__all__ = ["TANGENT_LABELS", "marginal_covariances", "save_covariances"]

#: The tangent order of every 6x6 covariance: translation (rho: x, y, z in metres), then rotation
#: (phi: x, y, z in radians), of the right perturbation ``X Exp(delta)`` in the pose's own frame.
TANGENT_LABELS = ("tx", "ty", "tz", "rx", "ry", "rz")


def marginal_covariances(graph: PoseGraph, rotations: FloatArray | None,
                         translations: FloatArray | None, nodes: npt.ArrayLike, *,
                         linear_solver: str = "auto") -> FloatArray:
    """Marginal covariances ``(H^-1)_ii`` of the selected poses (see the module docstring).

    Parameters
    ----------
    graph : PoseGraph
    rotations, translations : (N, 3, 3), (N, 3) float64 or None
        The poses to linearize at, normally a solution of :func:`solve_exact` (None: the graph's
        estimate).
    nodes : array_like of int, shape (k,)
        Dense indices of the poses (``graph.node_ids`` gives their file ids).
    linear_solver : {"auto", "cholmod", "splu"}
        As :attr:`hybridpgo.solvers.config.GaussNewtonConfig.linear_solver`.

    Returns
    -------
    (k, 6, 6) float64
        Covariance of ``delta_i`` in ``X_i Exp(delta_i)``, order (rho, phi) (metres, radians);
        symmetric positive definite, or 0 for a pose held fixed by the gauge.

    Raises
    ------
    ValueError
        A node index out of range, or poses of the wrong shape.
    GraphError
        A connected part has no fixed pose and no GPS constraint.
    SolverError
        H is singular to rounding (a pose not determined by its constraints) or the
        linearization is not finite.
    """
    sel = np.asarray(nodes)
    if sel.ndim != 1 or not (sel.size == 0 or np.issubdtype(sel.dtype, np.integer)):
        raise ValueError(f"nodes must be a 1-D array of dense node indices, got {nodes!r}")
    sel = sel.astype(np.int64)
    if sel.size and (sel.min() < 0 or sel.max() >= graph.num_nodes):
        raise ValueError(f"node indices must lie in 0..{graph.num_nodes - 1}, got "
                         f"{int(sel.min())}..{int(sel.max())}")
    rot, trans = _initial_poses(graph, rotations, translations)
    fixed = default_fixed_nodes(graph)
    _check_gauge(graph, fixed)
    pat = _analyze(graph, fixed, reorder=True)
    out = np.zeros((sel.shape[0], 6, 6))
    var = pat.var_of_node[sel]
    free = var >= 0
    if not free.any():
        return out
    data = np.empty(pat.nnz)
    grad = np.empty(pat.dim)
    _assemble(graph, pat, rot, trans, data, grad)
    factorizer = _make_factorizer(_full_system(pat), linear_solver)
    try:
        factorizer.factor(data)
        factorizer.check()
    except SolverError as exc:
        raise SolverError("the covariances are not defined at these poses: H is singular to "
                          "rounding (a pose is not determined by its constraints, or the "
                          "information is too ill-conditioned)") from exc
    index = 6 * var[free][:, None] + np.arange(6, dtype=np.int64)[None, :]
    out[free] = factorizer.inverse_blocks(index)
    return out


def save_covariances(path: str | os.PathLike[str], ids: npt.ArrayLike,
                     covariances: npt.ArrayLike, *, fixed_ids: npt.ArrayLike = ()) -> None:
    """Write covariances as an ``.npz`` archive (the output rules of ``docs/security.md``:
    a temporary file renamed into place, symbolic links written through).

    The archive holds ``ids`` (k,) int64 file ids of the poses; ``cov`` (k, 6, 6) float64, the
    covariance of ``delta`` in ``X Exp(delta)`` in tangent order ``tangent`` (``TANGENT_LABELS``:
    tx ty tz rx ry rz, metres and radians); ``fixed_ids`` (f,) int64, the poses the gauge
    holds fixed (their covariance is 0; empty when GPS anchors the earth frame).  Read it with
    ``numpy.load(path)`` (no pickle needed).

    Raises
    ------
    ValueError
        Shapes that do not match.
    FormatError
        The file cannot be written (nothing is left behind).
    """
    ids_arr = np.asarray(ids, np.int64)
    cov = np.asarray(covariances, np.float64)
    if ids_arr.ndim != 1 or cov.shape != (ids_arr.shape[0], 6, 6):
        raise ValueError(f"need ids (k,) and covariances (k, 6, 6), got {ids_arr.shape} and "
                         f"{cov.shape}")
    name = os.fspath(path)
    fixed = np.asarray(fixed_ids, np.int64).reshape(-1)

    def dump(fh: IO[bytes]) -> None:
        np.savez(fh, ids=ids_arr, cov=cov, tangent=np.array(TANGENT_LABELS), fixed_ids=fixed)

    write_file(name, dump)
