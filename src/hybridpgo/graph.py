"""The pose graph: an immutable struct-of-arrays (docs/contributing.md#data, docs/conventions.md).

Frames and conventions
----------------------
* A pose ``X_i = (R_i, t_i)`` maps node-frame coordinates into the world frame (``T_world_node``).
* A relative constraint ``c`` between ``a = edge_nodes[c, 0]`` and ``b = edge_nodes[c, 1]``
  measures ``Z_c = X_a^-1 X_b`` (pose of b in a's frame).  Its error is
  ``e_c = Log(Z_c^-1 X_a^-1 X_b)`` in R^6 ordered (rho, phi) and its energy ``e_c^T Omega_c e_c``.
* A position-only ("GPS") constraint on node ``n`` measures ``g`` (earth frame) with error
  ``p_n - g`` and a 3x3 information.
* 2D graphs are lifted into SE(3) (docs/conventions.md): ``is_2d`` remembers to write them back as
SE(2).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from .errors import GraphError

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int32]

#: Symmetry tolerance of information matrices, relative to their largest entry.
SYMMETRY_RTOL = 1e-9

#: Largest magnitude of an information entry (over (rho, phi), or of a GPS information).  The
#: solvers square and whiten information (``Omega = L L^T``, energies ``e^T Omega e``, normal
#: equations ``J^T Omega J``); with entries up to 1e150 those stay finite (an entry of 1e308
#: overflowed the SPD check and made the chordal SVD fail), and every writer can represent the
#: graph (the iSAM square root is at most ~1e75, g2o's (t, q_vec) rotation block 4e150).
MAX_INFORMATION = 1e150


def _frozen(a: np.ndarray, dtype: type, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    arr: np.ndarray = np.array(a, dtype=dtype, order="C", copy=True)  # never freeze the caller's
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise GraphError(
            f"{name} must have shape (n, {', '.join(map(str, shape_tail))})"
            if shape_tail
            else f"{name} must have shape (n,)"
        )
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        bad = int(np.argwhere(~np.isfinite(arr.reshape(arr.shape[0], -1)).any(axis=1))[0, 0])
        raise GraphError(f"{name}[{bad}] is not finite")
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, slots=True)
class PoseGraph:
    """A pose graph in struct-of-arrays form.  All arrays are read-only after construction."""

    node_ids: npt.NDArray[np.int64]
    """(N,) int64: the file's vertex ids; dense index i <-> ``node_ids[i]``."""
    rotations: FloatArray
    """(N, 3, 3) float64: R_world_node of the initial estimate (identity if the file has none)."""
    translations: FloatArray
    """(N, 3) float64: t_world_node of the initial estimate, metres."""
    edge_nodes: IntArray
    """(M, 2) int32: dense indices (a, b) of each relative constraint."""
    edge_rotations: FloatArray
    """(M, 3, 3) float64: measured R_a_b."""
    edge_translations: FloatArray
    """(M, 3) float64: measured t_a_b (position of b in a's frame)."""
    edge_information: FloatArray
    """(M, 6, 6) float64: SPD information over (rho, phi).  A 2D graph (``is_2d``) may be given
    (M, 3, 3) information over (x, y, theta): it is lifted by :func:`lift_information_2d`."""
    gps_nodes: IntArray = field(default_factory=lambda: np.zeros(0, np.int32))
    """(G,) int32: dense index of the node each position-only constraint acts on."""
    gps_positions: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    """(G, 3) float64: measured position in the earth frame."""
    gps_information: FloatArray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    """(G, 3, 3) float64: SPD information of each position measurement."""
    fixed_nodes: IntArray = field(default_factory=lambda: np.zeros(0, np.int32))
    """(F,) int32: dense indices named by ``FIX`` lines (held constant)."""
    is_2d: bool = False
    """True when the graph was read from SE(2) data (written back as SE(2))."""
    has_estimates: bool = True
    """False when the file had no vertex lines (iSAM): rotations/translations are then identity."""
    source_format: str = ""
    """Format the graph was read from ('g2o', 'toro', 'isam'), or '' when built in code."""
    edge_lines: npt.NDArray[np.int64] | None = field(default=None, compare=False, repr=False)
    """(M,) int64: the file line of each relative constraint, when read from a file (None
    otherwise, or when it does not have one entry per edge).  Informative only: for messages."""
    gps_lines: npt.NDArray[np.int64] | None = field(default=None, compare=False, repr=False)
    """(G,) int64: the file line of each GPS constraint, as :attr:`edge_lines`."""

    def __post_init__(self) -> None:
        ids = np.ascontiguousarray(self.node_ids, dtype=np.int64)
        n = ids.shape[0]
        if ids.ndim != 1:
            raise GraphError("node_ids must be one-dimensional")
        if n == 0:
            raise GraphError("the graph has no poses")
        if np.unique(ids).shape[0] != n:
            raise GraphError("node_ids contains duplicates")
        object.__setattr__(self, "node_ids", _frozen(ids, np.int64, (), "node_ids"))
        object.__setattr__(
            self, "rotations", _frozen(self.rotations, np.float64, (3, 3), "rotations")
        )
        object.__setattr__(
            self, "translations", _frozen(self.translations, np.float64, (3,), "translations")
        )
        if self.rotations.shape[0] != n or self.translations.shape[0] != n:
            raise GraphError("rotations/translations must have one entry per node")
        en = np.ascontiguousarray(self.edge_nodes, dtype=np.int32).reshape(-1, 2)
        object.__setattr__(self, "edge_nodes", _frozen(en, np.int32, (2,), "edge_nodes"))
        m = en.shape[0]
        object.__setattr__(
            self,
            "edge_rotations",
            _frozen(self.edge_rotations, np.float64, (3, 3), "edge_rotations"),
        )
        object.__setattr__(
            self,
            "edge_translations",
            _frozen(self.edge_translations, np.float64, (3,), "edge_translations"),
        )
        info = np.asarray(self.edge_information, dtype=np.float64)
        if info.ndim == 3 and info.shape[1:] == (3, 3):
            if not self.is_2d:
                raise GraphError("edge_information: 3x3 information (over x, y, theta) is "
                                 "only for 2D graphs (is_2d=True); a 3D graph needs 6x6 over "
                                 "(rho, phi)")
            _check_entries(info, "edge")
            info = lift_information_2d(info)  # docs/conventions.md
        object.__setattr__(
            self, "edge_information", _frozen(info, np.float64, (6, 6), "edge_information"),
        )
        for name in ("edge_rotations", "edge_translations", "edge_information"):
            if getattr(self, name).shape[0] != m:
                raise GraphError(f"{name} must have one entry per edge ({m})")
        gn = np.ascontiguousarray(self.gps_nodes, dtype=np.int32).reshape(-1)
        object.__setattr__(self, "gps_nodes", _frozen(gn, np.int32, (), "gps_nodes"))
        g = gn.shape[0]
        object.__setattr__(
            self, "gps_positions", _frozen(self.gps_positions, np.float64, (3,), "gps_positions")
        )
        object.__setattr__(
            self,
            "gps_information",
            _frozen(self.gps_information, np.float64, (3, 3), "gps_information"),
        )
        if self.gps_positions.shape[0] != g or self.gps_information.shape[0] != g:
            raise GraphError("gps_positions/gps_information must have one entry per GPS constraint")
        fx = np.ascontiguousarray(self.fixed_nodes, dtype=np.int32).reshape(-1)
        object.__setattr__(self, "fixed_nodes", _frozen(fx, np.int32, (), "fixed_nodes"))
        for name, arr in (("edge_nodes", en), ("gps_nodes", gn), ("fixed_nodes", fx)):
            if arr.size and (arr.min() < 0 or arr.max() >= n):
                raise GraphError(f"{name} refers to a node index outside 0..{n - 1}")
        if m and np.any(en[:, 0] == en[:, 1]):
            c = int(np.argmax(en[:, 0] == en[:, 1]))
            raise GraphError(f"edge {c} is a self-loop on node {int(ids[en[c, 0]])}")
        check_information(self.edge_information, "edge")
        check_information(self.gps_information, "GPS constraint")
        for name, count in (("edge_lines", m), ("gps_lines", g)):
            lines = getattr(self, name)
            if lines is not None:
                line_nos = np.array(lines, dtype=np.int64).reshape(-1)
                line_nos.flags.writeable = False
                object.__setattr__(self, name, line_nos if line_nos.shape[0] == count else None)

    # ------------------------------------------------------------------ sizes
    @property
    def num_nodes(self) -> int:
        return int(self.node_ids.shape[0])

    @property
    def num_edges(self) -> int:
        return int(self.edge_nodes.shape[0])

    @property
    def num_gps(self) -> int:
        return int(self.gps_nodes.shape[0])

    @property
    def num_constraints(self) -> int:
        return self.num_edges + self.num_gps

    def index_from_id(self) -> dict[int, int]:
        """Map file id -> dense index."""
        return {int(v): i for i, v in enumerate(self.node_ids)}

    def with_poses(self, rotations: FloatArray, translations: FloatArray) -> PoseGraph:
        """Return a copy of this graph whose vertex estimates are the given poses."""
        return PoseGraph(
            node_ids=self.node_ids,
            rotations=rotations,
            translations=translations,
            edge_nodes=self.edge_nodes,
            edge_rotations=self.edge_rotations,
            edge_translations=self.edge_translations,
            edge_information=self.edge_information,
            gps_nodes=self.gps_nodes,
            gps_positions=self.gps_positions,
            gps_information=self.gps_information,
            fixed_nodes=self.fixed_nodes,
            is_2d=self.is_2d,
            has_estimates=True,
            source_format=self.source_format,
            edge_lines=self.edge_lines,
            gps_lines=self.gps_lines,
        )

    def add_gps(
        self, node_id: int | npt.ArrayLike, xyz: npt.ArrayLike, information: npt.ArrayLike
    ) -> PoseGraph:
        """Return a copy with position-only (GPS) constraints added (the graph is immutable).

        Parameters
        ----------
        node_id : int or (k,) ints
            File ids of the poses the readings are of.
        xyz : (3,) or (k, 3) float
            Measured positions in the earth frame (metres).
        information : (3, 3) or (k, 3, 3) float
            SPD information of each reading (inverse covariance, 1/m^2); one matrix is shared.
        """
        ids = np.atleast_1d(np.asarray(node_id, dtype=np.int64))
        pos = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        info = np.asarray(information, dtype=np.float64)
        if info.shape == (3, 3):
            info = np.broadcast_to(info, (ids.shape[0], 3, 3))
        if pos.shape[0] != ids.shape[0] or info.shape != (ids.shape[0], 3, 3):
            raise GraphError(
                f"add_gps: {ids.shape[0]} node id(s) need as many positions (k, 3) "
                f"and informations (k, 3, 3); got {pos.shape} and {info.shape}"
            )
        index = np.searchsorted(self.node_ids, ids)
        index = np.minimum(index, self.num_nodes - 1)
        unknown = self.node_ids[index] != ids
        if np.any(unknown):
            raise GraphError(f"add_gps: unknown pose id(s) {ids[unknown][:5].tolist()}")
        check_information(np.ascontiguousarray(info), "GPS reading")
        return dataclasses.replace(
            self,
            gps_nodes=np.concatenate([self.gps_nodes, index.astype(np.int32)]),
            gps_positions=np.concatenate([self.gps_positions, pos]),
            gps_information=np.concatenate([self.gps_information, info]),
        )

    def connected_components(self) -> npt.NDArray[np.int32]:
        """Label of the connected component of every node (GPS links through the earth node)."""
        import scipy.sparse as sp
        from scipy.sparse.csgraph import connected_components

        n = self.num_nodes
        a = self.edge_nodes[:, 0].astype(np.int64)
        b = self.edge_nodes[:, 1].astype(np.int64)
        if self.num_gps:
            earth = np.full(self.num_gps, n, np.int64)
            a = np.concatenate([a, earth])
            b = np.concatenate([b, self.gps_nodes.astype(np.int64)])
        size = n + (1 if self.num_gps else 0)
        adj = sp.coo_matrix((np.ones(a.shape[0]), (a, b)), shape=(size, size))
        _, labels = connected_components(adj, directed=False)
        out: npt.NDArray[np.int32] = labels[:n].astype(np.int32)
        return out

    def check_connected(self, source: str = "the graph") -> None:
        """Raise :class:`GraphError` naming the parts when the graph is not connected."""
        labels = self.connected_components()
        parts = np.unique(labels)
        if parts.shape[0] <= 1:
            return
        desc = []
        for p in parts[:5]:
            members = self.node_ids[labels == p]
            span = f"{int(members.min())}..{int(members.max())}" if members.size > 1 else ""
            desc.append(f"{members.size} pose(s) {span}".rstrip() + f" (e.g. id {int(members[0])})")
        more = f" and {parts.shape[0] - 5} more" if parts.shape[0] > 5 else ""
        raise GraphError(
            f"{source} is not connected: {parts.shape[0]} separate parts: "
            + "; ".join(desc)
            + more
            + ". Every pose must be linked to the others by constraints"
            " (or by GPS constraints through the earth frame)."
        )


def _check_entries(info: FloatArray, what: str) -> None:
    """Raise unless every entry is finite and at most :data:`MAX_INFORMATION` in magnitude."""
    if info.shape[0] == 0:
        return
    big = np.abs(info).reshape(info.shape[0], -1).max(axis=1)
    bad = np.nonzero(~(big <= MAX_INFORMATION))[0]
    if bad.size:
        k = int(bad[0])
        if not np.isfinite(big[k]):
            raise GraphError(f"{what} {k}: information matrix is not finite")
        raise GraphError(f"{what} {k}: information entry {big[k]:.3g} is too large (at most "
                         f"{MAX_INFORMATION:.0e} in magnitude, so that it can be squared)")


def _cholesky_fails(mats: FloatArray) -> npt.NDArray[np.bool_]:
    """(k,) True where the Cholesky factorization of the matrix fails (halving the stack
    where one does: LAPACK reports one failure for the whole stack)."""
    out = np.zeros(mats.shape[0], bool)
    if mats.shape[0] == 0:
        return out
    try:
        np.linalg.cholesky(mats)
    except np.linalg.LinAlgError:
        if mats.shape[0] == 1:
            out[0] = True
        else:
            half = mats.shape[0] // 2
            out[:half] = _cholesky_fails(mats[:half])
            out[half:] = _cholesky_fails(mats[half:])
    return out


def positive_definite(info: FloatArray, eig_min: npt.ArrayLike | None = None,
                      ) -> npt.NDArray[np.bool_]:
    """(k,) True where the symmetric matrix in ``info`` (k, d, d) is positive definite to
    float64 rounding: its smallest eigenvalue (``eig_min``, computed when not given) is > 0
    *and* its Cholesky factorization succeeds.  (An eigenvalue at the rounding level of the
    largest, ~1e-16 of it, comes out with either sign: such a matrix may pass the first test
    and fail the second, which every whitening in the package uses.)"""
    lam = (np.asarray(eig_min, np.float64) if eig_min is not None
           else np.linalg.eigvalsh(info)[:, 0] if info.shape[0] else np.zeros(0))
    ok: npt.NDArray[np.bool_] = np.asarray(lam > 0.0)
    idx = np.nonzero(ok)[0]
    ok[idx[_cholesky_fails(info[idx])]] = False
    return ok


def pd_problem(eig_min: float) -> str:
    """Why a matrix :func:`positive_definite` refuses is not positive definite, for messages:
    its smallest eigenvalue, and whether only the Cholesky factorization failed."""
    if eig_min > 0.0:
        return (f"smallest eigenvalue {eig_min:.6g}, at the rounding level of the largest: "
                "its Cholesky factorization fails")
    return f"smallest eigenvalue {eig_min:.6g}"


def asymmetric(info: FloatArray) -> npt.NDArray[np.bool_]:
    """Which matrices of ``info`` (k, d, d) differ from their transpose by more than
    :data:`SYMMETRY_RTOL` times their largest entry's magnitude."""
    k = info.shape[0]
    if k == 0:
        return np.zeros(0, np.bool_)
    scale = np.abs(info).reshape(k, -1).max(axis=1)
    asym = np.abs(info - np.swapaxes(info, 1, 2)).reshape(k, -1).max(axis=1)
    return np.asarray(asym > SYMMETRY_RTOL * np.maximum(scale, 1e-300))


def check_information(info: FloatArray, what: str) -> None:
    """Raise :class:`GraphError` unless every matrix in ``info`` (k, d, d) is symmetric,
    positive definite to rounding (:func:`positive_definite`) and with entries at most
    :data:`MAX_INFORMATION` in magnitude."""
    if info.shape[0] == 0:
        return
    _check_entries(info, what)
    bad = np.nonzero(asymmetric(info))[0]
    if bad.size:
        raise GraphError(f"{what} {int(bad[0])}: information matrix is not symmetric")
    eig_min = np.linalg.eigvalsh(info)[:, 0]
    bad = np.nonzero(~positive_definite(info, eig_min))[0]
    if bad.size:
        raise GraphError(
            f"{what} {int(bad[0])}: information matrix is not positive definite "
            f"({pd_problem(float(eig_min[bad[0]]))})"
        )


#: In-plane (x, y, yaw) and out-of-plane (z, roll, pitch) coordinates of the tangent over
#: (rho, phi) (docs/conventions.md).
IN_PLANE = np.array([0, 1, 5])
OUT_OF_PLANE = np.array([2, 3, 4])


def lift_information_2d(info3: FloatArray) -> FloatArray:
    """Lift (k, 3, 3) SE(2) information over (x, y, theta) into (k, 6, 6) over (rho, phi).

    docs/conventions.md: x, y, yaw go to indices 0, 1, 5; z, roll, pitch get a stiffness equal to
    the
    largest in-plane diagonal entry.
    """
    info3 = np.asarray(info3, dtype=np.float64)
    k = info3.shape[0]
    out = np.zeros((k, 6, 6))
    out[:, IN_PLANE[:, None], IN_PLANE[None, :]] = info3
    stiff = np.max(np.diagonal(info3, axis1=1, axis2=2), axis=1)
    for j in (2, 3, 4):
        out[:, j, j] = stiff
    return out


def planar_information(info6: FloatArray) -> FloatArray:
    """Inverse of :func:`lift_information_2d`: the (x, y, yaw) block of (k, 6, 6) information."""
    return np.ascontiguousarray(np.asarray(info6)[:, IN_PLANE[:, None], IN_PLANE[None, :]])


def planar_motions(rotations: FloatArray, translations: FloatArray) -> bool:
    """True when every transform ``(R, t)`` keeps the xy-plane: ``R e3 = e3`` and ``t_z = 0``,
    compared exactly."""
    e3 = np.array([0.0, 0.0, 1.0])
    return bool(np.all(rotations[:, 2, :] == e3) and np.all(rotations[:, :, 2] == e3)
                and np.all(translations[:, 2] == 0.0))


def decoupled_information(info: FloatArray) -> bool:
    """True when no (6, 6) information over (rho, phi) couples an in-plane coordinate (x, y,
    yaw) with an out-of-plane one (z, roll, pitch); both blocks compared exactly (an input is
    symmetric only to a tolerance)."""
    return not (np.any(info[:, IN_PLANE[:, None], OUT_OF_PLANE[None, :]] != 0.0)
                or np.any(info[:, OUT_OF_PLANE[:, None], IN_PLANE[None, :]] != 0.0))


def planar_data(graph: PoseGraph) -> bool:
    """True when the graph's data are planar data lifted into 3D.

    Every relative measurement is a motion in the xy-plane (``R e3 = e3``, ``t_z = 0``), every
    GPS reading lies in it (``z = 0``), and no information couples an in-plane coordinate
    (x, y, yaw; a GPS reading's x, y) with an out-of-plane one (z, roll, pitch; its z).  Then
    a map whose poses share a plane has no out-of-plane error, nor a step out of its plane,
    and its least-squares optimum is planar: each relative constraint's χ² has 3 degrees of
    freedom, as in a 2D file (``PoseGraph.is_2d``).  The poses are not checked: the first
    pose may put the plane anywhere without GPS.  Exact comparisons, as the solver's check of
    its planar reduction.

    Parameters
    ----------
    graph : PoseGraph

    Returns
    -------
    bool
        False for a graph without relative constraints.
    """
    return planar_arrays(graph.edge_rotations, graph.edge_translations,
                         graph.edge_information, graph.gps_positions, graph.gps_information)


def planar_arrays(edge_rotations: FloatArray, edge_translations: FloatArray,
                  edge_information: FloatArray, gps_positions: FloatArray,
                  gps_information: FloatArray) -> bool:
    """:func:`planar_data` of the constraints given as arrays ((M, 3, 3), (M, 3), (M, 6, 6),
    (G, 3), (G, 3, 3))."""
    if edge_rotations.shape[0] == 0 or not planar_motions(edge_rotations, edge_translations):
        return False
    if not decoupled_information(edge_information):
        return False
    gps = gps_information
    return bool(np.all(gps_positions[:, 2] == 0.0) and np.all(gps[:, :2, 2] == 0.0)
                and np.all(gps[:, 2, :2] == 0.0))
