"""Bad nuPlan input through the real CLI (``omnire train ... nuplan``): each case must end with
exit 2 and one line naming the file (and table / column), no traceback, inputs unchanged
(tests/hostile.py, surface "nuplan")."""
from __future__ import annotations

import os
import pickle
import shutil
import sqlite3
from pathlib import Path

import pytest

from hostile import run_case
from omnire_nuplan.pointcloud import parse_pcd, write_pcd
from omnire_nuplan.writer import LOG, blobs_path, database_path, load_source, write_nuplan

SMALL = ["--scale", "1", "--trainer.max-steps", "1", "--trainer.no-progress", "--method.rasterizer", "torch"]


class _Evil:
    def __reduce__(self):
        return (os.system, ("touch /tmp/omnire-pwned",))


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    from omnire_synthetic.generate import SynthOptions, generate

    root = tmp_path_factory.mktemp("nuplan_hostile")
    generate(root / "processed", "urban", SynthOptions(frames=3, width=32, height=24, num_cameras=2, lidar_beams=8,
                                                       lidar_azimuth_step_deg=2.0, write_depth=False))
    write_nuplan(load_source(root / "processed"), root / "log")
    return root / "log"


def sql(db: Path, *statements, args=()) -> None:
    conn = sqlite3.connect(db)
    try:
        for s in statements:
            conn.execute(s, args)
        conn.commit()
    finally:
        conn.close()


def first_blob(root: Path, folder: str) -> Path:
    return sorted((blobs_path(root) / LOG / folder).iterdir())[0]


# Each case breaks a copy of the log and returns the text the one-line error must contain.
def _missing_db(root):
    database_path(root).unlink()
    return "holds 0 .db files"


def _garbage_db(root):
    database_path(root).write_bytes(b"this is not a database at all " * 200)
    return f"{database_path(root)}: not a readable SQLite database"


def _truncated_db(root):
    db = database_path(root)
    db.write_bytes(db.read_bytes()[:6000])
    return str(db)


def _pickle_bomb() -> bytes:
    level = [1.0]
    for _ in range(12):  # 100**12 numbers if expanded; a few kB pickled (shared references)
        level = [level] * 100
    return pickle.dumps(level)


SQL_CASES = {  # case: (statement on the database, its argument or None, the text the error must contain)
    "missing table": ("DROP TABLE lidar_box", None, "no table lidar_box"),
    "missing column": ("ALTER TABLE camera RENAME COLUMN intrinsic TO k", None,
                       "table camera lacks column(s) intrinsic"),
    "text timestamp": ("UPDATE lidar_pc SET timestamp = 'soon' WHERE rowid = 2", None,
                       "column timestamp = 'soon'; expected an INTEGER"),
    "text coordinate": ("UPDATE ego_pose SET x = 'east'", None, "column x = 'east'; expected a finite number"),
    "number as foreign key": ("UPDATE image SET ego_pose_token = 5", None,
                              "column ego_pose_token = 5; expected a token"),
    "dangling track": ("UPDATE lidar_box SET track_token = x'0000000000000000' WHERE rowid = 1", None,
                       "column track_token = 0000000000000000 names no row of table track"),
    "malicious pickle": ("UPDATE camera SET translation = ?", pickle.dumps(_Evil()), "refers to posix.system"),
    "short translation": ("UPDATE camera SET translation = ?", pickle.dumps([1.0, 2.0]),
                          "column translation unpickles to a list of 2 items; expected a pickled list of 3 finite"),
    "pickle bomb": ("UPDATE camera SET intrinsic = ?", _pickle_bomb(),
                    "column intrinsic unpickles to a list of 100 items; expected a pickled list of 3x3"),
    "float in a pickle cell": ("UPDATE lidar SET rotation = 1.5", None,
                               "column rotation = 1.5; expected a pickled list of 4"),
    "not a unit quaternion": ("UPDATE ego_pose SET qw = 2.0", None, "is not a unit quaternion"),
    "negative box size": ("UPDATE lidar_box SET length = -4.0 WHERE rowid = 1", None,
                          "column length = -4.0; expected a positive size"),
    "no camera": ("DELETE FROM camera", None, "the log has no camera"),
    "no images": ("DELETE FROM image", None, "the log has no image"),
    "no lidar": ("DELETE FROM lidar_pc", None, "table lidar_pc has no rows: the log has no LiDAR"),
    "wrong image size": ("UPDATE camera SET width = 40", None, "image is 32x24, but table camera row"),
}


def _sql_case(statement: str, arg, needle: str):
    def corrupt(root):
        sql(database_path(root), statement, args=() if arg is None else (arg,))
        return needle
    return corrupt


def _missing_image(root):
    path = first_blob(root, "CAM_F0")
    path.unlink()
    return f"{path}: missing image blob of CAM_F0"


def _no_lidar_blobs(root):
    shutil.rmtree(blobs_path(root) / LOG / "MergedPointCloud")
    return "none of the 3 LiDAR blobs"


def _truncated_pcd(root):
    path = first_blob(root, "MergedPointCloud")
    path.write_bytes(path.read_bytes()[:400])
    return f"{path}: .pcd POINTS"


def _not_a_pcd(root):
    path = first_blob(root, "MergedPointCloud")
    path.write_bytes(bytes(range(256)) * 4)
    return str(path)


def _bad_ring(value: float):
    def corrupt(root):
        path = first_blob(root, "MergedPointCloud")
        rec = parse_pcd(path.read_bytes(), path).copy()
        rec["ring"][5] = value
        path.write_bytes(write_pcd(rec))
        return f"{path}: field ring must hold whole numbers in 0..32767 (found {value:g} at point 5"
    return corrupt


def _no_sensor_blobs(root):
    shutil.rmtree(blobs_path(root))
    return "no sensor_blobs folder beside the log database"


def _two_databases(root):
    shutil.copy(database_path(root), database_path(root).with_name("other.db"))
    return "holds 2 .db files"


CORRUPT = {
    "missing database": _missing_db, "garbage database": _garbage_db, "truncated database": _truncated_db,
    "missing image blob": _missing_image, "no lidar blobs": _no_lidar_blobs,
    "truncated pcd": _truncated_pcd, "not a pcd": _not_a_pcd, "no sensor blobs": _no_sensor_blobs,
    "negative ring": _bad_ring(-1.0), "fractional ring": _bad_ring(2.5),
    "two databases": _two_databases,
    **{case: _sql_case(*spec) for case, spec in SQL_CASES.items()},
}


@pytest.mark.parametrize("case", sorted(CORRUPT))
def test_corrupt_log(case, log, tmp_path, capsys):
    root = tmp_path / "log"
    shutil.copytree(log, root)
    needle = CORRUPT[case](root)
    run_case(case, ["train", "3dgs", "nuplan", "--data", str(root), *SMALL,
                    "--trainer.output-dir", str(tmp_path / "out")], capsys, [root], needles=(needle,), surface="nuplan")
    assert not Path("/tmp/omnire-pwned").exists()
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.pt"))


@pytest.mark.parametrize("flags, needle", [
    (["--cameras", "CAM_X"], "are not nuPlan cameras"),
    (["--frame-step", "0"], "frame_step: 0, expected >= 1"),
    (["--start-frame", "5"], "select nothing of the 3 frames"),
    (["--sensor-blobs", "/nonexistent/blobs"], "/nonexistent/blobs: --sensor-blobs folder does not exist"),
    (["--max-camera-offset", "0.01", "--frame-step", "1"], "--max-camera-offset sets the tolerance"),
])
def test_bad_options(flags, needle, log, tmp_path, capsys):
    run_case(f"option {' '.join(flags)}", ["train", "3dgs", "nuplan", "--data", str(log), *SMALL, *flags,
                                           "--trainer.output-dir", str(tmp_path / "out")],
             capsys, [log], needles=(needle,), surface="nuplan")
