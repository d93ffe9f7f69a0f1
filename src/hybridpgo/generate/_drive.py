"""What the drive generators (:mod:`.city`, :mod:`.grid`) share: their parameters from a preset,
the graph of a drive (odometry, then loop closures, in online order; dead-reckoned vertices),
and the false loop closures added at the end."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

from ..graph import FloatArray, PoseGraph
from ._common import chain, online_order
from .outliers import Outliers, add_outliers, no_outliers


def check_preset(presets: Mapping[str, object], preset: str | None, what: str) -> None:
    """Raise ``ValueError`` naming ``what`` (e.g. ``"grid preset"``) unless ``preset`` is None
    or one of ``presets``."""
    if preset is not None and preset not in presets:
        raise ValueError(f"unknown {what} {preset!r}; choose one of {', '.join(presets)}")


def preset_values(presets: Mapping[str, Mapping[str, Any]], preset: str | None,
                  params: Mapping[str, Any], params_class: type, kind: str,
                  preset_what: str) -> dict[str, Any]:
    """The keywords of ``params_class``: the preset's (none for None), overridden by ``params``.

    Raises ``ValueError`` for an unknown preset and ``TypeError`` listing the valid names for a
    parameter that is not a field of ``params_class`` (``kind``: the generator, in the message).
    """
    check_preset(presets, preset, preset_what)
    fields = {f.name for f in dataclasses.fields(params_class)}
    unknown = sorted(set(params) - fields)
    if unknown:
        raise TypeError(f"unknown {kind} parameter(s) {', '.join(unknown)}; valid: "
                        + ", ".join(sorted(fields)))
    values: dict[str, Any] = dict(presets[preset]) if preset is not None else {}
    values.update(params)
    return values


def drive_graph(rot: FloatArray, trans: FloatArray, odometry: tuple[FloatArray, FloatArray],
                loops: tuple[np.ndarray, np.ndarray, FloatArray, FloatArray],
                information: FloatArray, **extra: Any) -> PoseGraph:
    """The pose graph of a drive of true poses ``(rot, trans)`` (N of them).

    ``odometry = (zr, zt)``: the N - 1 measurements of edges ``(i, i + 1)``; ``loops = (la,
    lb, lr, lt)``: the loop closures ``(la, lb)`` and their measurements; ``information``:
    (N - 1 + L, 6, 6) in that order (odometry, then loops).  The edges are stored in the order a
    front end would emit them (:func:`._common.online_order`); the vertex estimates are the
    odometry chained from the true first pose.  ``extra``: more :class:`PoseGraph` fields.
    """
    n = rot.shape[0]
    zr, zt = odometry
    la, lb, lr, lt = loops
    order = online_order(n, lb)
    odo_nodes = np.column_stack([np.arange(n - 1), np.arange(1, n)])
    nodes = np.concatenate([odo_nodes, np.column_stack([la, lb])]).astype(np.int32)
    dr_rot, dr_trans = chain(rot[0], trans[0], zr, zt)
    return PoseGraph(
        node_ids=np.arange(n, dtype=np.int64), rotations=dr_rot, translations=dr_trans,
        edge_nodes=nodes[order], edge_rotations=np.concatenate([zr, lr])[order],
        edge_translations=np.concatenate([zt, lt])[order], edge_information=information[order],
        **extra,
    )


class OutlierParams(Protocol):
    """The parameters of a drive generator that :func:`with_outliers` reads."""

    @property
    def num_outliers(self) -> int: ...
    @property
    def near_miss_fraction(self) -> float: ...
    @property
    def near_miss_min_m(self) -> float: ...
    @property
    def near_miss_max_m(self) -> float: ...
    @property
    def loop_min_gap(self) -> int: ...


def with_outliers(graph: PoseGraph, rot: FloatArray, trans: FloatArray, p: OutlierParams,
                  rng: np.random.Generator) -> tuple[PoseGraph, Outliers]:
    """``graph`` with ``p.num_outliers`` false loop closures added (:func:`.add_outliers`) and
    which they are; the true poses ``rot``, ``trans`` are made read-only."""
    outliers = no_outliers()
    if p.num_outliers:
        graph, outliers = add_outliers(
            graph, rot, trans, p.num_outliers, seed=rng,
            near_miss_fraction=p.near_miss_fraction, near_miss_min_m=p.near_miss_min_m,
            near_miss_max_m=p.near_miss_max_m, min_gap=p.loop_min_gap)
    rot.flags.writeable = False
    trans.flags.writeable = False
    return graph, outliers
