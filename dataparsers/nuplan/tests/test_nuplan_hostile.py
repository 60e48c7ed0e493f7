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


def _missing_table(root):
    sql(database_path(root), "DROP TABLE lidar_box")
    return "no table lidar_box"


def _missing_column(root):
    sql(database_path(root), "ALTER TABLE camera RENAME COLUMN intrinsic TO k")
    return "table camera lacks column(s) intrinsic"


def _text_timestamp(root):
    sql(database_path(root), "UPDATE lidar_pc SET timestamp = 'soon' WHERE rowid = 2")
    return "column timestamp = 'soon'; expected an INTEGER"


def _text_coordinate(root):
    sql(database_path(root), "UPDATE ego_pose SET x = 'east'")
    return "table ego_pose row"


def _number_foreign_key(root):
    sql(database_path(root), "UPDATE image SET ego_pose_token = 5")
    return "column ego_pose_token = 5; expected a token"


def _dangling_track(root):
    sql(database_path(root), "UPDATE lidar_box SET track_token = x'0000000000000000' WHERE rowid = 1")
    return "column track_token = 0000000000000000 names no row of table track"


def _evil_pickle(root):
    sql(database_path(root), "UPDATE camera SET translation = ?", args=(pickle.dumps(_Evil()),))
    return "refers to posix.system"


def _short_translation(root):
    sql(database_path(root), "UPDATE camera SET translation = ?", args=(pickle.dumps([1.0, 2.0]),))
    return "column translation unpickles to a list of 2 items; expected a pickled list of 3 finite numbers"


def _pickle_bomb(root):
    level = [1.0]
    for _ in range(12):  # 100**12 numbers if expanded; a few kB pickled (shared references)
        level = [level] * 100
    sql(database_path(root), "UPDATE camera SET intrinsic = ?", args=(pickle.dumps(level),))
    return "column intrinsic unpickles to a list of 100 items; expected a pickled list of 3x3"


def _float_in_pickle_cell(root):
    sql(database_path(root), "UPDATE lidar SET rotation = 1.5")
    return "table lidar row"


def _not_unit_quaternion(root):
    sql(database_path(root), "UPDATE ego_pose SET qw = 2.0")
    return "is not a unit quaternion"


def _negative_box(root):
    sql(database_path(root), "UPDATE lidar_box SET length = -4.0 WHERE rowid = 1")
    return "column length = -4.0; expected a positive size"


def _missing_image(root):
    path = first_blob(root, "CAM_F0")
    path.unlink()
    return f"{path}: missing image blob of CAM_F0"


def _wrong_image_size(root):
    sql(database_path(root), "UPDATE camera SET width = 40")
    return "image is 32x24, but table camera row"


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


def _no_camera(root):
    sql(database_path(root), "DELETE FROM camera")
    return "the log has no camera"


def _no_images(root):
    sql(database_path(root), "DELETE FROM image")
    return "the log has no image"


def _no_lidar(root):
    sql(database_path(root), "DELETE FROM lidar_pc")
    return "table lidar_pc has no rows: the log has no LiDAR"


def _no_sensor_blobs(root):
    shutil.rmtree(blobs_path(root))
    return "no sensor_blobs folder beside the log database"


def _two_databases(root):
    shutil.copy(database_path(root), database_path(root).with_name("other.db"))
    return "holds 2 .db files"


CORRUPT = {
    "missing database": _missing_db, "garbage database": _garbage_db, "truncated database": _truncated_db,
    "missing table": _missing_table, "missing column": _missing_column, "text timestamp": _text_timestamp,
    "text coordinate": _text_coordinate, "number as foreign key": _number_foreign_key, "dangling track": _dangling_track,
    "malicious pickle": _evil_pickle, "short translation": _short_translation,
    "float in a pickle cell": _float_in_pickle_cell,
    "pickle bomb": _pickle_bomb, "not a unit quaternion": _not_unit_quaternion,
    "negative box size": _negative_box, "missing image blob": _missing_image, "wrong image size": _wrong_image_size,
    "no lidar blobs": _no_lidar_blobs, "truncated pcd": _truncated_pcd, "not a pcd": _not_a_pcd,
    "no camera": _no_camera, "no images": _no_images, "no lidar": _no_lidar, "no sensor blobs": _no_sensor_blobs,
    "two databases": _two_databases,
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
