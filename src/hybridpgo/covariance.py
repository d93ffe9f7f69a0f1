"""Marginal covariances of selected poses at a solution (Laplace approximation).

Convention.  With measurement information ``Omega_c`` (inverse noise covariance) the energy
``E = sum_c e_c^T Omega_c e_c`` (no 1/2, docs/conventions.md) is ``-2 log`` of the likelihood
``exp(-E / 2)``.  Linearized at the poses X with right perturbations ``X_i Exp(delta_i)`` (tangent
order (rho, phi): translation, then rotation, in the node's own frame), the poses are Gaussian in
delta with *information* ``H = J^T Omega J`` -- the matrix of the exact solver's normal equations
(:func:`hybridpgo.solvers.gauss_newton.normal_equations`), not the Hessian of E, which is 2H --
and covariance ``H^-1``.  This is GTSAM's ``Marginals`` with factors built from the same
``Omega`` (GTSAM's error is ``E / 2``), up to its (rotation, translation) tangent order.

Gauge: the same as the exact solver's (:func:`hybridpgo.solvers.gauss_newton.default_fixed_nodes`):
the ``FIX`` nodes, else pose 0, unless the graph has GPS constraints (then the earth frame and no
pose is fixed).  Covariances are relative to the gauge: a fixed pose has covariance 0.

Cost (``linear_solver="auto"``): one block Cholesky factorization of H in 6x6 pose blocks
(:class:`hybridpgo.linalg.BlockCholesky`, as in an exact-solver iteration), then selected
inversion (:mod:`hybridpgo.linalg._selinv`): Takahashi's recurrences give ``H^-1``
on the factor's sparsity pattern, so the diagonal blocks of *every* pose come in about twice the
factorization's time and in the factor's own memory -- the dense inverse is never formed.  With
``"cholmod"`` or ``"splu"`` the named library factors H and each requested pose costs one
triangular solve with 6 unit right-hand sides (``~12 nnz(L)`` flops).

:func:`save_covariances` writes them as ``.npz`` (the layout of ``optimize --covariance``).
"""

from __future__ import annotations

import os
from typing import IO

import numpy as np
import numpy.typing as npt

from ._output import write_file
from .graph import FloatArray, PoseGraph
from .solvers.config import GaussNewtonConfig
from .solvers.gauss_newton import ExactSolver

__all__ = ["TANGENT_LABELS", "marginal_covariances", "save_covariances"]

#: The tangent order of every 6x6 covariance: translation (rho: x, y, z in metres), then rotation
#: (phi: x, y, z in radians), of the right perturbation ``X Exp(delta)`` in the pose's own frame.
TANGENT_LABELS = ("tx", "ty", "tz", "rx", "ry", "rz")


def marginal_covariances(graph: PoseGraph, rotations: FloatArray | None,
                         translations: FloatArray | None, nodes: npt.ArrayLike | None = None,
                         *, linear_solver: str = "auto") -> FloatArray:
    """Marginal covariances ``(H^-1)_ii`` of the poses (see the module docstring).

    Parameters
    ----------
    graph : PoseGraph
    rotations, translations : (N, 3, 3), (N, 3) float64 or None
        The poses to linearize at, normally a solution of :func:`solve_exact` (None: the graph's
        estimate).
    nodes : array_like of int, shape (k,), optional
        Dense indices of the poses (``graph.node_ids`` gives their file ids); None (the
        default): every pose, ``k = N``.
    linear_solver : {"auto", "cholmod", "splu"}
        "auto": the block Cholesky factor and selected inversion (every pose for about the
        price of two factorizations); "cholmod" or "splu": that library's factorization and
        one triangular solve per requested pose (an independent route, for checks).

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
    sel = np.arange(graph.num_nodes) if nodes is None else np.asarray(nodes)
    if sel.ndim != 1 or not (sel.size == 0 or np.issubdtype(sel.dtype, np.integer)):
        raise ValueError(f"nodes must be a 1-D array of dense node indices, got {nodes!r}")
    sel = sel.astype(np.int64)
    if sel.size and (sel.min() < 0 or sel.max() >= graph.num_nodes):
        raise ValueError(f"node indices must lie in 0..{graph.num_nodes - 1}, got "
                         f"{int(sel.min())}..{int(sel.max())}")
    solver = ExactSolver(graph, GaussNewtonConfig(
        linear_solver=linear_solver))  # type: ignore[arg-type]  # checked there
    out = np.zeros((sel.shape[0], 6, 6))
    var = solver.pattern.var_of_node[sel]
    free = var >= 0
    if solver.pattern.num_vars == 0:
        return out
    if linear_solver == "auto":
        block = solver.factor(rotations, translations, block=True)
        out[free] = block.inverse_diagonal_blocks(overwrite=True)[var[free]]
        return out
    factorizer = solver.factor(rotations, translations)
    if free.any():
        index = 6 * var[free][:, None] + np.arange(6, dtype=np.int64)[None, :]
        out[free] = factorizer.inverse_blocks(index)
    return out


def save_covariances(path: str | os.PathLike[str], ids: npt.ArrayLike,
                     covariances: npt.ArrayLike, *, fixed_ids: npt.ArrayLike = ()) -> None:
    """Write covariances as an ``.npz`` archive (the output rules of :mod:`hybridpgo._output`:
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
