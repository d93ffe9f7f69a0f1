"""Exchange pose graphs with GTSAM (optional: ``pip install hybridpgo[gtsam]``).

>>> from hybridpgo import read_graph                                   # doctest: +SKIP
>>> from hybridpgo.gtsam_bridge import from_gtsam, to_gtsam            # doctest: +SKIP
>>> graph = read_graph("sphere2500.g2o")                               # doctest: +SKIP
>>> factors, values = to_gtsam(graph, anchor=True)                     # doctest: +SKIP
>>> result = gtsam.LevenbergMarquardtOptimizer(factors, values).optimize()  # doctest: +SKIP
>>> rotations, translations = from_gtsam(graph, result)                # doctest: +SKIP

Conventions (docs/conventions.md), chosen so that **our energy E equals 2 x GTSAM's error** at the
same poses (GTSAM's error carries a 1/2, ours does not):

* **Keys** are the file's node ids (``graph.node_ids``), so ``values.atPose3(7)`` is the pose the
  file calls 7.  GTSAM keys are unsigned: a negative id is an error.
* **Relative constraints** become ``BetweenFactorPose3(a, b, Z_c, noiseModel.Gaussian.Information(P
  Omega_c P))``.  Our tangent order is (translation rho, rotation phi); GTSAM's Pose3 tangent is
  (rotation, translation), so ``P`` swaps the two 3x3 halves.  ``BetweenFactor``'s error is
  ``Logmap(Z_c^-1 X_a^-1 X_b)`` (GTSAM's default full SE(3) chart), i.e. our ``e_c`` reordered.
  The information is *ours*, already converted from g2o's quaternion convention (``gtsam.readG2o``
  keeps the g2o rotation block unscaled, so its optimum differs from ours in 3D).
* **GPS (position-only) constraints** become ``GPSFactor(n, g_c, Gaussian.Information(Omega_c))``:
  its error ``p_n - g_c`` in the earth frame is ours exactly.
* **2D graphs** (read from SE(2) files) become ``Pose2`` / ``BetweenFactorPose2`` with the
  (x, y, yaw) block of the information, the natural GTSAM model, and 2D energy equals the lifted
  3D one exactly (docs/conventions.md).  A 2D graph with GPS uses Pose3, since a GPS reading is 3D
  (``planar=False`` forces Pose3 for any graph; ``planar=True`` on a graph with GPS is an error).
* **Gauge**: our solvers hold the root fixed (the ``FIX`` nodes, else the first pose; with GPS
  the earth frame).  GTSAM needs that said with a prior: ``anchor=True`` appends
  :func:`gauge_prior`'s factors.  They are zero at the given poses but not elsewhere, so compute
  energies on a graph built with ``anchor=False``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ._poses import given_or_start
from .errors import GraphError, HybridPGOError
from .graph import FloatArray, PoseGraph, planar_information

__all__ = ["from_gtsam", "gauge_prior", "require_gtsam", "to_gtsam"]

#: Our tangent (rho, phi) -> GTSAM Pose3's (rotation, translation): indices into ours.
TO_GTSAM_TANGENT = np.r_[3:6, 0:3]
#: Standard deviation (metres and radians) of the gauge prior of :func:`gauge_prior`.
GAUGE_SIGMA = 1e-6


def require_gtsam() -> Any:
    """Import and return the ``gtsam`` module, or raise an error naming the extra to install."""
    try:
        import gtsam
    except ImportError as exc:
        raise HybridPGOError("the GTSAM bridge needs gtsam, which is not installed: "
                             "pip install hybridpgo[gtsam]") from exc
    return gtsam


def _uses_pose2(graph: PoseGraph, planar: bool | None) -> bool:
    if planar is None:
        return graph.is_2d and graph.num_gps == 0
    if planar and graph.num_gps:
        raise ValueError("planar=True: GTSAM's Pose2 cannot carry the graph's "
                         f"{graph.num_gps} GPS (3D position) constraints; use planar=False")
    return bool(planar)


def _keys(graph: PoseGraph) -> list[int]:
    if graph.num_nodes and int(graph.node_ids[0]) < 0:  # node_ids are sorted
        raise GraphError(f"node id {int(graph.node_ids[0])}: GTSAM keys are unsigned, so "
                         "negative node ids cannot be keys")
    return [int(v) for v in graph.node_ids]


def _yaw(rot: FloatArray) -> FloatArray:
    return np.arctan2(rot[..., 1, 0], rot[..., 0, 0])


def to_gtsam(graph: PoseGraph, rotations: FloatArray | None = None,
             translations: FloatArray | None = None, *, anchor: bool = False,
             planar: bool | None = None) -> tuple[Any, Any]:
    """GTSAM factors and initial values of ``graph`` (see the module docstring's conventions).

    Parameters
    ----------
    graph : PoseGraph
    rotations, translations : (N, 3, 3), (N, 3) float64, optional
        Poses to put in the values (R_world_node, t_world_node); default: the graph's vertices,
        or the tree initialization when the file had none (iSAM).
    anchor : bool
        Append :func:`gauge_prior` (fix the gauge as our solvers do, for GTSAM's optimizers).
    planar : bool, optional
        Pose2 (True) or Pose3 (False); default: Pose2 for 2D graphs without GPS.

    Returns
    -------
    factors : gtsam.NonlinearFactorGraph
        One factor per relative constraint in ``graph``'s edge order, then one ``GPSFactor`` per
        GPS constraint, then (``anchor``) the gauge prior.  Without ``anchor``,
        ``2 * factors.error(values)`` equals :func:`hybridpgo.energy` at the same poses.
    values : gtsam.Values
        Keyed by the file's node ids.

    Raises
    ------
    HybridPGOError
        gtsam is not installed (the message names ``hybridpgo[gtsam]``).
    GraphError
        A node id is negative (GTSAM keys are unsigned).
    """
    gtsam = require_gtsam()
    rot, trans = given_or_start(graph, rotations, translations)
    pose2 = _uses_pose2(graph, planar)
    keys = _keys(graph)
    values = gtsam.Values()
    if pose2:
        yaw = _yaw(rot)
        for i, key in enumerate(keys):
            values.insert(key, gtsam.Pose2(float(trans[i, 0]), float(trans[i, 1]), float(yaw[i])))
    else:
        for i, key in enumerate(keys):
            values.insert(key, gtsam.Pose3(gtsam.Rot3(rot[i]), trans[i]))

    factors = gtsam.NonlinearFactorGraph()
    a_keys = graph.node_ids[graph.edge_nodes[:, 0]].tolist()
    b_keys = graph.node_ids[graph.edge_nodes[:, 1]].tolist()
    information = gtsam.noiseModel.Gaussian.Information
    if pose2:
        info3 = planar_information(graph.edge_information)
        z_yaw = _yaw(graph.edge_rotations)
        zt = graph.edge_translations
        for c in range(graph.num_edges):
            z = gtsam.Pose2(float(zt[c, 0]), float(zt[c, 1]), float(z_yaw[c]))
            factors.add(gtsam.BetweenFactorPose2(a_keys[c], b_keys[c], z, information(info3[c])))
    else:
        perm = TO_GTSAM_TANGENT
        info6 = np.ascontiguousarray(graph.edge_information[:, perm[:, None], perm[None, :]])
        for c in range(graph.num_edges):
            z = gtsam.Pose3(gtsam.Rot3(graph.edge_rotations[c]), graph.edge_translations[c])
            factors.add(gtsam.BetweenFactorPose3(a_keys[c], b_keys[c], z, information(info6[c])))
        gps_keys = graph.node_ids[graph.gps_nodes].tolist()
        for c in range(graph.num_gps):
            factors.add(gtsam.GPSFactor(gps_keys[c], graph.gps_positions[c],
                                        information(graph.gps_information[c])))
    if anchor:
        factors.push_back(gauge_prior(graph, values))
    return factors, values


def gauge_prior(graph: PoseGraph, values: Any, sigma: float = GAUGE_SIGMA) -> Any:
    """Priors that hold the gauge where our solvers hold it, at the poses in ``values``.

    The ``FIX`` nodes, else the first pose, each get a ``PriorFactorPose3`` (or ``Pose2``) with
    isotropic standard deviation ``sigma``.  A graph with GPS constraints needs none (the earth
    frame is fixed): the result is then empty.

    Returns
    -------
    gtsam.NonlinearFactorGraph
    """
    gtsam = require_gtsam()
    prior = gtsam.NonlinearFactorGraph()
    if graph.num_gps:
        return prior
    fixed = graph.fixed_nodes if graph.fixed_nodes.size else np.zeros(1, np.int32)
    for key in graph.node_ids[fixed].tolist():
        if values.exists(key) and _holds_pose2(values, key):
            prior.add(gtsam.PriorFactorPose2(key, values.atPose2(key),
                                             gtsam.noiseModel.Isotropic.Sigma(3, sigma)))
        else:
            prior.add(gtsam.PriorFactorPose3(key, values.atPose3(key),
                                             gtsam.noiseModel.Isotropic.Sigma(6, sigma)))
    return prior


def _holds_pose2(values: Any, key: int) -> bool:
    try:
        values.atPose2(key)
    except RuntimeError:
        return False
    return True


def from_gtsam(graph: PoseGraph, values: Any) -> tuple[FloatArray, FloatArray]:
    """The poses of ``graph``'s nodes held in GTSAM ``values`` (keyed by node id).

    Parameters
    ----------
    graph : PoseGraph
    values : gtsam.Values
        Pose3 or Pose2 values (as :func:`to_gtsam` makes them, e.g. an optimizer's result); other
        keys are ignored.

    Returns
    -------
    rotations : (N, 3, 3) float64
        R_world_node in ``graph``'s node order (Pose2: rotations about z).
    translations : (N, 3) float64
        t_world_node (Pose2: z = 0).

    Raises
    ------
    GraphError
        A node of ``graph`` has no Pose3/Pose2 in ``values`` (the message lists some ids).
    """
    gtsam = require_gtsam()
    ids = graph.node_ids
    n = graph.num_nodes
    for kind in ("Pose3", "Pose2"):
        keys = np.asarray(list(getattr(gtsam.utilities, f"all{kind}s")(values).keys()),
                          np.int64)
        if keys.size == 0:
            continue
        pos = np.searchsorted(keys, ids)  # both sorted ascending
        found = (pos < keys.size) & (keys[np.minimum(pos, keys.size - 1)] == ids)
        if not found.all():
            if found.any():
                break  # some nodes here: report the missing ones below
            continue
        data = np.asarray(getattr(gtsam.utilities, f"extract{kind}")(values), np.float64)[pos]
        if kind == "Pose3":
            rot = np.ascontiguousarray(data[:, :9].reshape(n, 3, 3))
            trans = np.ascontiguousarray(data[:, 9:12])
        else:
            c, s = np.cos(data[:, 2]), np.sin(data[:, 2])
            rot = np.zeros((n, 3, 3))
            rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1] = c, -s, s, c
            rot[:, 2, 2] = 1.0
            trans = np.column_stack([data[:, 0], data[:, 1], np.zeros(n)])
        return rot, trans
    else:
        found = np.zeros(n, bool)
    missing = ids[~found]
    shown = ", ".join(str(int(v)) for v in missing[:10])
    more = f" and {missing.size - 10} more" if missing.size > 10 else ""
    raise GraphError(f"the GTSAM values hold no Pose3 or Pose2 for {missing.size} of {n} "
                     f"node(s): id(s) {shown}{more}")
