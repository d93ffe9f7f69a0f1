"""Accuracy of an estimated trajectory against ground truth, and TUM export.

Example (not a doctest)::

    from hybridpgo.io import read_graph
    from hybridpgo.metrics import evaluate, match_by_ids, read_ground_truth

    out = read_graph("city_solved.g2o")
    gt_rot, gt_trans, gt_ids = read_ground_truth("city_gt.g2o")
    ie, ig = match_by_ids(out.node_ids, gt_ids)
    evaluate(out.rotations[ie], out.translations[ie], gt_rot[ig], gt_trans[ig],
             align=out.num_gps == 0)

* **Position error**: ``|p_est - p_gt|``.  Without GPS the solution's frame is arbitrary (gauge:
  the first pose), so ``align=True`` first moves the estimate by the rigid motion (rotation +
  translation, no scale; Kabsch/Umeyama) that best fits its positions onto the true ones.  With
  GPS the earth frame is absolute: ``align=False``.
* **Rotation error**: the angle of ``R_gt^T R_est``, the full 3D orientation difference (after
  the alignment rotation when aligned); evo's APE ``rotation_angle_deg``.
* **Heading error**: the yaw-only difference ``|wrap(yaw_est - yaw_gt)|`` with
  ``yaw = atan2(R[1, 0], R[0, 0])``, the direction of the body x axis in the horizontal plane
  (the vehicle's heading); roll and pitch errors do not count.
* **Relative pose error** (RPE) over pose pairs ``(i, i + delta)``: the translation (m) and angle
  (deg) of ``(T_gt_i^-1 T_gt_j)^-1 (T_est_i^-1 T_est_j)``, RMSE; alignment-free by nature.

Each per-pose error is summarized as evo does: RMSE, mean, median, standard deviation
(population, ``ddof=0``) and max (keys ``<error>_<stat>_<unit>``).

Poses are ``(R_world_node (N, 3, 3), t_world_node (N, 3))``.  :func:`write_tum` writes the TUM
format (``timestamp tx ty tz qx qy qz qw``) that ``evo`` reads.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .errors import FormatError, GraphError
from .geometry import se3, so3
from .io import read_graph_source
from .io._lines import PathLike, Source, fmt_floats, load_source, parse_float, write_atomic
from .io.tum import read_tum as read_tum  # re-exported: one TUM reader
from .io.tum import read_tum_source

__all__ = [
    "align_rigid",
    "evaluate",
    "match_by_ids",
    "read_ground_truth",
    "read_tum",
    "write_tum",
]

FloatArray = npt.NDArray[np.float64]
IdArray = npt.NDArray[np.int64]

#: How many missing ids an error message lists before "... and k more".
_MAX_LISTED = 10


def _poses(rot: npt.ArrayLike, trans: npt.ArrayLike, what: str) -> tuple[FloatArray, FloatArray]:
    r = np.asarray(rot, dtype=np.float64)
    t = np.asarray(trans, dtype=np.float64)
    if r.ndim != 3 or r.shape[1:] != (3, 3) or t.shape != (r.shape[0], 3):
        raise ValueError(f"{what} poses must have shapes (N, 3, 3) and (N, 3), got {r.shape} "
                         f"and {t.shape}")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(t))):
        raise ValueError(f"{what} poses contain non-finite values")
    return r, t


def align_rigid(source: npt.ArrayLike, target: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Rotation R and translation t minimizing ``sum |R source_i + t - target_i|^2`` (no scale).

    Kabsch/Umeyama: SVD of the cross-covariance, with the sign fix that excludes reflections.
    Degenerate point sets (fewer than 3 points, collinear) give one of the equally good fits.

    Parameters
    ----------
    source, target : (N, 3) array_like

    Returns
    -------
    R : (3, 3) float64 rotation
    t : (3,) float64
    """
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape or src.shape[0] == 0:
        raise ValueError(f"source and target must both have shape (N, 3), N >= 1, got "
                         f"{src.shape} and {dst.shape}")
    mu_s = src.mean(axis=0)
    mu_d = dst.mean(axis=0)
    cov = (dst - mu_d).T @ (src - mu_s)  # sum of d_i s_i^T
    u, _, vt = np.linalg.svd(cov)
    d = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(u @ vt)) or 1.0)])
    r = u @ d @ vt
    return r, mu_d - r @ mu_s


def evaluate(est_rot: npt.ArrayLike, est_trans: npt.ArrayLike, gt_rot: npt.ArrayLike,
             gt_trans: npt.ArrayLike, *, align: bool, rpe_delta: int = 1
             ) -> dict[str, float | int | bool]:
    """Position, heading and relative pose errors of an estimate against ground truth.

    Parameters
    ----------
    est_rot, est_trans : (N, 3, 3), (N, 3) array_like
        Estimated R_world_node, t_world_node (metres).
    gt_rot, gt_trans : (N, 3, 3), (N, 3) array_like
        True poses, same order (see :func:`match_by_ids`).
    align : bool
        First fit the estimate rigidly onto the truth by its positions (no GPS: the frame is
        arbitrary); False with GPS (the earth frame is absolute).
    rpe_delta : int
        RPE over pairs ``(i, i + rpe_delta)`` (1: consecutive poses).

    Returns
    -------
    dict
        JSON-friendly plain numbers: ``num_poses``, ``aligned``, ``alignment_rotation_deg``,
        ``alignment_translation_m`` (the applied fit; 0 when not aligned); for each of
        ``position_..._m``, ``rotation_error_..._deg`` (full angle) and
        ``heading_error_..._deg`` (yaw only) the statistics ``rmse``, ``mean``, ``median``,
        ``std``, ``max`` (e.g. ``position_rmse_m``, ``heading_error_median_deg``); then
        ``rpe_delta``, ``rpe_num_pairs``, ``rpe_translation_rmse_m``, ``rpe_rotation_rmse_deg``
        (RPE values are 0 with no pairs).

    Raises
    ------
    ValueError
        Shapes differ or are wrong, values not finite, no poses, ``rpe_delta < 1``.
    """
    er, et = _poses(est_rot, est_trans, "estimated")
    gr, gt = _poses(gt_rot, gt_trans, "ground-truth")
    n = er.shape[0]
    if gr.shape[0] != n:
        raise ValueError(f"the estimate has {n} poses and the ground truth {gr.shape[0]}: "
                         "match them first (match_by_ids)")
    if n == 0:
        raise ValueError("no poses to evaluate")
    if rpe_delta < 1:
        raise ValueError(f"rpe_delta must be at least 1, got {rpe_delta}")
    if align:
        r_al, t_al = align_rigid(et, gt)
        er = r_al @ er
        et = et @ r_al.T + t_al
        al_rot = float(np.degrees(so3.angle(r_al)))
        al_trans = float(np.linalg.norm(t_al))
    else:
        al_rot = al_trans = 0.0
    pos = np.linalg.norm(et - gt, axis=1)
    rot_err = np.degrees(so3.angle(np.swapaxes(gr, 1, 2) @ er))
    head = np.degrees(np.abs(_wrap(_yaw(er) - _yaw(gr))))

    pairs = max(n - rpe_delta, 0)
    rpe_t = rpe_r = 0.0
    if pairs:
        i, j = np.arange(pairs), np.arange(rpe_delta, n)
        rel_er, rel_et = se3.between(er[i], et[i], er[j], et[j])
        rel_gr, rel_gt = se3.between(gr[i], gt[i], gr[j], gt[j])
        d_r, d_t = se3.between(rel_gr, rel_gt, rel_er, rel_et)
        rpe_t = float(np.sqrt(np.mean(np.einsum("ij,ij->i", d_t, d_t))))
        rpe_r = float(np.sqrt(np.mean(np.degrees(so3.angle(d_r)) ** 2)))
    return {
        "num_poses": int(n),
        "aligned": bool(align),
        "alignment_rotation_deg": al_rot,
        "alignment_translation_m": al_trans,
        **_stats(pos, "position", "m"),
        **_stats(rot_err, "rotation_error", "deg"),
        **_stats(head, "heading_error", "deg"),
        "rpe_delta": int(rpe_delta),
        "rpe_num_pairs": int(pairs),
        "rpe_translation_rmse_m": rpe_t,
        "rpe_rotation_rmse_deg": rpe_r,
    }


#: The statistics of each per-pose error, in evo's definitions.
STATISTICS = ("rmse", "mean", "median", "std", "max")


def _stats(err: FloatArray, name: str, unit: str) -> dict[str, float]:
    """``{name_rmse_unit: ..., name_mean_unit: ...}`` as evo computes them (std: ddof=0)."""
    values = {"rmse": np.sqrt(np.mean(err**2)), "mean": np.mean(err), "median": np.median(err),
              "std": np.std(err), "max": np.max(err)}
    return {f"{name}_{k}_{unit}": float(values[k]) for k in STATISTICS}


def _yaw(rot: FloatArray) -> FloatArray:
    """Heading of the body x axis in the horizontal plane (ZYX Euler yaw), radians."""
    return np.arctan2(rot[..., 1, 0], rot[..., 0, 0])


def _wrap(angle: FloatArray) -> FloatArray:
    """Angles into [-pi, pi)."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def match_by_ids(est_ids: npt.ArrayLike, gt_ids: npt.ArrayLike) -> tuple[IdArray, IdArray]:
    """Index arrays pairing every estimated pose with the ground-truth pose of the same id.

    Parameters
    ----------
    est_ids, gt_ids : (N,), (K,) array_like of int
        Node ids of the estimate and of the ground truth (the truth may hold more poses).

    Returns
    -------
    est_index, gt_index : (N,) int64
        ``est_ids[est_index] == gt_ids[gt_index]``, in the estimate's order (``est_index`` is
        ``arange(N)``).

    Raises
    ------
    GraphError
        An estimated id has no ground truth (the message lists them), or ids repeat.
    """
    e = np.asarray(est_ids).reshape(-1)
    g = np.asarray(gt_ids).reshape(-1)
    for name, ids in (("estimate", e), ("ground truth", g)):
        if ids.size and not np.issubdtype(ids.dtype, np.integer):
            if not np.all(np.equal(np.mod(ids, 1), 0)):
                raise GraphError(f"the {name}'s ids must be integers")
        uniq, counts = np.unique(ids, return_counts=True)
        if np.any(counts > 1):
            dup = uniq[counts > 1]
            raise GraphError(f"the {name} repeats node id(s) {_listing(dup)}")
    e = e.astype(np.int64)
    g = g.astype(np.int64)
    order = np.argsort(g, kind="stable")
    pos = np.searchsorted(g[order], e)
    pos_c = np.minimum(pos, max(g.size - 1, 0))
    found = (pos < g.size) & (g[order][pos_c] == e) if g.size else np.zeros(e.size, bool)
    if not np.all(found):
        missing = e[~found]
        raise GraphError(f"{missing.size} of {e.size} estimated pose(s) have no ground truth: "
                         f"node id(s) {_listing(missing)}")
    return np.arange(e.size, dtype=np.int64), order[pos_c].astype(np.int64)


def _listing(ids: npt.NDArray[np.int64]) -> str:
    shown = ", ".join(str(int(v)) for v in ids[:_MAX_LISTED])
    more = f" and {ids.size - _MAX_LISTED} more" if ids.size > _MAX_LISTED else ""
    return shown + more


# =========================================================================== files
def _looks_like_tum(src: Source) -> bool:
    """True when the first data line starts with a number (g2o/TORO lines start with a tag)."""
    for line in src.lines:
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        return parse_float(tok[0]) is not None
    return False


def read_ground_truth(path: PathLike, *, fix_information: str | None = None,
                      ) -> tuple[FloatArray, FloatArray, IdArray]:
    """Poses of a ground-truth file: g2o/TORO vertices, or a TUM trajectory (``"-"``: stdin).

    ``fix_information`` applies to the constraints of a graph file, as in
    :func:`hybridpgo.io.read_graph` (they are read but not used).

    A file whose first data line starts with a number is read as TUM (:func:`read_tum`);
    anything else with :func:`hybridpgo.io.read_graph` (its vertex lines; the constraints are
    read too but not used, and need not connect the poses).

    Returns
    -------
    rotations : (N, 3, 3) float64
    translations : (N, 3) float64
    ids : (N,) int64
        The file's vertex ids (g2o/TORO), or for TUM the timestamps when they are all integers
        (as :func:`write_tum` writes node ids), else 0..N-1.

    Raises
    ------
    FormatError
        The file cannot be read, is malformed, or has no vertex lines (e.g. iSAM).
    """
    src = load_source(path, fix_information)  # once: "-" (standard input) can be read once
    if _looks_like_tum(src):
        stamps, rot, trans = read_tum_source(src)
        if (np.all(np.equal(np.mod(stamps, 1.0), 0.0)) and np.unique(stamps).size == stamps.size
                and np.abs(stamps).max() < 2.0**63):
            ids = stamps.astype(np.int64)
        else:
            ids = np.arange(stamps.size, dtype=np.int64)
        return rot, trans, ids
    graph = read_graph_source(src, check_connected=False)
    if not graph.has_estimates:
        raise FormatError("the file has no vertex lines, so no poses to compare with", src.path)
    return (np.array(graph.rotations), np.array(graph.translations), np.array(graph.node_ids))


def write_tum(path: PathLike, rotations: npt.ArrayLike, translations: npt.ArrayLike,
              timestamps: npt.ArrayLike | None = None) -> None:
    """Write poses as a TUM trajectory (``timestamp tx ty tz qx qy qz qw``), atomically.

    Numbers are written with ``repr`` (round-trip exact); quaternions are unit, ``w >= 0``.

    Parameters
    ----------
    rotations, translations : (N, 3, 3), (N, 3) array_like
    timestamps : (N,) array_like, optional
        Default: the pose index 0..N-1.  Pass node ids to keep them (:func:`read_ground_truth`
        returns integer timestamps as ids).
    """
    r, t = _poses(rotations, translations, "the")
    n = r.shape[0]
    stamps = np.arange(n, dtype=np.float64) if timestamps is None else \
        np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if stamps.shape[0] != n:
        raise ValueError(f"timestamps must have one entry per pose ({n}), got {stamps.shape[0]}")
    rows = np.column_stack([stamps, t, so3.matrix_to_quat_xyzw(r)])
    write_atomic(path, lambda: fmt_floats(rows))  # "-": standard output
