"""Body templates with the SMPL skeleton, in SMPL's canonical frame.

SMPL canonical frame: y up, z forward (the body faces +z), x to the body's left, metres,
origin near the pelvis. Two sources:

- the shipped open template derived from the Anny body model
  (``assets/anny_cmu_mb_rest_neutral.npz``, see ``assets/README.md`` for licence and
  attribution). Its file frame is z up, +x = body's left, front = -y; it is converted with
  ``p_smpl = (x, z, -y)``.
- a user-given SMPL model pickle (licence-restricted, never shipped), read through the
  restricted unpickler :func:`omnire.io.safe_pickle.load`.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import numpy as np

from omnire.api import MissingFileError, UserError, safe_pickle

ASSET_DIR = Path(__file__).resolve().parent / "assets"
ANNY_TEMPLATE = ASSET_DIR / "anny_cmu_mb_rest_neutral.npz"

NUM_JOINTS = 24
SMPL_JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand",
)
SMPL_PARENTS = np.array(
    [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21], dtype=np.int64
)

# Anny file frame (z up, front -y) -> SMPL canonical (y up, front +z): p_smpl = A @ p_anny.
ANNY_TO_SMPL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


class BodyTemplateError(UserError):
    """A body template file is missing fields or has inconsistent shapes (message names the file)."""


@dataclasses.dataclass
class BodyTemplate:
    """A skinnable body in SMPL's canonical frame (float64).

    Attributes:
        vertices: (V, 3) rest-pose vertices.
        faces: (F, 3) int64 triangle indices.
        joints: (24, 3) rest joint positions, SMPL order.
        parents: (24,) int64 parent index per joint, -1 for the pelvis.
        weights: (V, 24) skinning weights, rows sum to 1.
        shapedirs: optional (V, 3, B) shape blend shapes.
        posedirs: optional (V, 3, 207) pose blend shapes (23 joints x 9 entries of R - I).
        J_regressor: optional (24, V) joint regressor (joints = J_regressor @ shaped vertices).
        source: where the template came from.
    """

    vertices: np.ndarray
    faces: np.ndarray
    joints: np.ndarray
    parents: np.ndarray
    weights: np.ndarray
    shapedirs: Optional[np.ndarray] = None
    posedirs: Optional[np.ndarray] = None
    J_regressor: Optional[np.ndarray] = None
    source: str = ""

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    def check(self) -> "BodyTemplate":
        """Validate shapes; raise :class:`BodyTemplateError` naming the source."""
        V = self.vertices.shape[0]
        expect = {
            "vertices": (self.vertices, (V, 3)),
            "joints": (self.joints, (NUM_JOINTS, 3)),
            "parents": (self.parents, (NUM_JOINTS,)),
            "weights": (self.weights, (V, NUM_JOINTS)),
        }
        for name, (arr, shape) in expect.items():
            if arr.shape != shape:
                raise BodyTemplateError(f"{self.source}: {name} has shape {arr.shape}, expected {shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise BodyTemplateError(f"{self.source}: faces has shape {self.faces.shape}, expected (F, 3)")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= V):
            raise BodyTemplateError(f"{self.source}: faces index outside 0..{V - 1}")
        if self.parents[0] != -1 or any(self.parents[j] >= j or self.parents[j] < 0 for j in range(1, NUM_JOINTS)):
            raise BodyTemplateError(f"{self.source}: parents must be a tree with parent[j] < j and parent[0] = -1")
        if self.shapedirs is not None and self.shapedirs.shape[:2] != (V, 3):
            raise BodyTemplateError(f"{self.source}: shapedirs has shape {self.shapedirs.shape}, expected (V, 3, B)")
        if self.posedirs is not None and self.posedirs.shape != (V, 3, 207):
            raise BodyTemplateError(f"{self.source}: posedirs has shape {self.posedirs.shape}, expected ({V}, 3, 207)")
        if self.J_regressor is not None and self.J_regressor.shape != (NUM_JOINTS, V):
            raise BodyTemplateError(
                f"{self.source}: J_regressor has shape {self.J_regressor.shape}, expected ({NUM_JOINTS}, {V})"
            )
        return self


def load_anny_template(path: str | Path = ANNY_TEMPLATE) -> BodyTemplate:
    """Load the open Anny-derived template (npz, no pickles) converted to SMPL's frame."""
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"{path}: body template not found")
    with np.load(path, allow_pickle=False) as d:
        missing = [k for k in ("vertices", "faces", "joints24", "joint24_parents", "weights24") if k not in d.files]
        if missing:
            raise BodyTemplateError(f"{path}: missing arrays {missing}")
        verts = d["vertices"].astype(np.float64) @ ANNY_TO_SMPL.T  # (V, 3)
        joints = d["joints24"].astype(np.float64) @ ANNY_TO_SMPL.T  # (24, 3)
        tmpl = BodyTemplate(
            vertices=verts,
            faces=d["faces"].astype(np.int64),
            joints=joints,
            parents=d["joint24_parents"].astype(np.int64),
            weights=d["weights24"].astype(np.float64),
            source=str(path),
        )
    return tmpl.check()


def _dense(x: object, name: str, path: Path) -> np.ndarray:
    if x is None:
        raise BodyTemplateError(f"{path}: SMPL pickle has no {name!r}")
    arr = np.asarray(x)
    if arr.dtype == object:
        raise BodyTemplateError(f"{path}: {name!r} is not a numeric array")
    return arr


class _ChumpyArray(safe_pickle.StandIn):
    """Stand-in for ``chumpy.ch.Ch``: keeps the ``x`` array from its pickled state."""

    def __init__(self, *args, **kwargs) -> None:
        self.x: np.ndarray | None = None

    def to_plain(self):
        return self.x

    def __setstate__(self, state) -> None:
        self.x = np.asarray(state.get("x", state.get("_x"))) if isinstance(state, dict) else np.asarray(state)


class _SparseMatrix(safe_pickle.StandIn):
    """Stand-in for scipy ``csc_matrix`` / ``csr_matrix``: densified from its pickled state."""

    compressed_columns = True

    def __init__(self, *args, **kwargs) -> None:
        self.state: dict = {}

    def __setstate__(self, state) -> None:
        self.state = dict(state)

    def to_plain(self) -> np.ndarray:
        s = self.state
        shape = tuple(s["_shape"]) if "_shape" in s else tuple(s["shape"])
        data, indices, indptr = (np.asarray(s[k]) for k in ("data", "indices", "indptr"))
        out = np.zeros(shape, dtype=data.dtype)
        major = shape[1] if self.compressed_columns else shape[0]
        for j in range(major):
            rows, vals = indices[indptr[j]:indptr[j + 1]], data[indptr[j]:indptr[j + 1]]
            if self.compressed_columns:
                out[rows, j] = vals
            else:
                out[j, rows] = vals
        return out


class _CsrMatrix(_SparseMatrix):
    compressed_columns = False


SMPL_PICKLE = safe_pickle.NUMPY_DATA | safe_pickle.PickleAllowlist(frozenset(), {
    ("chumpy.ch", "Ch"): _ChumpyArray,
    ("chumpy.reordering", "Select"): _ChumpyArray,
    ("scipy.sparse.csc", "csc_matrix"): _SparseMatrix,
    ("scipy.sparse._csc", "csc_matrix"): _SparseMatrix,
    ("scipy.sparse.csr", "csr_matrix"): _CsrMatrix,
    ("scipy.sparse._csr", "csr_matrix"): _CsrMatrix,
})
"""What an SMPL model pickle may hold: numpy data, chumpy arrays and scipy sparse matrices
(both replaced by numpy, so neither package is needed)."""
SMPL_PICKLE_MAX_BYTES = 1 << 30
"""SMPL model files are ~40-250 MB unpickled; larger content is refused."""


def load_smpl_pickle(path: str | Path) -> BodyTemplate:
    """Load a user-given SMPL model pickle (``v_template``, ``weights``, ``J_regressor``,
    ``kintree_table``, ``shapedirs``, ``posedirs``, ``f``) through the restricted unpickler.

    Chumpy arrays and scipy sparse matrices are turned into numpy by the unpickler's
    stand-ins, so neither package is needed.
    """
    path = Path(path)
    data = safe_pickle.load(path, SMPL_PICKLE, SMPL_PICKLE_MAX_BYTES)
    if not isinstance(data, dict):
        raise BodyTemplateError(f"{path}: expected a dict, got {type(data).__name__}")
    verts = _dense(data.get("v_template"), "v_template", path).astype(np.float64)  # (V, 3)
    weights = _dense(data.get("weights"), "weights", path).astype(np.float64)  # (V, 24)
    regressor = _dense(data.get("J_regressor"), "J_regressor", path).astype(np.float64)  # (24, V)
    kintree = _dense(data.get("kintree_table"), "kintree_table", path).astype(np.int64)  # (2, 24)
    faces = _dense(data.get("f"), "f", path).astype(np.int64)
    parents = kintree[0].copy()
    parents[0] = -1  # SMPL stores 2**32-1 for the root
    shapedirs = data.get("shapedirs")
    posedirs = data.get("posedirs")
    tmpl = BodyTemplate(
        vertices=verts,
        faces=faces,
        joints=regressor @ verts,
        parents=parents,
        weights=weights,
        shapedirs=None if shapedirs is None else _dense(shapedirs, "shapedirs", path).astype(np.float64),
        posedirs=None if posedirs is None else _dense(posedirs, "posedirs", path).astype(np.float64),
        J_regressor=regressor,
        source=str(path),
    )
    return tmpl.check()


def load_template(path: str | Path | None = None) -> BodyTemplate:
    """The shipped open template, or the file at ``path`` (``.npz`` Anny-style, else an SMPL pickle)."""
    if path is None:
        return load_anny_template()
    path = Path(path)
    if path.suffix == ".npz":
        return load_anny_template(path)
    return load_smpl_pickle(path)
