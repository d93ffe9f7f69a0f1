"""Certificates of global optimality in SE-Sync's model of a pose graph, and its relaxation.

The model (SE-Sync: Rosen, Carlone, Bandeira & Leonard, IJRR 2019, "Problem 1")
-------------------------------------------------------------------------------
::

    F(t, R) = sum_c kappa_c ||R_b - R_a Rm_c||_F^2 + tau_c ||t_b - t_a - R_a tm_c||^2

over rotations ``R_i`` and positions ``t_i`` (``Rm_c, tm_c``: the measurement of constraint
``c = (a, b)``), with one isotropic rotational and one translational weight per constraint,
taken from its information matrix as SE-Sync's loader does (cross terms are ignored):

* 3D: ``tau = 3 / tr(Omega_tt^-1)`` and ``kappa = 3 / (2 tr(Omega_q^-1))`` with ``Omega_q`` the
  g2o rotation block over ``q_vec``.  Our information is over ``phi`` with
  ``Omega_phi = Omega_q / 4`` (:mod:`hybridpgo.io.g2o`), so ``kappa = 6 / tr(Omega_phi^-1)``.
* 2D: ``tau = 2 / tr(Omega_xy^-1)`` and ``kappa = Omega_theta_theta``.

GPS constraints (a position ``g`` of pose ``i`` in the earth frame) enter as relative
constraints from one more unknown pose, the earth frame ``(R_e, t_e)``:
``tau_g ||t_i - t_e - R_e g||^2`` with ``tau_g = d / tr(Omega_g^-1)`` (as a relative constraint's
translation) and no rotation term.  F is then invariant under a rigid motion of every pose *and*
the earth, so the earth is the gauge (held at the identity); at ``R_e = I, t_e = 0`` the term is
``tau_g ||t_i - g||^2``, E's GPS term with isotropic information.  On planar graphs this
relaxation certifies as SE-Sync's does (M3500 and intel with a GPS reading every 100 poses:
gaps <= 1e-7).  In 3D, S is ill-conditioned along the earth's rotation, whose rows answer to
the readings alone: S can have eigenvalues far below those of S without those rows, so that the
shift that makes ``S + sigma I`` definite bounds the gap loosely or not at all.  At rank d the
certificate of a 3D graph with GPS therefore holds the earth's rotation at the identity (the
*earth-fixed form*): with ``Y_e = I`` F is a quadratic
``tr(Y_r^T Q_rr Y_r) + 2 tr(Y_r^T Q_re) + tr(Q_ee)`` in the graph's rotations ``Y_r``.  With
``S_rr`` (S without the earth's rows and columns) and ``P = S_rr + sigma I`` positive definite,
every ``Y_r`` with orthonormal blocks has ``F = tr(Y_r^T P Y_r) + 2 tr(Y_r^T Q_re) + tr(Q_ee) +
sum_(i != e) tr(Lambda_i) - sigma d (n - 1)``, and its minimum over unconstrained ``Y_r`` is a
lower bound of F's global minimum, ``tr(G^T P^-1 G)`` below F at the point
(``G = P Y_r + Q_re``, :meth:`SyncProblem._earth_fixed_gap`).  It is the value of a feasible
point of the same relaxation's dual (``Lambda_i - sigma I`` for the graph's rotations,
``Q_ee - Q_er P^-1 Q_re`` for the earth's): the form changes which dual point is tested, not
the relaxation.  Planar graphs keep the lifted form, which certifies them; the staircase's
ranks above d lift the earth's rotation (:func:`staircase_start`).

``F`` is **not** the energy E the solvers minimize (E uses geodesic ``Log`` errors and the full
information): it is the objective that SE-Sync's certificate and its published optimal values
refer to.  :func:`sesync_weights` computes the weights.

Form
----
Stack the unknowns as ``V = [T; Y]``: ``T`` (n, k) holds the positions, ``Y`` (d n, k) the
rotations, in block rows of ``d`` rows.  In 3D (real, ``d = k = 3``) ``T`` row ``i`` is
``t_i^T`` and ``Y_i = R_i^T``; in 2D the problem is written over complex numbers as in
Cartan-Sync / CPL-SLAM (Fan et al.): ``d = k = 1``, ``T_i = x_i + i y_i`` and
``Y_i = z_i = exp(i theta_i)``, with ``||R_b - R_a Rm||_F^2 = 2 |z_b - z_a r_c|^2``.  Then
``F = tr(V^H M V)`` for a sparse Hermitian ``M``; eliminating the positions (the gauge pose's
held at 0) leaves ``F = tr(Y^H Q Y)`` with the Schur complement ``Q = A - B D^-1 B^H`` (``D``:
the ``tau``-weighted position Laplacian, factored once; ``Q`` stays implicit).

Relaxation and certificate
--------------------------
The rank-restricted relaxation replaces each block ``Y_i`` by a (d, p) block with orthonormal
rows (:meth:`SyncProblem.minimize`; p = d is the problem itself).  For *any* such ``Y`` let
``Lambda = Herm(BlockDiag(Q Y Y^H))`` and ``S = Q - Lambda`` (the certificate matrix).  If
``S + sigma I`` is positive semidefinite, ``Lambda - sigma I`` is feasible for the dual of the
semidefinite relaxation, whose value ``tr(Lambda) - sigma d n = tr(Y^H Q Y) - sigma d n`` is
then a lower bound of F's global minimum (weak duality).  At a rank-d point (rotations) this
bounds how far F there is above F's global minimum: ``gap <= sigma d n``.  The test "``S + sigma
I`` is positive definite" is one sparse Cholesky factorization, of ``M`` with the gauge
position removed and ``Lambda - sigma I`` subtracted from its rotation block (its Schur
complement is ``S + sigma I``); the smallest eigenvalue of S is found by Lanczos iterations on
``(S + sigma I)^-1`` with that factorization (shift-invert, SE-Sync's approach; a handful of
solves).  :func:`sesync_certificate` first refines the given rotations to a stationary point of
F with Newton's method (:meth:`SyncProblem.refine`): the certificate needs a stationary point
of F, and ours (E's) is not one.

What "certified" means (:func:`certify`)
----------------------------------------
The solution's F-refined rotations are the global minimum of F within the gap bound, *and* the
exact solver started there (the certified start) ends at the solution's energy E (within
:data:`SAME_OPTIMUM` relative): the solution is what a certifiably optimal start leads to.  It
is not a proof that E has no lower minimum elsewhere: E and F are different functions.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from .errors import HybridPGOError
from .graph import FloatArray, PoseGraph

__all__ = ["Certificate", "SyncProblem", "certify", "ensure_compiled", "gps_weights",
           "sesync_certificate", "sesync_weights", "staircase_start", "sync_problem"]

ComplexArray = npt.NDArray[np.complex128]
Array = npt.NDArray[Any]

#: Relative gap bound up to which a stationary point of F counts as certified (gap / F).
GAP_TOLERANCE = 1e-6
#: The certificate's smallest shift, relative to the largest diagonal entry of M: a Cholesky
#: factorization of a matrix with condition number up to ~1e12 still decides its sign reliably.
_SHIFT_FLOOR = 1e-13
#: Relative gap bound up to which the smallest shift (``_SHIFT_FLOOR``) still certifies.  Where F
#: is small next to M's entries (few loops, little noise: F/(d n) ~ 0.03 on generated cities
#: with 1e6 information) even that shift bounds the gap only to ~1e-5 F: S is positive
#: semidefinite as far as float64 can tell, and the (rigorous) gap reported is the shift's.
FLOOR_GAP_TOLERANCE = 1e-4
#: Energies of two polishes within this fraction are the same optimum.
SAME_OPTIMUM = 1e-9
#: Newton on F stops when the predicted decrease is below this fraction of F.
_NEWTON_TOLERANCE = 1e-14
#: Factorizations Newton's method on F makes at most (:meth:`SyncProblem.refine`).
NEWTON_FACTORIZATIONS = 30
#: A factorization of F's Hessian is reused while each step's predicted decrease falls at
#: least this many times below the last one (a chord step costs a solve and a gradient, a
#: refactorization is then due).  M3500_isam: 13 chord steps at a rate of 3-10 (34 ms), or 2
#: factorizations and 7 steps at 10 (22 ms); intel, garage, sphere2500 take the same steps
#: either way.
_CHORD_RATE = 10.0
#: Newton's damping on F (``H + mu diag(H)``) starts here when H is not positive definite, and
#: grows this many times per failed factorization; a damped step that lowers F divides it as
#: much (to 0 below 10x the floor).  F's Hessian is indefinite far from a minimum: on garage,
#: sphere2200 and sphere_bignoise from the chordal start, steps of 10x from 1e-8 took 7, 5 and
#: 11 factorizations (3, 2 and 5 of them failed ones, each nearly as costly as a good one),
#: these take 4, 3 and 8; the other benchmark files take the same number either way.
_DAMPING_FLOOR = 1e-6
_DAMPING_INDEFINITE = 100.0
#: After an undamped factorization failed (H indefinite), a step damped near the floor returns
#: to mu = 0 only when F fell by its predicted decrease within this fraction (the model has
#: become Newton's).  Returning to 0 after every damped step costs a failed factorization per
#: step wherever H stays indefinite (``benchmarks/results/2026-11-30-scale-d``: the 100 000-pose
#: city's certificate, half of Newton's 30 factorizations from the chordal start).
_NEWTON_LIKE = 0.25

_E = np.zeros((3, 3, 3))
_E[0, 2, 1], _E[0, 1, 2] = 1.0, -1.0
_E[1, 0, 2], _E[1, 2, 0] = 1.0, -1.0
_E[2, 1, 0], _E[2, 0, 1] = 1.0, -1.0
#: hat(e_k) for k = 0, 1, 2, and (hat(e_k) hat(e_l) + hat(e_l) hat(e_k)) / 2.
_GEN = _E
_GEN2 = 0.5 * (np.einsum("kab,lbc->klac", _E, _E) + np.einsum("lab,kbc->klac", _E, _E))


def sesync_weights(graph: PoseGraph) -> tuple[FloatArray, FloatArray]:
    """SE-Sync's isotropic weights ``(kappa, tau)`` of every relative constraint.

    3D: ``kappa = 6 / tr(Omega_phi^-1)`` (SE-Sync's ``3 / (2 tr(Omega_q^-1))`` in g2o's
    ``q_vec`` units), ``tau = 3 / tr(Omega_rho^-1)``; 2D: ``kappa = Omega_yaw,yaw``,
    ``tau = 2 / tr(Omega_xy^-1)`` (the module docstring).
    """
    info = graph.edge_information
    if graph.is_2d:
        kappa = np.array(info[:, 5, 5], np.float64)
        tau = 2.0 / np.trace(np.linalg.inv(info[:, :2, :2]), axis1=1, axis2=2)
    else:
        kappa = 6.0 / np.trace(np.linalg.inv(info[:, 3:, 3:]), axis1=1, axis2=2)
        tau = 3.0 / np.trace(np.linalg.inv(info[:, :3, :3]), axis1=1, axis2=2)
    return kappa, tau


def gps_weights(graph: PoseGraph) -> FloatArray:
    """The isotropic weight ``tau`` of every GPS constraint, as :func:`sesync_weights` weighs a
    relative constraint's translation: ``3 / tr(Omega^-1)`` (3D), ``2 / tr(Omega_xy^-1)``
    (2D)."""
    info = graph.gps_information
    dim = 2 if graph.is_2d else 3
    out: FloatArray = dim / np.trace(np.linalg.inv(info[:, :dim, :dim]), axis1=1, axis2=2)
    return out


def _hat(v: FloatArray) -> FloatArray:
    """(..., 3, 3) cross-product matrices of (..., 3) vectors."""
    out: FloatArray = np.einsum("...k,kij->...ij", v, _GEN)
    return out


def _pair(m: FloatArray) -> FloatArray:
    """``<M, hat(e_k)>`` for k = 0, 1, 2 of (..., 3, 3) matrices (twice the axial vector of
    M's antisymmetric part)."""
    return np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                     m[..., 1, 0] - m[..., 0, 1]], axis=-1)


def _sym_minus_trace(m: FloatArray) -> FloatArray:
    """``sym(M) - tr(M) I`` of (..., 3, 3) matrices."""
    out: FloatArray = 0.5 * (m + np.swapaxes(m, -1, -2)) - np.trace(
        m, axis1=-2, axis2=-1)[..., None, None] * np.eye(3)
    return out


def _herm(x: Array) -> Array:
    out: Array = 0.5 * (x + np.conj(np.swapaxes(x, -1, -2)))
    return out


@dataclass(frozen=True)
class Spectrum:
    """The certificate matrix's smallest eigenvalue at a point, and what it proves."""

    objective: float
    """F at the point (``tr(Y^H Q Y)``)."""
    shift: float
    """The smallest shift sigma tried with ``S + sigma I`` positive definite (inf: none)."""
    lambda_min: float
    """The smallest eigenvalue of S (Lanczos on ``(S + shift I)^-1``; nan if not found)."""
    vector: Array | None
    """Its eigenvector (d n, one column of Y's layout), or None."""
    lower_bound: float
    """A lower bound of F's global minimum (-inf: none): ``objective - shift d n``, or with
    the earth-fixed form (:meth:`SyncProblem.spectrum`) its own bound."""
    factorizations: int
    """Sparse factorizations spent (one per shift tried)."""
    floor: float = 0.0
    """The ladder's smallest shift (below it a factorization does not resolve the sign)."""
    earth_held: bool = False
    """The earth-fixed form (3D with GPS, rank d): S is the graph's rotations' part."""
    definite: float = float("inf")
    """The first shift of the ladder with ``S + sigma I`` positive definite, whether or not
    it certifies (inf: none tried was)."""
    excess: float = float("nan")
    """The earth-fixed form: F less its lower bound at :attr:`definite`
    (:meth:`SyncProblem._earth_fixed_gap`; NaN: not computed)."""


class SyncProblem:
    """A pose graph in SE-Sync's model (module docstring): the data matrix M, its Schur
    complement Q (implicit), the rank-restricted relaxation, Newton's method on F and the
    certificate.

    Parameters
    ----------
    graph : PoseGraph
        2D graphs use the complex form (one complex number per rotation and per position), 3D
        graphs the real one.  A graph with GPS constraints gets one more unknown pose, the
        earth frame (index ``num_poses``, the gauge), and each GPS reading becomes a relative
        constraint from it with no rotation term (``kappa = 0``, ``tau``: :func:`gps_weights`);
        such a graph may not also fix a pose.  It must be connected (ValueError otherwise).
    weights : {"sesync", "planar"}
        ``"sesync"``: :func:`sesync_weights`.  ``"planar"`` (2D only): ``kappa`` the yaw
        information over ``|z_b - z_a r_c|^2`` and ``tau`` the mean of the x and y information
        (the weights of :func:`hybridpgo.initialization.planar_relaxation_start`).
    """

    def __init__(self, graph: PoseGraph, weights: str = "sesync") -> None:
        if graph.num_gps and graph.fixed_nodes.size:
            raise ValueError("SE-Sync's model of a graph with GPS constraints holds the earth "
                             "frame, not a fixed pose")
        if weights not in ("sesync", "planar") or (weights == "planar" and not graph.is_2d):
            raise ValueError(f"weights must be 'sesync' or, for 2D graphs, 'planar'; got "
                             f"{weights!r}")
        gps = graph.num_gps
        self.num_poses = graph.num_nodes
        """The graph's poses: the problem's first unknowns (the earth frame's follows)."""
        self.earth = graph.num_nodes if gps else -1
        """Index of the earth frame's unknowns (-1: no GPS constraint)."""
        n = graph.num_nodes + (1 if gps else 0)
        self.n = n
        self.complex = bool(graph.is_2d)
        d = 1 if self.complex else 3
        self.d = d
        if gps:
            self.gauge = self.earth
        else:
            self.gauge = int(graph.fixed_nodes[0]) if graph.fixed_nodes.size else 0
        # a GPS constraint is a relative one from the earth frame with no rotation term
        a = np.concatenate([graph.edge_nodes[:, 0].astype(np.int64), np.full(gps, self.earth)])
        b = np.concatenate([graph.edge_nodes[:, 1].astype(np.int64),
                            graph.gps_nodes.astype(np.int64)])
        m = a.size
        if np.unique(graph.connected_components()).size > 1:
            # D, the position Laplacian, would be singular (a pose without constraints, or
            # parts that nothing ties together): F has no unique optimal positions
            raise ValueError("SE-Sync's model needs a connected graph (every pose tied to "
                             "the others by constraints); this one is not (see "
                             "PoseGraph.check_connected)")
        kappa, tau = sesync_weights(graph)
        tau_gps = gps_weights(graph)
        if weights == "planar":
            info = graph.edge_information
            kappa, tau = info[:, 5, 5] / 2.0, 0.5 * (info[:, 0, 0] + info[:, 1, 1])
            tau_gps = 0.5 * (graph.gps_information[:, 0, 0] + graph.gps_information[:, 1, 1])
        kappa = np.concatenate([kappa, np.zeros(gps)])
        tau = np.concatenate([tau, tau_gps])
        rot_m = np.concatenate([graph.edge_rotations, np.broadcast_to(np.eye(3), (gps, 3, 3))])
        trans_m = np.concatenate([graph.edge_translations, graph.gps_positions])
        one = np.ones((m, 1, 1))
        # residual = sum_k c_k V_k (V_k: the rows of one unknown, named by its pose, a (0) or b
        # (1), and its first slot in that pose's block: the position is slot 0, the
        # rotation's d rows follow); each term w ||residual||^2 adds w c_p^H c_q to M
        terms: list[tuple[list[tuple[int, int, Array]], FloatArray]]
        if self.complex:
            rz = rot_m[:, 0, 0] + 1j * rot_m[:, 1, 0]
            rz = rz / np.abs(rz)
            tz = trans_m[:, 0] + 1j * trans_m[:, 1]
            terms = [([(1, 1, one), (0, 1, -rz[:, None, None])], 2.0 * kappa),
                     ([(1, 0, one), (0, 0, -one), (0, 1, -tz[:, None, None])], tau)]
        else:
            eye = np.broadcast_to(np.eye(3), (m, 3, 3))
            terms = [([(1, 1, eye), (0, 1, -np.swapaxes(rot_m, 1, 2))], kappa),
                     ([(1, 0, one), (0, 0, -one), (0, 1, -trans_m[:, None, :])], tau)]
        dtype = np.complex128 if self.complex else np.float64
        size = 1 + d  # a pose's unknowns: its position, then its rotation's d rows
        # each constraint's part of the pose blocks (a, a), (a, b), (b, a), (b, b)
        part = np.zeros((4, m, size, size), dtype)
        for blocks, w in terms:
            for end_p, at_p, cp in blocks:
                for end_q, at_q, cq in blocks:
                    part[2 * end_p + end_q, :, at_p: at_p + cp.shape[2],
                         at_q: at_q + cq.shape[2]] += (
                        w[:, None, None] * (np.conj(np.swapaxes(cp, 1, 2)) @ cq))
        # M pose by pose: (size, size) blocks on the pose graph (and every diagonal block)
        self._edges = (a, b)
        bm = self._block_map(np.arange(n))
        at = bm["where"].ravel()
        order = np.argsort(at, kind="stable")
        first = np.flatnonzero(np.diff(at[order], prepend=-1))
        pose = np.zeros((bm["nblocks"], size, size), dtype)
        if m:
            pose[at[order[first]]] = np.add.reduceat(part.reshape(4 * m, size, size)[order],
                                                     first, axis=0)
        del part
        block_ptr, block_col = bm["indptr"], bm["indices"]
        self._pose = (pose, block_ptr, block_col, bm["diag"])
        keep = np.flatnonzero(np.arange(n) != self.gauge)
        self._t_keep = keep
        self._weights = (np.ascontiguousarray(2.0 * kappa if self.complex else kappa, np.float64),
                         np.ascontiguousarray(tau, np.float64))
        if self.complex:
            self._measured: tuple[Array, Array] = (rz, tz)
        else:
            self._measured = (np.ascontiguousarray(rot_m, np.float64),
                              np.ascontiguousarray(trans_m, np.float64))
        self._a = sp.csr_matrix(sp.bsr_matrix((pose[:, 1:, 1:], block_col, block_ptr),
                                              shape=(d * n, d * n)))
        self._a.eliminate_zeros()
        b_all = sp.csr_matrix(sp.bsr_matrix((pose[:, 1:, :1], block_col, block_ptr),
                                            shape=(d * n, n)))
        self._b = sp.csr_matrix(b_all[:, keep])
        self._b.eliminate_zeros()
        self._bh = sp.csr_matrix(self._b.conj().T)
        laplacian = sp.csr_matrix((np.ascontiguousarray(pose[:, 0, 0].real), block_col,
                                   block_ptr), shape=(n, n))
        from .linalg import SparseSPD

        self._d = SparseSPD(sp.csc_matrix(laplacian[keep][:, keep]))
        self._d.factor(check=True)
        self._newton: dict[str, Any] | None = None
        self.refine_converged = False
        """Whether the last :meth:`refine` converged (False before any, and when it stopped at
        its caps)."""
        self._cert: dict[str, Any] | None = None

    @property
    def m(self) -> sp.csr_matrix:
        """The data matrix M (module docstring, ``F = tr(V^H M V)``) over ``V = [T; Y]``: the n
        positions' rows, then the rotations' ``d n`` (pose ``i``'s ``d`` rows at ``n + d i``);
        canonical CSR without stored zeros, built on each access from M's pose blocks, which
        the problem keeps."""
        pose, block_ptr, block_col, _ = self._pose
        n, d = self.n, self.d
        size = 1 + d
        whole = sp.csr_matrix(sp.bsr_matrix((pose, block_col, block_ptr),
                                            shape=(size * n, size * n)))
        start = size * np.arange(n)
        order = np.concatenate([start, (start[:, None] + 1 + np.arange(d)[None, :]).ravel()])
        out = sp.csr_matrix(whole[order][:, order])
        out.eliminate_zeros()
        out.sort_indices()
        return out

    # ------------------------------------------------------------------ conversions
    def to_y(self, rotations: FloatArray) -> Array:
        """Rotations (N, 3, 3) as the rank-d ``Y`` (d n, d); the graph's N poses get the
        identity appended for the earth frame (GPS)."""
        if rotations.shape[0] == self.num_poses < self.n:
            rotations = np.concatenate([rotations, np.eye(3)[None]])
        if self.complex:
            z = rotations[:, 0, 0] + 1j * rotations[:, 1, 0]
            return np.asarray((z / np.abs(z))[:, None], np.complex128)
        return np.ascontiguousarray(np.swapaxes(rotations, 1, 2).reshape(3 * self.n, 3))

    def rotations(self, y: Array) -> FloatArray:
        """Rotations (N, 3, 3) from a rank-d ``Y`` whose blocks are rotations."""
        n = self.n
        if self.complex:
            z = y[:, 0]
            out = np.zeros((n, 3, 3))
            out[:, 0, 0] = out[:, 1, 1] = z.real
            out[:, 1, 0] = z.imag
            out[:, 0, 1] = -z.imag
            out[:, 2, 2] = 1.0
            return out
        return np.ascontiguousarray(np.swapaxes(y.reshape(n, 3, 3), 1, 2))

    def translations(self, t: Array) -> FloatArray:
        """Positions (N, 3) from ``T`` (n, d)."""
        if self.complex:
            out = np.zeros((self.n, 3))
            out[:, 0], out[:, 1] = t[:, 0].real, t[:, 0].imag
            return out
        return np.ascontiguousarray(t, np.float64)

    def poses(self, y: Array, reference: tuple[FloatArray, FloatArray] | None = None
              ) -> tuple[FloatArray, FloatArray]:
        """The graph's poses ``(R, t)`` (N of them) of a rank-d ``Y`` with its optimal
        positions, expressed in the frame of ``reference`` at the gauge pose (the same pose
        there; none: as they are).  With GPS constraints always in the earth frame (its
        unknowns turned to the identity), whatever ``reference``."""
        rot = self.rotations(y)
        trans = self.translations(self.positions(y))
        g = self.gauge
        there: tuple[FloatArray, FloatArray] | None = None  # the gauge pose's new frame
        if self.earth >= 0:
            there = (np.eye(3), np.zeros(3))
        elif reference is not None:
            there = (reference[0][g], reference[1][g])
        if there is not None:
            turn = there[0] @ rot[g].T
            if self.complex:  # keep the planar form exact
                c, s = turn[0, 0], turn[1, 0]
                h = np.hypot(c, s)
                turn = np.array([[c / h, -s / h, 0.0], [s / h, c / h, 0.0], [0.0, 0.0, 1.0]])
            rot = turn[None] @ rot
            trans = (trans - trans[g]) @ turn.T + there[1]
        return rot[:self.num_poses], trans[:self.num_poses]

    # ------------------------------------------------------------------ Q and F
    def _dsolve(self, rhs: Array) -> Array:
        """``D^-1 rhs`` for an (n-1, k) right-hand side (complex: one real solve of 2k)."""
        if not self.complex:
            return self._d.solve(np.asarray(rhs, np.float64))
        k = rhs.shape[1]
        x = self._d.solve(np.concatenate([rhs.real, rhs.imag], axis=1))
        out: Array = x[:, :k] + 1j * x[:, k:]
        return out

    def q(self, y: Array) -> Array:
        """``Q Y`` for Y (d n, p)."""
        out: Array = self._a @ y - self._b @ self._dsolve(self._bh @ y)
        return out

    def cost(self, y: Array) -> float:
        """``tr(Y^H Q Y)``: F at the rotations Y (rank d) with their optimal positions."""
        return float(np.real(np.vdot(y, self.q(y))))

    def positions(self, y: Array) -> Array:
        """The optimal ``T`` (n, p) for Y (the gauge pose's row 0)."""
        out = np.zeros((self.n, y.shape[1]), y.dtype)
        out[self._t_keep] = -self._dsolve(self._bh @ y)
        return out

    def lambda_blocks(self, y: Array, qy: Array | None = None) -> Array:
        """``Lambda``: the (n, d, d) Hermitian diagonal blocks of ``Q Y Y^H`` (``qy``: ``Q Y``
        when computed already)."""
        n, d = self.n, self.d
        qyb = (self.q(y) if qy is None else qy).reshape(n, d, -1)
        yb = y.reshape(n, d, -1)
        return _herm(qyb @ np.conj(np.swapaxes(yb, 1, 2)))

    @property
    def holds_earth(self) -> bool:
        """Whether rank-d certificates hold the earth frame's rotation at the identity (the
        earth-fixed form, module docstring: a 3D graph with GPS)."""
        return self.earth >= 0 and not self.complex

    def certificate_product(self, y: Array, x: Array) -> Array:
        """``S X = Q X - Lambda(Y) X`` for X (d n, k)."""
        n, d = self.n, self.d
        lam = self.lambda_blocks(y)
        out: Array = self.q(x) - (lam @ x.reshape(n, d, -1)).reshape(n * d, -1)
        return out

    # ------------------------------------------------------------------ manifold
    def tangent(self, y: Array, v: Array) -> Array:
        """Projection of V onto the tangent space at Y (blocks with orthonormal rows)."""
        n, d = self.n, self.d
        if d == 1:
            out: Array = v - np.real(np.sum(np.conj(y) * v, axis=1, keepdims=True)) * y
            return out
        yb = y.reshape(n, d, -1)
        vb = v.reshape(n, d, -1)
        sym = _herm(vb @ np.conj(np.swapaxes(yb, 1, 2)))
        moved: Array = (vb - sym @ yb).reshape(v.shape)
        return moved

    def retract(self, v: Array) -> Array:
        """The nearest Y with orthonormal block rows (polar factor of each block)."""
        if self.d == 1:
            out: Array = v / np.linalg.norm(v, axis=1, keepdims=True)
            return out
        from ._sync_kernels import polar_rows

        blocks = np.ascontiguousarray(np.real(v), np.float64).reshape(self.n, self.d, -1)
        polar = np.empty_like(blocks)
        ok = np.empty(self.n, np.bool_)
        polar_rows(blocks, polar, ok)  # Newton's iteration, in a kernel (a batched SVD is slower)
        if not ok.all():  # nearly dependent rows: the SVD's polar factor
            u, _, vh = np.linalg.svd(blocks[~ok], full_matrices=False)
            polar[~ok] = u @ vh
        return polar.reshape(v.shape)

    def minimize(self, y: Array, max_iterations: int, gradient_tolerance: float = 1e-6,
                 stall: float = 1e-6,
                 precondition: Callable[[Array], Array] | None = None
                 ) -> tuple[Array, float, int]:
        """Riemannian conjugate gradients (Polak-Ribiere+, the tangent projection as
        transport) on the blocks of Y, from ``y``; each step minimizes the quadratic model
        along the direction, then retracts (Armijo backtracking).  Stops when the Riemannian
        gradient falls below ``gradient_tolerance`` of its first norm, or the cost fell by less
        than ``stall`` (relative) over 20 iterations.  ``precondition``: a positive definite
        map of (d n, p) arrays (:meth:`preconditioner`), applied to each gradient before its
        projection onto the tangent space.  Returns ``(Y, cost, its)``."""
        def pre(at: Array, grad: Array) -> Array:
            return grad if precondition is None else self.tangent(at, precondition(grad))

        qy = self.q(y)
        f = float(np.real(np.vdot(y, qy)))
        grad = self.tangent(y, 2.0 * qy)
        pgrad = pre(y, grad)
        g0 = float(np.linalg.norm(grad))
        direction = -pgrad
        past = [f]
        it = 0
        while it < max_iterations and g0 > 0.0:
            it += 1
            slope = float(np.real(np.vdot(grad, direction)))
            if slope >= 0.0:
                direction = -pgrad
                slope = -float(np.real(np.vdot(grad, pgrad)))
            curv = 2.0 * float(np.real(np.vdot(direction, self.q(direction))))
            step = -slope / curv if curv > 0.0 else 1.0
            while True:
                y_new = self.retract(y + step * direction)
                qy_new = self.q(y_new)
                f_new = float(np.real(np.vdot(y_new, qy_new)))
                if f_new <= f + 1e-4 * step * slope or step < 1e-14:
                    break
                step *= 0.5
            if not f_new <= f:
                break
            grad_new = self.tangent(y_new, 2.0 * qy_new)
            pgrad_new = pre(y_new, grad_new)
            moved = self.tangent(y_new, pgrad)
            beta = max(0.0, float(np.real(np.vdot(grad_new, pgrad_new - moved)))
                       / float(np.real(np.vdot(grad, pgrad))))
            direction = self.tangent(y_new, direction)
            direction = -pgrad_new + beta * direction
            y, grad, pgrad, f = y_new, grad_new, pgrad_new, f_new
            past.append(f)
            if float(np.linalg.norm(grad)) <= gradient_tolerance * g0:
                break
            if len(past) > 20 and past[-21] - f <= stall * abs(past[-21]):
                break
        return y, f, it

    def preconditioner(self, y: Array, sigma: float
                       ) -> tuple[Callable[[Array], Array] | None, float]:
        """``(apply, shift)``: ``apply(G) = (S(Y) + shift I)^-1 G`` for (d n, p) arrays G, with
        the certificate matrix at Y (any rank) factored once (its own copy of the
        certificate's sparse matrix, :meth:`_spectrum_setup`); ``shift`` is the first of
        ``sigma, 10 sigma, ...`` (from the ladder's floor at least; a ``sigma`` that is not a
        finite number above it starts at the floor) with ``S + shift I`` positive definite.
        Near a minimum of the relaxation S is F's Riemannian Hessian there (up to the
        projection), so the map is Newton's.  ``(None, inf)`` when no shift up
        to ``max lambda(Lambda_i)`` (where S + shift I is always definite) factors.  ``apply``
        solves with the factorization of the latest call: a new call replaces it."""
        from .linalg import NotPositiveDefinite, SparseSPD

        cs = self._spectrum_setup()
        if "pre" not in cs:
            n = self.n
            bsr = sp.bsr_matrix((cs["values"].reshape(-1, 4, 4).copy(), self._pose[2],
                                 self._pose[1]), shape=(4 * n, 4 * n))
            cs["pre"] = SparseSPD(bsr)
        spd, dim, rot, mask = cs["pre"], cs["dim"], cs["rot"], cs["mask"]
        lam = self.lambda_blocks(y)
        values = self._certificate_values(lam)
        top = float(np.max(np.linalg.eigvalsh(lam))) if self.n else 0.0
        shift = _SHIFT_FLOOR * cs["scale"]
        if np.isfinite(sigma) and sigma > shift:
            shift = float(sigma)
        while True:
            try:
                spd.factor(shift * mask, values=values)
                break
            except NotPositiveDefinite:
                if shift > max(top, 0.0) + cs["scale"] * 1e-6:
                    return None, float("inf")
                shift *= 10.0
        complex_ = self.complex

        def apply(g: Array) -> Array:
            k = g.shape[1]
            if complex_:  # the real form: (re, im) of each pose's entry, one after the other
                real = np.empty((rot.size, k))
                real[0::2], real[1::2] = g.real, g.imag
            else:
                real = np.asarray(g, np.float64)
            rhs = np.zeros((dim, real.shape[1]))
            rhs[rot] = real
            x: Array = np.asarray(spd.solve(rhs)[rot], np.float64)
            if complex_:
                out: Array = x[0::2] + 1j * x[1::2]
                return out
            return x

        return apply, shift

    def round(self, y: Array) -> Array:
        """The rank-d rotations nearest Y's leading d-dimensional part (SE-Sync's rounding):
        the d leading left singular vectors scaled by their singular values, reflected if most
        blocks have a negative determinant (3D), then each block projected onto the rotations.
        The global rotation is arbitrary."""
        u, s, _ = np.linalg.svd(y, full_matrices=False)
        yd = u[:, :self.d] * s[None, :self.d]
        if self.d == 1:
            mag = np.abs(yd)
            out: Array = np.where(mag > 0, yd / np.where(mag > 0, mag, 1.0), 1.0 + 0j)
            return out
        blocks = yd.reshape(self.n, 3, 3)
        if np.count_nonzero(np.linalg.det(blocks) > 0.0) < 0.5 * self.n:
            blocks = blocks * np.array([1.0, 1.0, -1.0])[None, None, :]
        uu, _, vh = np.linalg.svd(blocks)
        det = np.linalg.det(uu @ vh)
        uu[:, :, 2] *= det[:, None]
        return np.ascontiguousarray((uu @ vh).reshape(3 * self.n, 3))

    # ------------------------------------------------------------------ Newton on F
    def _block_map(self, free: Array) -> dict[str, Any]:
        """The block pattern over the poses with ``free[i] >= 0`` (their new numbers) of F's
        Hessian and of M, pose by pose: ``where`` (4, M) gives each constraint's (a, a),
        (a, b), (b, a), (b, b) block (-1: a held pose), ``indices``/``indptr`` the BSR
        structure, ``diag`` every pose's diagonal block (a pose without constraints has one
        too)."""
        a, b = self._edges
        fa, fb = free[a], free[b]
        nf = int(np.count_nonzero(free >= 0))
        pairs = np.stack([fa * nf + fa, fa * nf + fb, fb * nf + fa, fb * nf + fb])  # (4, m)
        ok = np.stack([fa >= 0, (fa >= 0) & (fb >= 0), (fa >= 0) & (fb >= 0), fb >= 0])
        keys = np.unique(np.concatenate([pairs[ok], np.arange(nf) * (nf + 1)]))
        where = np.full(pairs.shape, -1, np.int64)
        where[ok] = np.searchsorted(keys, pairs[ok])
        indptr = np.zeros(nf + 1, np.int64)
        np.cumsum(np.bincount(keys // max(nf, 1), minlength=nf), out=indptr[1:])
        return {"where": where, "nblocks": keys.size, "indices": keys % max(nf, 1),
                "indptr": indptr, "nf": nf,
                "diag": np.searchsorted(keys, np.arange(nf) * (nf + 1))}

    def _newton_setup(self) -> dict[str, Any]:
        """The Newton system's block pattern (the pose graph without the gauge pose, BSR with
        (P, P) blocks) and its factorization's analysis, computed once."""
        if self._newton is not None:
            return self._newton
        from .linalg import SparseSPD

        n, g = self.n, self.gauge
        pp = 3 if self.complex else 6
        free = np.arange(n) - (np.arange(n) > g)
        free[g] = -1
        bm = self._block_map(free)
        nf = bm["nf"]
        dim = pp * nf
        pattern = sp.bsr_matrix((np.zeros((bm["nblocks"], pp, pp)), bm["indices"],
                                 bm["indptr"]), shape=(dim, dim))
        # LM's normal equations have this pattern (shared_patterns: one construction)
        self._newton = {**bm, "pp": pp, "spd": SparseSPD(pattern, share=True) if nf else None,
                        "keep": np.flatnonzero(np.repeat(free >= 0, pp))}
        return self._newton

    def _edge_terms(self, y: Array, hessian: bool = True,
                    blocks: dict[str, Any] | None = None) -> dict[str, Any]:
        """F at rotations Y (rank d) and their optimal positions, with its gradient over the
        parameters ``[position shift (world frame), rotation]`` of every pose (``z exp(i
        theta)``; ``R Exp(omega)``) and, with ``hessian``, its Newton Hessian (the Gauss-Newton
        part plus the residuals' curvature along the rotation parameters) on the block pattern
        ``blocks`` (:meth:`_block_map`; default: the Newton system's, without the gauge pose).

        Returns ``f`` (F), ``grad`` (n, P), ``blocks`` (nb, P, P) with ``hessian``, and
        ``noise``: a bound of F's rounding error (:mod:`hybridpgo._sync_kernels`)."""
        from ._sync_kernels import sync_terms_2d, sync_terms_3d

        a, b = self._edges
        t = self.positions(y)
        w_r, w_t = self._weights
        rm, tm = self._measured
        pp = 3 if self.complex else 6
        bm = blocks if blocks is not None else self._newton_setup()
        grad = np.zeros((self.n, pp))
        out = np.zeros((bm["nblocks"] if hessian else 0, pp, pp))
        if self.complex:
            f, rounding = sync_terms_2d(np.ascontiguousarray(y[:, 0]),
                                        np.ascontiguousarray(t[:, 0]), a, b, w_r, w_t, rm, tm,
                                        bm["where"], hessian, grad, out)
        else:
            rot = np.ascontiguousarray(np.swapaxes(y.reshape(self.n, 3, 3), 1, 2))
            f, rounding = sync_terms_3d(rot, np.ascontiguousarray(t), a, b, w_r, w_t, rm, tm,
                                        bm["where"], hessian, grad, out)
        terms: dict[str, Any] = {
            "f": f, "grad": grad,
            # rounding: each residual is computed to ~eps of the numbers it subtracts
            "noise": 1e3 * float(np.finfo(np.float64).eps) * (f + rounding)}
        if hessian:
            terms["blocks"] = out
        return terms

    def newton_system(self, y: Array) -> tuple[sp.csr_matrix, FloatArray, float]:
        """``(H, g, F)``: F's Newton system at rotations Y (rank d) and their optimal
        positions over every pose's parameters (:meth:`_edge_terms`; the gauge pose's too):
        ``F(p) ~ F + g.p + p.H.p / 2``, H (P n, P n) sparse, g (P n,)."""
        bm = self._block_map(np.arange(self.n))
        terms = self._edge_terms(y, blocks=bm)
        pp = terms["grad"].shape[1]
        h = sp.bsr_matrix((terms["blocks"], bm["indices"], bm["indptr"]),
                          shape=(pp * self.n, pp * self.n))
        return sp.csr_matrix(h), terms["grad"].ravel(), terms["f"]

    def _step(self, y: Array, delta: FloatArray) -> Array:
        """Rotations moved by the rotation parameters of ``delta`` (n, P)."""
        if self.complex:
            out: Array = y * np.exp(1j * delta[:, 2])[:, None]
            return out
        from .geometry.so3 import exp

        rot = np.swapaxes(y.reshape(self.n, 3, 3), 1, 2) @ exp(delta[:, 3:])
        return np.ascontiguousarray(np.swapaxes(rot, 1, 2).reshape(3 * self.n, 3))

    def refine(self, y: Array, max_iterations: int = NEWTON_FACTORIZATIONS
               ) -> tuple[Array, float, int]:
        """Newton's method on F over the rotations (rank d) and positions, from ``y``, the
        gauge pose held; the positions are re-optimized after each step.

        A factorization of the Hessian is reused while the steps it gives lower F and their
        predicted decrease falls at least ``_CHORD_RATE`` times per step (a chord method:
        each such step costs a gradient and a solve); else it is refactored at the current
        point (after the step when it lowered F), and damped (``H + mu diag(H)``) while it is
        not positive definite (``mu`` from ``_DAMPING_FLOOR``, ``_DAMPING_INDEFINITE`` times
        more per failed factorization) or its step raises F by more than F's rounding error
        (10 times more); a damped step that lowers F divides ``mu`` by
        ``_DAMPING_INDEFINITE``, down to 0, except that after an undamped factorization
        failed, a step damped at most 10 times the floor returns to 0 only when F fell by the
        model's decrease within ``_NEWTON_LIKE`` (else that factorization serves chord steps).
        Stops
        after a step whose predicted decrease is below ``_NEWTON_TOLERANCE`` of F, or below
        F's rounding error when a fresh factorization no longer shrinks it ``_CHORD_RATE``
        times (:attr:`refine_converged` then True), or at ``max_iterations`` factorizations,
        a damping of 1e12, or ``4 max_iterations`` steps (False).  Returns
        ``(Y, F, factorizations)``.
        """
        from .linalg import NotPositiveDefinite

        self.refine_converged = True
        if self.n < 2:
            return y, self.cost(y), 0
        self.refine_converged = False
        nw = self._newton_setup()
        pp, keep, spd = nw["pp"], nw["keep"], nw["spd"]
        mu = 0.0
        factorizations = 0
        terms = self._edge_terms(y)
        g, f = terms["grad"], terms["f"]
        fresh = False
        stale = True
        indefinite = False  # the last undamped factorization failed
        previous = np.inf
        for _ in range(4 * max_iterations):
            if stale:
                if factorizations >= max_iterations or mu >= 1e12:
                    break
                if "blocks" not in terms:
                    terms = self._edge_terms(y)
                values = terms["blocks"]
                diag = np.diagonal(values[nw["diag"]], axis1=1, axis2=2).ravel()
                diag = np.maximum(diag, 1e-12 * max(float(np.max(np.abs(diag))), 1.0))
                factorizations += 1
                try:
                    spd.factor(mu * diag, values=values.ravel())
                except NotPositiveDefinite:
                    indefinite = indefinite or mu == 0.0
                    mu = max(_DAMPING_FLOOR, _DAMPING_INDEFINITE * mu)
                    continue
                indefinite = indefinite and mu > 0.0
                fresh, stale = True, False
            gk = g.ravel()[keep]
            step = spd.solve(-gk)
            predicted = -0.5 * float(gk @ step)
            if not (predicted >= 0.0 and np.all(np.isfinite(step))):
                mu = max(_DAMPING_FLOOR, 10.0 * mu) if fresh else mu
                stale = True
                continue
            full = np.zeros(pp * self.n)
            full[keep] = step
            y_new = self._step(y, full.reshape(self.n, pp))
            noise = terms["noise"]
            # converged: a tiny predicted decrease, or a fresh Newton step that no longer
            # shrinks it below F's rounding error (rounding floor)
            small = predicted <= _NEWTON_TOLERANCE * abs(f) or (
                fresh and predicted <= noise and predicted > previous / _CHORD_RATE)
            new_terms = self._edge_terms(y_new, hessian=False)
            f_new = new_terms["f"]
            if small or (f_new <= f + noise and (fresh or predicted <= previous / _CHORD_RATE)):
                # the model's decrease met within _NEWTON_LIKE: the undamped Hessian may be
                # positive definite by now
                newton_like = abs((f - f_new) - predicted) <= _NEWTON_LIKE * predicted
                y, terms = y_new, new_terms
                g, f = terms["grad"], f_new
                if small:
                    self.refine_converged = True
                    break
                previous = predicted
                if fresh and mu > 10.0 * _DAMPING_FLOOR:
                    mu = mu / _DAMPING_INDEFINITE
                    stale = True  # less damping: refactor
                elif fresh and mu > 0.0 and (newton_like or not indefinite):
                    mu = 0.0
                    stale = True
                # else: H was indefinite at the last undamped try and the model is still off;
                # the floor's factorization serves chord steps until it is refactored
                fresh = False
            elif not fresh and f_new < f:  # a chord step that lowers F, slowly: keep it and
                y, terms = y_new, new_terms  # refactor there
                g, f = terms["grad"], f_new
                previous = predicted
                stale = True
            else:
                if fresh:
                    mu = max(_DAMPING_FLOOR, 10.0 * mu)
                stale = True
        return y, f, factorizations

    # ------------------------------------------------------------------ certificate
    def _spectrum_setup(self) -> dict[str, Any]:
        """The certificate's matrix ``K = M + c e e^T - blockdiag(0, Lambda)`` in real form,
        pose by pose (BSR, (4, 4) blocks on the pose graph: a pose's position then rotation
        entries), where Lambda's entries go, and the factorization's analysis, computed once.

        ``c e e^T`` anchors the gauge pose's position (``c``: the mean diagonal of M's
        position block): the positions' Schur complement is still Q, since ``B 1 = 0`` (F does
        not change when every position moves together), so K is positive definite iff
        ``S = Q - Lambda`` is."""
        if self._cert is not None:
            return self._cert
        from .linalg import SparseSPD

        n = self.n
        i = np.arange(n)
        pose, block_ptr, block_col, diag_block = self._pose
        if self.complex:  # an entry p + i q of M becomes [[p, -q], [q, p]]
            blocks = np.empty((pose.shape[0], 4, 4))
            blocks[:, 0::2, 0::2] = blocks[:, 1::2, 1::2] = pose.real
            blocks[:, 1::2, 0::2] = pose.imag
            blocks[:, 0::2, 1::2] = -pose.imag
        else:
            blocks = np.array(pose, np.float64)
        anchor, rot_slots = ([0, 1], [2, 3]) if self.complex else ([0], [1, 2, 3])
        diag_t = pose[diag_block, 0, 0].real
        c_anchor = float(np.mean(diag_t)) if n else 1.0
        for q in anchor:
            blocks[diag_block[self.gauge], q, q] += c_anchor
        dim = 4 * n
        bsr = sp.bsr_matrix((blocks, block_col, block_ptr), shape=(dim, dim))
        rs = np.asarray(rot_slots)
        mask = np.zeros((n, 4))
        mask[:, rs] = 1.0
        rot = (4 * i[:, None] + rs[None, :]).ravel()
        self._cert = {"values": np.asarray(bsr.data, np.float64).ravel().copy(),
                      "diag": diag_block, "slots": rs, "spd": SparseSPD(bsr),
                      "mask": mask.ravel(), "dim": dim, "rot": rot,
                      "scale": float(np.max(np.abs(np.diagonal(pose[diag_block], axis1=1,
                                                                axis2=2))))}
        if self.earth >= 0:  # the earth-fixed form (:meth:`spectrum`)
            e = self.earth
            fixed = mask.copy()
            fixed[e] = 0.0
            diag_e = np.diagonal(pose[diag_block], axis1=1, axis2=2).real.copy()
            diag_e[e, 1:] = 0.0  # the earth's rotation entries: an identity when it is held
            self._cert.update(
                scale_fixed=float(np.max(np.abs(diag_e))),
                earth_rows=np.arange(block_ptr[e], block_ptr[e + 1]),
                earth_cols=np.flatnonzero(block_col == e), mask_fixed=fixed.ravel(),
                rot_fixed=rot[(rot // 4) != e],
                y_fixed=np.flatnonzero(np.repeat(np.arange(n) != e, self.d)))
        return self._cert

    def _certificate_values(self, lam: Array, fixed_earth: bool = False) -> FloatArray:
        """The values of the certificate's matrix K (:meth:`_spectrum_setup`) with the blocks
        ``lam`` of Lambda subtracted from each pose's rotation entries (a copy).  With
        ``fixed_earth`` the earth frame's rotation rows and columns are those of the identity
        (its rotation is no unknown: K's Schur complement onto the rotations is then S with
        the earth's rows and columns deleted, beside an identity block)."""
        cs = self._spectrum_setup()
        values: FloatArray = cs["values"].copy()
        blocks = values.reshape(-1, 4, 4)
        rs = cs["slots"]
        if self.complex:
            lr = np.real(lam[:, 0, 0])
            blocks[cs["diag"], 2, 2] -= lr
            blocks[cs["diag"], 3, 3] -= lr
        else:
            blocks[cs["diag"][:, None, None], rs[None, :, None], rs[None, None, :]] -= lam
        if fixed_earth:
            blocks[cs["earth_rows"][:, None], rs[None, :], :] = 0.0
            blocks[cs["earth_cols"][:, None], :, rs[None, :]] = 0.0
            blocks[cs["diag"][self.earth], rs, rs] = 1.0
        return values

    def _earth_fixed_gap(self, y: Array, lam: Array, shift: float,
                         qy: Array | None = None) -> float:
        """How far F at the rank-d ``y`` lies above the earth-fixed lower bound of F's minimum
        (module docstring), from the factorization of the earth-fixed K shifted by ``shift``
        (:meth:`spectrum`; 3D): ``tr(G^T P^-1 G)`` with ``P = S_rr + shift I`` and
        ``G = P Y_r + Q_re = (Q Y)_r - Lambda_r Y_r + shift Y_r`` (Y turned so that the earth's
        block is the identity; Lambda and F do not change).  Nonnegative by construction, and
        free of the cancellation of the bound's large terms (``tr(Q_ee)``: the readings'
        positions squared; ``qy``: ``Q Y`` when computed already)."""
        cs = self._spectrum_setup()
        n, d, e = self.n, self.d, self.earth
        turn = y[d * e: d * e + d].T  # the earth's block becomes the identity
        y = y @ turn
        qy = self.q(y) if qy is None else qy @ turn
        yb = y.reshape(n, d, d)
        g = (qy.reshape(n, d, d) - lam @ yb + shift * yb).reshape(d * n, d)
        g[d * e: d * e + d] = 0.0  # the earth's rows: P's identity block
        rhs = np.zeros((cs["dim"], d))
        rhs[cs["rot"]] = g
        solved = np.asarray(cs["spd"].solve(rhs), np.float64)[cs["rot"]]
        return max(float(np.sum(g * solved)), 0.0)

    def spectrum(self, y: Array, gap_tolerance: float = GAP_TOLERANCE,
                 eigenvector: bool = False, eigenvalue: bool = True) -> Spectrum:
        """The certificate at Y (any rank): the smallest shift ``sigma`` of a ladder (from
        ``_SHIFT_FLOOR`` of M's largest diagonal entry, x100 per rung) with ``S + sigma I``
        positive definite, then ``lambda_min(S)`` from ``(S + sigma I)^-1`` (power iterations
        when sigma certifies, where that eigenvalue dominates by orders of magnitude; else
        Lanczos, ARPACK).

        The ladder stops at the first positive definite rung; rungs above ``gap_tolerance F /
        (d n)`` (which could not certify) only serve to find a shift for the eigenvalue, up to
        the bound ``max lambda(Lambda_i)`` above which S + sigma I is always definite.  The
        first rung certifies also when its gap bound is within ``FLOOR_GAP_TOLERANCE`` of F
        (a smaller shift is below what the factorization resolves).  With ``eigenvalue``
        False the ladder stops where no rung could certify: an uncertified Y then gets no
        eigenvalue (NaN) and costs no more factorizations nor Lanczos iterations (a
        certified one gets its eigenvalue as always).

        A 3D graph with GPS at rank d is certified with the earth frame's rotation held at
        the identity (the earth-fixed form, module docstring): S loses the earth's rows and
        columns (the ladder starts from the largest diagonal entry without the earth's
        rotation), the lower bound is F less :meth:`_earth_fixed_gap` at the first definite
        rung (whether or not it is below the gap tolerance's shift), and the point is certified
        when that excess is within the gap tolerance; the eigenvalue and its vector are those
        of that S (the vector's earth rows 0).
        """
        from scipy.sparse.linalg import ArpackNoConvergence, LinearOperator, eigsh

        from .linalg import NotPositiveDefinite

        n, d = self.n, self.d
        cs = self._spectrum_setup()
        qy = self.q(y)
        lam = self.lambda_blocks(y, qy)
        objective = float(np.sum(np.real(np.trace(lam, axis1=1, axis2=2))))
        fixed = self.holds_earth and y.shape[1] == d
        values = self._certificate_values(lam, fixed)
        spd, dim = cs["spd"], cs["dim"]
        scale = cs["scale_fixed"] if fixed else cs["scale"]
        mask, rot = (cs["mask_fixed"], cs["rot_fixed"]) if fixed else (cs["mask"], cs["rot"])
        size = d * (n - 1) if fixed else d * n  # the rotation blocks' rows
        cap = gap_tolerance * abs(objective) / size
        if _SHIFT_FLOOR * scale <= FLOOR_GAP_TOLERANCE * abs(objective) / size:
            cap = max(cap, _SHIFT_FLOOR * scale)  # the smallest shift float64 resolves
        top = float(np.max(np.linalg.eigvalsh(lam))) if n else 0.0
        sigma = _SHIFT_FLOOR * scale
        shift = float("inf")
        tries = 0
        while True:
            tries += 1
            try:
                spd.factor(sigma * mask, values=values)
                shift = sigma
                break
            except NotPositiveDefinite:
                pass
            if sigma > max(top, 0.0) + scale * 1e-6:
                break
            sigma *= 100.0 if sigma < cap else 10.0
            if not eigenvalue and sigma > cap:  # no rung left that could certify
                break
        certified = shift <= cap
        lower = objective - shift * size if certified else -np.inf
        excess = float("nan")
        if fixed and np.isfinite(shift):  # the bound holds at any definite shift
            excess = self._earth_fixed_gap(y, lam, shift, qy)
            certified = excess <= cap * size
            lower = objective - excess if certified else -np.inf
        lam_min = float("nan")
        vec: Array | None = None
        if np.isfinite(shift) and (certified or eigenvalue):
            def apply(v: FloatArray) -> FloatArray:
                rhs = np.zeros(dim)
                rhs[rot] = np.ravel(v)
                return np.asarray(spd.solve(rhs)[rot], np.float64)

            x = np.random.default_rng(0).standard_normal(rot.size)
            x /= np.linalg.norm(x)
            theta = float("nan")
            converged = False
            if certified:  # 1/sigma dominates: a few power iterations, until lambda_min
                last = np.inf  # moves by less than 1e-3 of the shift
                for _ in range(8):
                    z = apply(x)
                    theta = float(x @ z)
                    x = z / np.linalg.norm(z)
                    estimate = 1.0 / theta - shift if theta > 0 else np.inf
                    converged = bool(abs(estimate - last) <= 1e-3 * shift)
                    last = estimate
                    if converged:
                        break
            if not converged:
                op = LinearOperator((rot.size, rot.size), matvec=apply, dtype=np.float64)
                try:
                    vals, vecs = eigsh(op, k=1, which="LA", v0=x, tol=1e-10,
                                       ncv=min(rot.size, 12), maxiter=2000)
                    theta, x, converged = float(vals[0]), vecs[:, 0], True
                except ArpackNoConvergence:
                    pass
            if converged and theta > 0:
                lam_min = 1.0 / theta - shift
                if fixed:  # the earth's rotation rows: 0
                    full = np.zeros(d * n)
                    full[cs["y_fixed"]] = x
                    x = full
                vec = (x[0::2] + 1j * x[1::2])[:, None] if self.complex else x[:, None]
        return Spectrum(objective, shift if certified else float("inf"), lam_min,
                        vec if eigenvector else None, lower, tries, _SHIFT_FLOOR * scale,
                        fixed, shift, excess)


# ------------------------------------------------------------------ results
@dataclass(frozen=True)
class Certificate:
    """What :func:`sesync_certificate`, :func:`certify` or :func:`staircase_start` found at a
    solution."""

    certified: bool
    """True: the module docstring's "certified" (F's global minimum within ``gap`` at the
    refined start, and, for :func:`certify`, the polish from there reaches the solution)."""
    lambda_min: float
    """Smallest eigenvalue of the certificate matrix S at the F-refined rotations (3D with
    GPS: of S without the earth's rows and columns, the earth-fixed form; nan when it could
    not be computed)."""
    gap: float
    """Upper bound of F(refined) - min F, absolute (inf when not certified)."""
    relative_gap: float
    """``gap / F(refined)`` (inf when not certified)."""
    objective: float
    """F at the refined rotations (SE-Sync's objective; its published values are comparable)."""
    seconds: float
    """Wall time of the certificate: refinement, factorizations, eigenvalue (and polish)."""
    reason: str
    """One line: why it is or is not certified."""
    rotations: FloatArray = field(repr=False, default_factory=lambda: np.zeros((0, 3, 3)))
    """(N, 3, 3) the F-refined rotations (the certified start), in the solution's frame."""
    translations: FloatArray = field(repr=False, default_factory=lambda: np.zeros((0, 3)))
    """(N, 3) their F-optimal positions."""
    stats: dict[str, Any] = field(default_factory=dict)
    """Newton iterations, factorizations, seconds per part, polish energies."""
    point: tuple[Array, Spectrum] | None = field(repr=False, compare=False, default=None)
    """The refined rotations in the relaxation's layout (rank d) and the certificate
    matrix's :class:`Spectrum` there (with its eigenvector from :func:`sesync_certificate`;
    None when not computed)."""

    def summary(self) -> str:
        """``"certified global optimum (gap <= ...)"`` or ``"not certified (...)"``."""
        if self.certified:
            return f"certified global optimum (gap ≤ {self.relative_gap:.1e} relative)"
        if np.isfinite(self.lambda_min):
            return f"not certified (λ_min = {self.lambda_min:.3g}): {self.reason}"
        return f"not certified: {self.reason}"


_COMPILED: set[bool] = set()


def ensure_compiled(planar: bool) -> float:
    """Compile (or load from Numba's cache) the kernels of F for planar graphs (the complex
    form) or 3D ones, once per process: a certificate of a three-pose loop, and in 3D the
    staircase's retraction.  Returns the seconds spent (0 when already done)."""
    if planar in _COMPILED:
        return 0.0
    from ._warmup import tiny_graph

    t0 = time.perf_counter()
    graph = tiny_graph(planar=planar)
    prob = SyncProblem(graph)
    sesync_certificate(graph, graph.rotations, graph.translations, problem=prob)
    if not planar:  # the staircase's retraction (its minimization's kernel)
        y = prob.to_y(graph.rotations)
        prob.retract(np.concatenate([y, np.zeros((y.shape[0], 1))], axis=1))
    _COMPILED.add(planar)
    return time.perf_counter() - t0


def not_applicable(graph: PoseGraph, robust: str = "none") -> str:
    """Why SE-Sync's model does not describe ``graph`` ("" when it does)."""
    if graph.num_gps and graph.fixed_nodes.size:
        return "GPS constraints and a fixed pose (not in SE-Sync's model)"
    if robust != "none":
        return "robust kernel (not in SE-Sync's model)"
    if graph.fixed_nodes.size > 1:
        return "several fixed poses (not in SE-Sync's model)"
    if graph.num_nodes < 2 or graph.num_edges == 0:
        return "fewer than 2 poses or no constraint"
    if np.unique(graph.connected_components()).size > 1:
        return "the graph is not connected"
    return ""


def sync_problem(graph: PoseGraph) -> tuple[SyncProblem | None, float]:
    """``(problem, seconds)``: the graph's :class:`SyncProblem` and the seconds its set-up
    took, to share between a certificate and the staircase; None where the certificate does
    not apply (:func:`not_applicable`) or F overflows (:func:`sesync_certificate` then says
    so)."""
    t0 = time.perf_counter()
    if not_applicable(graph):
        return None, 0.0
    try:
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            return SyncProblem(graph), time.perf_counter() - t0
    except FloatingPointError:
        return None, time.perf_counter() - t0


def sesync_certificate(graph: PoseGraph, rotations: FloatArray,
                       translations: FloatArray | None = None, *,
                       gap_tolerance: float = GAP_TOLERANCE,
                       problem: SyncProblem | None = None,
                       max_factorizations: int = NEWTON_FACTORIZATIONS) -> Certificate:
    """Certify F's global optimum near given poses (no claim about E).

    Newton's method refines the rotations to a stationary point of F (SE-Sync's objective),
    then the certificate (:meth:`SyncProblem.spectrum`) bounds its gap.  ``certified`` is True
    when ``gap / F <= gap_tolerance``.  The refined poses are returned in the frame of the given
    ones at the gauge pose (``translations`` default: the F-optimal positions as they come).
    The certificate keeps its refined point and spectrum (:attr:`Certificate.point`), with
    which :func:`staircase_start` starts at rank d.  ``max_factorizations``: Newton's cap
    (:meth:`SyncProblem.refine`; ``stats["refine_converged"]`` says whether it converged
    before it).  Where it did not and the point does not certify, ``lambda_min`` is NaN (the
    eigenvalue of a point short of a stationary point is not computed).
    """
    t0 = time.perf_counter()
    why = not_applicable(graph)
    if why:
        return Certificate(False, float("nan"), float("inf"), float("inf"), float("nan"),
                           time.perf_counter() - t0, why)
    try:
        with np.errstate(over="raise", invalid="raise", divide="raise"):
            prob = problem or SyncProblem(graph)
            t1 = time.perf_counter()
            y, f, its = prob.refine(prob.to_y(rotations), max_factorizations)
            t2 = time.perf_counter()
            # the eigenvalue of a point short of F's stationary points says nothing of F's
            # minima: computed only where Newton's method converged (or where it certifies)
            spec = prob.spectrum(y, gap_tolerance, eigenvector=True,
                                 eigenvalue=prob.refine_converged)
            t3 = time.perf_counter()
    except FloatingPointError as exc:  # measurements of ~1e154: F overflows
        return Certificate(False, float("nan"), float("inf"), float("inf"), float("nan"),
                           time.perf_counter() - t0, f"F overflows float64 ({exc})")
    ref = None if translations is None else (rotations, translations)
    return _certificate_at(prob, y, f, its, spec, ref, (t1 - t0, t2 - t1, t3 - t2),
                           prob.cost(prob.to_y(rotations)), time.perf_counter() - t0,
                           gap_tolerance, prob.refine_converged)


def _certificate_at(prob: SyncProblem, y: Array, f: float, its: int, spec: Spectrum,
                    ref: tuple[FloatArray, FloatArray] | None,
                    seconds: tuple[float, float, float], before: float, took: float,
                    gap_tolerance: float, converged: bool) -> Certificate:
    """The :class:`Certificate` of the Newton-refined point ``y`` (F = ``f``, ``its``
    factorizations, ``converged`` whether that refinement converged) from its spectrum
    (computed with ``gap_tolerance``): poses in the frame of ``ref`` at the gauge pose,
    ``seconds`` of set-up, refinement and spectrum, ``before`` F before the refinement,
    ``took`` the certificate's wall time."""
    rot, trans = prob.poses(y, ref)
    gap = spec.objective - spec.lower_bound
    ok = bool(np.isfinite(gap))  # within gap_tolerance, or at the smallest shift (spectrum)
    rel = gap / abs(spec.objective) if spec.objective else (0.0 if gap == 0.0 else np.inf)
    s_name = "S without the earth's rotation rows" if spec.earth_held else "S"
    m_name = ("the certificate matrix without the earth's rotation rows" if spec.earth_held
              else "the certificate matrix")
    if ok:
        reason = (f"{s_name} + {spec.shift:.2g} I is positive definite: F is within {gap:.3g} "
                  f"of its global minimum ({rel:.2g} relative)")
    elif spec.earth_held and np.isfinite(spec.excess) and not (
            np.isfinite(spec.lambda_min) and spec.lambda_min < -spec.floor):
        reason = (f"{s_name} + {spec.definite:.2g} I is positive definite, but F lies "
                  f"{spec.excess:.3g} above the dual bound there, more than the gap tolerance "
                  "(the refined rotations are not close enough to a stationary point of F"
                  + ("" if converged else f": Newton's method stopped after {its} "
                     "factorizations") + ")")
    elif np.isfinite(spec.lambda_min) and spec.lambda_min >= -spec.floor:
        reason = (f"{m_name} is positive semidefinite as far as float64 resolves "
                  f"(λ_min = {spec.lambda_min:.3g}), but F = {f:.3g} is too small next to the "
                  f"information for a gap bound within {FLOOR_GAP_TOLERANCE:g} of it (a graph "
                  "with few loops or little noise)")
    elif np.isfinite(spec.lambda_min):
        reason = (f"{m_name} has a negative eigenvalue {spec.lambda_min:.3g}: the refined "
                  "rotations are not certified as F's global minimum (a local minimum of F, "
                  "or a point where the relaxation is not tight)")
    elif not converged:
        reason = (f"Newton's method on F stopped after {its} factorizations short of a "
                  f"stationary point; {s_name} + σI is not positive definite for any shift of "
                  "the ladder up to the gap tolerance's there (its eigenvalue is not computed)")
    else:
        reason = "the certificate's eigenvalue could not be computed"
    return Certificate(
        ok, spec.lambda_min, gap if ok else float("inf"), rel if ok else float("inf"), f,
        took, reason, rot, trans,
        {"newton_iterations": its, "factorizations": spec.factorizations, "shift": spec.shift,
         "shift_floor": spec.floor, "seconds_setup": seconds[0], "seconds_refine": seconds[1],
         "seconds_spectrum": seconds[2], "objective_before_refine": before,
         "refine_converged": converged, "gap_tolerance": gap_tolerance},
        (y, spec))


#: ``polish(rotations, translations) -> (rotations, translations, energy)``.
PolishCallback = Callable[[FloatArray, FloatArray], tuple[FloatArray, FloatArray, float]]


def _default_polish(graph: PoseGraph) -> PolishCallback:
    def polish(rot: FloatArray, trans: FloatArray) -> tuple[FloatArray, FloatArray, float]:
        from .solvers.gauss_newton import solve_exact

        res = solve_exact(graph, rot, trans)
        return res.rotations, res.translations, res.final_energy
    return polish


def certify(graph: PoseGraph, rotations: FloatArray, translations: FloatArray, *,
            energy: float | None = None, polish: PolishCallback | None = None,
            gap_tolerance: float = GAP_TOLERANCE) -> Certificate:
    """Certify a solution (module docstring, "What certified means").

    Parameters
    ----------
    graph : PoseGraph
    rotations, translations : (N, 3, 3), (N, 3) float64
        The solution (a minimum of E).
    energy : float, optional
        Its energy E (default: computed).
    polish : callable, optional
        ``polish(R, t) -> (R, t, E)``: the exact solver from a start (default:
        :func:`hybridpgo.solvers.gauss_newton.solve_exact` with its defaults).
    gap_tolerance : float
        Largest relative gap bound of F that counts as certified.

    Returns
    -------
    Certificate
        ``certified`` only if F's refined minimum is certified *and* the polish from it ends
        at the solution's energy within :data:`SAME_OPTIMUM` (relative).
    """
    from .energy import energy as energy_of

    t0 = time.perf_counter()
    e_sol = energy_of(graph, rotations, translations) if energy is None else float(energy)
    try:
        cert = sesync_certificate(graph, rotations, translations, gap_tolerance=gap_tolerance)
    except (HybridPGOError, ValueError, np.linalg.LinAlgError, RuntimeError) as exc:
        return Certificate(False, float("nan"), float("inf"), float("inf"), float("nan"),
                           time.perf_counter() - t0, f"the certificate failed: {exc}")
    if not cert.certified:
        return cert
    t1 = time.perf_counter()
    try:
        _, _, e_pol = (polish or _default_polish(graph))(cert.rotations, cert.translations)
    except (HybridPGOError, ValueError, np.linalg.LinAlgError, RuntimeError) as exc:
        return _replace(cert, certified=False, seconds=time.perf_counter() - t0,
                        reason=f"the polish from the certified start failed: {exc}")
    stats = {**cert.stats, "polish_energy": e_pol, "solution_energy": e_sol,
             "seconds_polish": time.perf_counter() - t1}
    if abs(e_pol - e_sol) <= SAME_OPTIMUM * max(abs(e_sol), abs(e_pol)):
        return _replace(cert, seconds=time.perf_counter() - t0, stats=stats,
                        reason=cert.reason + f"; the polish from there reaches E = {e_pol:.10g}")
    lower = e_pol < e_sol
    return _replace(cert, certified=False, seconds=time.perf_counter() - t0, stats=stats,
                    reason=(f"F's minimum is certified, but the polish from it ends at "
                            f"E = {e_pol:.10g}, {'below' if lower else 'above'} the solution's "
                            f"{e_sol:.10g}"))


def _replace(cert: Certificate, **changes: Any) -> Certificate:
    import dataclasses

    return dataclasses.replace(cert, **changes)


# ------------------------------------------------------------------ the staircase
#: Iterations of the staircase's minimization before its first try of rounding and
#: certifying; the next tries come after twice as many in all each time.
STAIRCASE_CHUNK = 50


def staircase_start(graph: PoseGraph, rotations: FloatArray, translations: FloatArray, *,
                    max_rank: int | None = None, max_iterations: int = 500,
                    gap_tolerance: float = GAP_TOLERANCE, problem: SyncProblem | None = None,
                    start: Certificate | None = None
                    ) -> tuple[FloatArray, FloatArray, dict[str, Any]]:
    """Poses from SE-Sync's Riemannian staircase, started at given poses.

    Rank d (the problem itself): Newton's method on F from the given rotations, then the
    certificate (or those of ``start``).  While it fails and the rank is below ``max_rank``
    (default d + 3): escape along the eigenvector of the certificate's negative eigenvalue
    into one more rank (``[Y, alpha v]``, ``alpha`` halved until F falls), minimize there
    (:meth:`SyncProblem.minimize`, at most ``max_iterations``, preconditioned by
    :meth:`SyncProblem.preconditioner` at the start of each chunk), round to rotations, refine
    them with Newton and certify again; the minimization stops after
    :data:`STAIRCASE_CHUNK` iterations, then each time their number doubled, for a rounding,
    refinement and certificate, and the staircase ends at the first that certifies.
    Returns the lowest-F rotations found with their optimal positions, in the
    frame of the given poses at the gauge pose, and ``info``: ``certified``, ``objective`` (F),
    ``lambda_min``, ``rank`` (where it ended), ``ranks`` (per rank: F of the relaxation, F
    rounded and refined, lambda_min of the relaxation's certificate (NaN when its rounding
    certified first), the minimization's iterations), ``max_angle`` (largest rotation
    difference from the given poses, rad), ``seconds``, and ``certificate``: the
    :class:`Certificate` of the returned poses, computed where they certified (None when
    not ``certified``; its ``objective_before_refine`` is F at the rounding it refined).
    ``problem``: the graph's :class:`SyncProblem` when one was built already (its set-up
    and factorizations' analysis are reused).  ``start``: the certificate of the given poses
    (:func:`sesync_certificate`, its refined poses being ``rotations`` and ``translations``):
    when its Newton's method converged and its gap tolerance is ``gap_tolerance``, rank d's
    point and spectrum are its own; else Newton goes on from the given rotations (a
    refinement stopped at its cap, short of F's local minimum, often ends at the global
    one).  On a 3D graph with GPS the ranks above d lift the earth frame's rotation too: their
    certificates are those of the whole S, which is ill-conditioned there (module docstring),
    while the roundings at rank d are certified in the earth-fixed form.
    """
    t0 = time.perf_counter()
    why = not_applicable(graph)
    if why:
        raise ValueError(f"the staircase does not apply: {why}")
    prob = problem or SyncProblem(graph)
    d = prob.d
    top = max_rank if max_rank is not None else d + 3
    cert: Certificate | None = None
    y0 = prob.to_y(rotations)
    if (start is not None and start.point is not None and start.stats.get("refine_converged")
            and start.stats.get("gap_tolerance") == gap_tolerance
            and start.point[0].shape == y0.shape
            and np.array_equal(start.rotations, rotations)):
        y, spec = start.point
        f = start.objective
        certified = bool(np.isfinite(spec.lower_bound))
        if certified:  # its poses in the frame of the given ones, as the staircase returns
            rot0, trans0 = prob.poses(y, (rotations, translations))
            cert = _replace(start, rotations=rot0, translations=trans0)
    else:
        t1 = time.perf_counter()
        y, f, factorizations = prob.refine(y0)
        t2 = time.perf_counter()
        spec = prob.spectrum(y, gap_tolerance, eigenvector=True)
        t3 = time.perf_counter()
        certified = bool(np.isfinite(spec.lower_bound))
        if certified:
            cert = _certificate_at(prob, y, f, factorizations, spec, (rotations, translations),
                                   (t1 - t0, t2 - t1, t3 - t2), prob.cost(y0), t3 - t0,
                                   gap_tolerance, prob.refine_converged)
    best_y, best_f = y, f
    ranks: list[dict[str, float]] = [{"rank": float(d), "relaxation": f, "rounded": f,
                                      "lambda_min": spec.lambda_min}]
    yp = y
    p = d
    while not certified and p < top and spec.vector is not None and spec.lambda_min < 0:
        # escape: one more column along the eigenvector (real part of the direction for C)
        v = spec.vector / np.linalg.norm(spec.vector)
        fp = prob.cost(yp)
        alpha = float(np.sqrt(prob.n))
        for _ in range(60):
            trial = prob.retract(np.concatenate([yp, alpha * v], axis=1))
            if prob.cost(trial) < fp:
                break
            alpha *= 0.5
        else:
            break
        p += 1
        # minimize in chunks; after each, round, refine and certify: a relaxation not yet
        # minimized often rounds into the certified optimum already; the chunks double, so a
        # relaxation that never certifies (m3500c) pays few tries.  Each chunk is
        # preconditioned by the shifted certificate matrix at its start (Newton's map near a
        # minimum): m3500 with 20 degrees of yaw noise and m3500b seed 2 (3 500 poses) certify
        # after the first chunk of 50 iterations at rank 2
        # (``stats["certificate"]["staircase"]["ranks"]`` of their default solves)
        yp, done, chunk = trial, 0, STAIRCASE_CHUNK
        sigma = 2.0 * abs(spec.lambda_min)  # the ladder's first guess (raised until definite)
        while True:
            pre, sigma = prob.preconditioner(yp, sigma)
            yp, fp, its = prob.minimize(yp, min(chunk, max_iterations - done),
                                        precondition=pre)
            sigma = sigma / 100.0 if np.isfinite(sigma) else 2.0 * abs(spec.lambda_min)
            done += its
            t1 = time.perf_counter()
            rounded = prob.round(yp)
            yr, fr, factorizations = prob.refine(rounded)
            converged = prob.refine_converged
            t2 = time.perf_counter()
            if fr < best_f:
                best_y, best_f = yr, fr
            spec_r = prob.spectrum(yr, gap_tolerance, eigenvalue=False)  # only the verdict
            certified = bool(np.isfinite(spec_r.lower_bound) and fr <= best_f)
            if certified:
                best_y, best_f = yr, fr
                t3 = time.perf_counter()
                cert = _certificate_at(prob, yr, fr, factorizations, spec_r,
                                       (rotations, translations), (0.0, t2 - t1, t3 - t2),
                                       prob.cost(rounded), t3 - t1, gap_tolerance,
                                       converged)
            if certified or its < chunk or done >= max_iterations:
                break
            chunk = done  # the tries at 50, 100, 200, 400, ... iterations
        if certified:
            ranks.append({"rank": float(p), "relaxation": fp, "rounded": fr,
                          "lambda_min": float("nan"), "iterations": float(done)})
            break
        spec_p = prob.spectrum(yp, gap_tolerance, eigenvector=True)
        ranks.append({"rank": float(p), "relaxation": fp, "rounded": fr,
                      "lambda_min": spec_p.lambda_min, "iterations": float(done)})
        spec = spec_p
        if np.isfinite(spec_p.lower_bound):  # the relaxation is solved: no lower rank helps
            break
    from .geometry.so3 import angle as rot_angle

    rot, trans = prob.poses(best_y, (rotations, translations))
    angle = rot_angle(np.swapaxes(rotations, 1, 2) @ rot)
    info = {"certified": bool(certified), "objective": best_f,
            "lambda_min": ranks[-1]["lambda_min"], "rank": p, "ranks": ranks,
            "max_angle": float(np.max(angle)) if angle.size else 0.0,
            "seconds": time.perf_counter() - t0, "certificate": cert}
    return rot, trans, info
