"""Which local axis of a processed scene's boxes points along the heading.

omnire boxes put local x along the heading with size = (length, width, height). The
reference's files do so for every source but PandaSet, whose boxes keep the dataset's own
frame: local y along the heading and box_size = (width, length, height) (see
``formats.BOX_HEADING_AXIS``). A file does not say which convention it follows, and files
from other tools may differ, so :func:`detect_heading_axis` checks the file itself:

- motion: a moving object travels along its heading, so the displacement of a box centre,
  written in the box's own frame, points along one local axis (+x, +y, -x or -y);
- shape: a vehicle is longer than wide, so its longer horizontal extent gives the heading
  axis up to its sign (``box_size[i]`` is the extent along local axis i in every source).

Axes are numbered k = 0, 1, 2, 3 for +x, +y, -x, -y: the heading is the file's local x
axis turned by k * 90 degrees about the box's z axis, and ``Rz(k * 90 deg)`` right-multiplied
into the file's box rotation turns it into omnire's box (odd k also swaps length and width).
"""
from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import numpy as np

AXES = ("+x", "+y", "-x", "-y")
"""Heading axis names by k."""

MIN_STEP = 1.0
"""Metres a box centre must move before its displacement counts as a direction of motion."""
MAX_GAP = 20
"""Frames within which that displacement must happen (2 s at 10 Hz)."""
TOLERANCE_DEG = 30.0
"""A displacement votes for the local axis it lies within this angle of (else it is ignored)."""
MIN_ELONGATION = 1.5
"""Vehicle boxes longer than this ratio (long / short horizontal extent) vote by shape."""


def axis_fix(k: int) -> np.ndarray:
    """(3, 3) rotation Rz(k * 90 deg): right-multiplied into a file box rotation whose heading
    axis is ``AXES[k]``, it gives the box rotation with x along the heading."""
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][k % 4]
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float64)


def size_fix(size: np.ndarray, k: int) -> np.ndarray:
    """(..., 3) file extents along local x, y, z -> (length, width, height) for heading axis k."""
    size = np.asarray(size, dtype=np.float64)
    return size[..., [1, 0, 2]] if k % 2 else size.copy()


def motion_votes(frames: np.ndarray, obj_to_world: np.ndarray) -> np.ndarray:
    """Votes of one track's motion for the heading axis.

    Args:
        frames: (n,) frame indices, increasing.
        obj_to_world: (n, 4, 4) box-to-world poses in the file's frame (any world: the
            displacement is measured in the box's own frame).
    Returns:
        (4,) counts of displacements lying along local +x, +y, -x, -y (within
        ``TOLERANCE_DEG``); each displacement runs from a frame to the first later frame at
        least ``MIN_STEP`` metres away and at most ``MAX_GAP`` frames later.
    """
    votes = np.zeros(4)
    n = len(frames)
    if n < 2:
        return votes
    frames = np.asarray(frames)
    c = obj_to_world[:, :3, 3]
    dist = np.linalg.norm(c[None] - c[:, None], axis=-1)  # (n, n)
    later = (frames[None] > frames[:, None]) & (frames[None] - frames[:, None] <= MAX_GAP) & (dist >= MIN_STEP)
    has = later.any(1)
    for i in np.flatnonzero(has):
        j = int(np.argmax(later[i]))  # first qualifying frame (frames increase)
        local = obj_to_world[i, :3, :3].T @ (c[j] - c[i])
        ang = np.arctan2(local[1], local[0])
        k = int(np.round(ang / (np.pi / 2))) % 4
        dev = abs((ang - k * np.pi / 2 + np.pi) % (2 * np.pi) - np.pi)
        if np.rad2deg(dev) <= TOLERANCE_DEG:
            votes[k] += 1
    return votes


def shape_vote(size: np.ndarray) -> Optional[int]:
    """0 if the box is clearly longer along local x, 1 if along local y, else None.
    ``size``: (3,) extents along local x, y, z."""
    a, b = float(size[0]), float(size[1])
    if min(a, b) <= 0:
        return None
    if a >= MIN_ELONGATION * b:
        return 0
    if b >= MIN_ELONGATION * a:
        return 1
    return None


@dataclasses.dataclass
class HeadingAxis:
    """Outcome of :func:`detect_heading_axis`.

    Attributes:
        k: heading axis index (``AXES[k]``).
        reason: how it was decided (one sentence, for messages).
        motion: (4,) moving tracks voting for +x, +y, -x, -y (one vote per track).
        shape: (2,) elongated vehicle tracks longer along local x, along local y.
        warning: set when the file's evidence is missing, ambiguous or contradicts the
            source's documented convention.
    """

    k: int
    reason: str
    motion: np.ndarray
    shape: np.ndarray
    warning: Optional[str] = None

    @property
    def axis(self) -> str:
        return AXES[self.k]


def detect_heading_axis(tracks: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray, str]], default: str,
                        source: str) -> HeadingAxis:
    """Decide the heading axis of a file's boxes from their motion and shapes.

    Args:
        tracks: per track ``(frames (n,), obj_to_world (n, 4, 4), sizes (n, 3), category)``
            as written in the file (all frames of the log).
        default: the source's documented axis (``formats.BOX_HEADING_AXIS``), used when the
            file gives no clear answer.
        source: dataset name, for messages.
    Rules: two or more moving tracks agreeing at 75% decide (a contradicting shape vote is
    reported); one moving track decides when the vehicles' shapes agree with it; otherwise
    the shapes choose between the default and the default turned by 90 degrees; with no
    evidence the default stands, with a warning.
    """
    k_default = AXES.index(default)
    motion = np.zeros(4)
    shape = np.zeros(2)
    for frames, o2w, sizes, category in tracks:
        if len(frames) == 0:
            continue
        v = motion_votes(frames, o2w)
        if v.sum() >= 3 and v.max() >= 0.6 * v.sum():
            motion[int(np.argmax(v))] += 1
        if category == "vehicle":
            s = shape_vote(np.median(sizes, axis=0))
            if s is not None:
                shape[s] += 1
    n_m, n_s = motion.sum(), shape.sum()
    k_m = int(np.argmax(motion))
    share_m = motion[k_m] / n_m if n_m else 0.0
    p_s = int(np.argmax(shape))
    shape_ok = n_s >= 3 and shape[p_s] >= 0.8 * n_s
    counts = (f"moving tracks along +x/+y/-x/-y: {motion.astype(int).tolist()}; elongated vehicles "
              f"longer along x/y: {shape.astype(int).tolist()}")
    convention = f"the reference's {source} boxes have their heading along local {default}"

    if n_m >= 2 and share_m >= 0.75:
        k, reason = k_m, f"motion of {int(motion[k_m])} of {int(n_m)} moving tracks"
        warning = None
        if shape_ok and p_s != k % 2:
            warning = (f"box motion says the heading is local {AXES[k]} but vehicle shapes say it lies along "
                       f"local {'xy'[p_s]} ({counts}); following the motion")
        elif k != k_default:
            warning = (f"boxes move along local {AXES[k]} ({counts}), but {convention}; following the motion "
                       f"(set box_heading_axis to override)")
        return HeadingAxis(k, reason, motion, shape, warning)
    if n_m >= 1 and share_m >= 0.75 and shape_ok and p_s == k_m % 2:
        return HeadingAxis(k_m, "motion of one track, confirmed by vehicle shapes", motion, shape,
                           None if k_m == k_default else f"boxes move along local {AXES[k_m]} ({counts}), but "
                           f"{convention}; following the motion (set box_heading_axis to override)")
    if shape_ok:
        if p_s == k_default % 2:
            return HeadingAxis(k_default, f"vehicle shapes agree with {convention}", motion, shape)
        k = p_s  # +x or +y: the sign cannot be told from shapes
        return HeadingAxis(k, "vehicle shapes", motion, shape,
                           f"ambiguous box axes: vehicle shapes put the heading along local {'xy'[p_s]} "
                           f"({counts}), unlike {convention}, and no clear motion gives its sign; assuming "
                           f"{AXES[k]} (set box_heading_axis to override)")
    return HeadingAxis(k_default, f"{convention} (assumed)", motion, shape,
                       f"cannot confirm the box heading axis from the file ({counts}); assuming {convention} "
                       f"(set box_heading_axis to override)")
