"""Saving and loading an online solver's state (``OnlineSolver.save`` / ``load``).

Format (:data:`FORMAT`, :data:`VERSION`): a NumPy ``.npz`` archive (a zip of ``.npy`` arrays,
no pickled object: :func:`numpy.load` reads it with ``allow_pickle=False``).  ``meta`` holds a
JSON object (the config, the counters); the other members are plain numeric arrays: the inputs
(pose ids, odometry, edges, GPS readings), the tree (parents, local transforms), 𝔅(H) and each
constraint's last contribution, the priorities, the queues, the constraints rejected as outliers,
the junction groups and the cost model.  Constraints are named in arrival order (an edge
``e``; a GPS reading ``g`` as ``-(g + 1)``), never by the store's internal index.

Loading never trusts the file: every member must have the expected dtype and shape, every
index must be in range, every matrix finite (rotations orthonormal, information SPD), the tree
a tree in which parents are older than their children; everything that can be derived (depths,
paths, path counts, whitening, group membership) is recomputed rather than read.  Anything else
is refused with one :class:`~hybridpgo.errors.FormatError` naming the file and the problem; a
state file can neither crash the process nor run code.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import FormatError
from ._validate import ROTATION_TOL
from .config import OnlineConfig

if TYPE_CHECKING:
    from .store import MapStore

#: File format tag and version.
FORMAT = "hybridpgo-online"
VERSION = 3
#: Versions read: 2 lacks ``rejected`` and ``requeue`` (read as empty).
READABLE = (2, 3)
#: Counters in ``meta`` (each an integer >= 0 unless said otherwise).
_COUNTERS = ("n", "placed", "m", "m_laid", "g", "g_laid", "frame", "ngroups", "cursor",
             "gps_cursor", "gps_links")
#: Members other than ``meta``: dtype kind and shape, in terms of the counters.  ``P`` is
#: ``placed + 1`` (tree nodes with the earth), ``E``/``G`` the path entries of the laid edges /
#: GPS readings, ``Q`` the queue's length, ``K`` the groups' members in all.
_MEMBERS: dict[str, tuple[str, tuple[str | int, ...]]] = {
    "ids": ("i", ("n",)), "odom": ("i", ("n",)),
    "first_rot": ("f", (3, 3)), "first_trans": ("f", (3,)),
    "parent": ("i", ("P",)), "rot": ("f", ("P", 3, 3)), "trans": ("f", ("P", 3)),
    "bdiag": ("f", ("P", 6, 6)),
    "edge_ab": ("i", ("m", 2)), "edge_rot": ("f", ("m", 3, 3)), "edge_trans": ("f", ("m", 3)),
    "edge_info": ("f", ("m", 6, 6)),
    "gps_node": ("i", ("g",)), "gps_pos": ("f", ("g", 3)), "gps_info": ("f", ("g", 3, 3)),
    "contrib_e": ("f", ("E", 6, 6)), "contrib_g": ("f", ("G", 6, 6)),
    "chi2_e": ("f", ("m",)), "chi2_g": ("f", ("g",)),
    "queue": ("i", ("Q",)),
    "rejected": ("i", ("R",)), "requeue": ("i", ("RQ",)),
    "group_ptr": ("i", ("ngroups+1",)), "group_members": ("i", ("K",)),
    "group_stamp": ("i", ("ngroups",)),
    "model": ("f", (3,)),
}
#: Largest member accepted (bytes): a crafted header cannot make the reader allocate more.
MAX_MEMBER_BYTES = 1 << 36


# --------------------------------------------------------------------------- saving
def state_arrays(st: MapStore, config: OnlineConfig, counters: dict[str, int]
                 ) -> dict[str, np.ndarray]:
    """Every member of a saved state (``meta`` as JSON bytes), copies: the store ``st``, the
    solver's ``config`` and its ``counters`` (``frame``, ``cursor``, ``gps_cursor``)."""
    from dataclasses import asdict

    p = st.placed + 1
    pe = int(st.ptr[st.m_laid])
    g0, g1 = st.cap_pe, int(st.ptr[st.cap_m + st.g_laid])
    cm = st.cap_m
    k = int(st.group_ptr[st.ngroups])
    meta = {"format": FORMAT, "version": VERSION, "config": asdict(config),
            "n": st.n, "placed": st.placed, "m": st.m, "m_laid": st.m_laid, "g": st.g,
            "g_laid": st.g_laid, "frame": int(counters["frame"]), "ngroups": st.ngroups,
            "cursor": int(counters["cursor"]), "gps_cursor": int(counters["gps_cursor"]),
            "gps_links": st.gps_links}
    arrays: dict[str, np.ndarray] = {
        "meta": np.frombuffer(json.dumps(meta).encode(), np.uint8),
        "ids": st.ids[: st.n], "odom": st.odom[: st.n],
        "first_rot": st.first_rot, "first_trans": st.first_trans,
        "parent": st.parent[:p], "rot": st.rot[:p], "trans": st.trans[:p],
        "bdiag": st.bdiag[:p],
        "edge_ab": st.edge_ab[: st.m], "edge_rot": st.edge_rot[: st.m],
        "edge_trans": st.edge_trans[: st.m], "edge_info": st.edge_info[: st.m],
        "gps_node": st.gps_node[: st.g], "gps_pos": st.gps_pos[: st.g],
        "gps_info": st.gps_info[: st.g],
        "contrib_e": st.contrib[:pe], "contrib_g": st.contrib[g0:g1],
        "chi2_e": st.chi2[: st.m], "chi2_g": st.chi2[cm: cm + st.g],
        "queue": st.arrival_names(st.pending()),
        "requeue": st.arrival_names(st.requeue),
        "rejected": st.arrival_names(np.concatenate([
            np.flatnonzero(st.rejected[: st.m]), cm + np.flatnonzero(st.rejected[cm: cm + st.g])])),
        "group_ptr": st.group_ptr[: st.ngroups + 1],
        "group_members": st.arrival_names(st.group_members[:k]),
        "group_stamp": st.group_stamp[: st.ngroups],
        "model": st.model,
    }  # fmt: skip
    return {k: np.array(v, copy=True) for k, v in arrays.items()}


def write_state(path: str | os.PathLike[str], arrays: dict[str, np.ndarray]) -> None:
    """Write the members ``arrays`` (:func:`state_arrays`) to ``path`` with the output rules of
    every file the package writes (:func:`hybridpgo._output.write_file`: a temporary file beside
    the target, then a rename; a symbolic link is written through; a directory, FIFO or device is
    refused)."""
    from .._output import write_file

    def dump(fh: Any) -> None:
        np.savez(fh, **arrays)  # type: ignore[arg-type]

    write_file(path, dump, streams=False)


# --------------------------------------------------------------------------- loading
def _read_members(name: str) -> dict[str, np.ndarray]:
    """Every member of the archive, each checked before it is read (plain numeric dtype, a
    size that matches the member's)."""
    try:
        zf = zipfile.ZipFile(name)
    except FileNotFoundError as exc:
        raise FormatError("no such file", path=name) from exc
    except (OSError, zipfile.BadZipFile, ValueError, EOFError) as exc:
        raise FormatError(f"not an online solver state (not a NumPy .npz archive: {exc})",
                          path=name) from exc
    out: dict[str, np.ndarray] = {}
    with zf:
        for info in zf.infolist():
            key = info.filename.removesuffix(".npy")
            if key not in _MEMBERS and key != "meta":
                raise FormatError(f"not an online solver state: unexpected member {key!r}",
                                  path=name)
            if info.file_size > MAX_MEMBER_BYTES:
                raise FormatError(f"member {key!r} is too large ({info.file_size} bytes)",
                                  path=name)
            try:
                data = zf.read(info)
                fh = io.BytesIO(data)
                version = np.lib.format.read_magic(fh)
                if version == (1, 0):
                    header = np.lib.format.read_array_header_1_0(fh, max_header_size=10_000)
                elif version == (2, 0):
                    header = np.lib.format.read_array_header_2_0(fh, max_header_size=10_000)
                else:
                    raise ValueError(f".npy format version {version}")
                shape, _, dtype = header
                if dtype.hasobject or dtype.kind not in "biuf" or dtype.subdtype is not None:
                    raise ValueError(f"dtype {dtype} is not a plain number")
                if int(np.prod(shape, dtype=np.int64)) * dtype.itemsize != len(data) - fh.tell():
                    raise ValueError("its size does not match its shape")
                fh.seek(0)
                out[key] = np.load(fh, allow_pickle=False)
            except (ValueError, OSError, EOFError, zipfile.BadZipFile, TypeError,
                    RuntimeError) as exc:
                raise FormatError(f"member {key!r} is not a readable array ({exc})",
                                  path=name) from exc
    return out


def _meta(name: str, raw: np.ndarray | None) -> dict[str, Any]:
    if raw is None:
        raise FormatError("not an online solver state (no 'meta' member)", path=name)
    try:
        meta = json.loads(bytes(np.asarray(raw, np.uint8)).decode())
    except (ValueError, UnicodeDecodeError, TypeError) as exc:
        raise FormatError(f"not an online solver state (meta: {exc})", path=name) from exc
    if not isinstance(meta, dict):
        raise FormatError("not an online solver state (meta is not a JSON object)", path=name)
    if meta.get("format") != FORMAT:
        raise FormatError(f"not an online solver state (format {meta.get('format')!r}, "
                          f"expected {FORMAT!r})", path=name)
    if meta.get("version") not in READABLE:
        raise FormatError(f"online solver state of version {meta.get('version')!r}; this "
                          f"hybridpgo reads versions {', '.join(map(str, READABLE))}",
                          path=name)
    for key in _COUNTERS:
        v = meta.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < 1 << 40:
            raise FormatError(f"meta: {key} must be an integer >= 0, got {v!r}", path=name)
    if not isinstance(meta.get("config"), dict):
        raise FormatError("meta: config must be a JSON object", path=name)
    return meta


def _shapes(meta: dict[str, Any], d: dict[str, np.ndarray]) -> dict[str, int]:
    """The sizes the members' shapes are written in."""
    sizes = {k: int(meta[k]) for k in _COUNTERS}
    sizes["P"] = sizes["placed"] + 1
    sizes["ngroups+1"] = sizes["ngroups"] + 1
    for key, sym in (("contrib_e", "E"), ("contrib_g", "G"), ("queue", "Q"),
                     ("group_members", "K"), ("rejected", "R"), ("requeue", "RQ")):
        sizes[sym] = int(d[key].shape[0]) if key in d and d[key].ndim else -1
    return sizes


def _check_members(name: str, meta: dict[str, Any], d: dict[str, np.ndarray]) -> None:
    for key in ("rejected", "requeue"):  # members of version 3
        if meta["version"] == 2 and key not in d:
            d[key] = np.zeros(0, np.int64)
    sizes = _shapes(meta, d)
    for key, (kind, shape) in _MEMBERS.items():
        if key not in d:
            raise FormatError(f"not an online solver state (no {key!r} member)", path=name)
        want = tuple(sizes[s] if isinstance(s, str) else s for s in shape)
        arr = d[key]
        if arr.shape != want or (kind == "f" and arr.dtype.kind != "f") or (
                kind == "i" and arr.dtype.kind not in "iu"):
            raise FormatError(f"member {key!r}: expected {kind} array of shape {want}, got "
                              f"{arr.dtype} {arr.shape}", path=name)
        if kind == "f" and not np.all(np.isfinite(arr)):
            raise FormatError(f"member {key!r} holds values that are not finite", path=name)


def read_state(path: str | os.PathLike[str]
               ) -> tuple[OnlineConfig, dict[str, Any], dict[str, np.ndarray]]:
    """The configuration, the ``meta`` record and the members of the state saved at ``path``,
    checked as a file (module docstring); :func:`._restore.restore` checks the values.

    Raises
    ------
    FormatError
        Anything wrong with the file, named with the file.
    """
    name = os.fspath(path)
    members = _read_members(name)
    meta = _meta(name, members.pop("meta", None))
    _check_members(name, meta, members)
    try:
        config = OnlineConfig(**meta["config"])
    except (TypeError, ValueError) as exc:
        raise FormatError(f"meta: config: {exc}", path=name) from exc
    return config, meta, members


__all__ = ["FORMAT", "MAX_MEMBER_BYTES", "READABLE", "ROTATION_TOL", "VERSION", "read_state",
           "state_arrays", "write_state"]
