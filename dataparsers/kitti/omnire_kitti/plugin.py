"""Entry point of the ``omnire-dataparser-kitti`` distribution: the ``kitti`` reader and writer."""
from omnire.api import DataparserSpec, SceneWriterSpec, lazy

SPECS = (
    DataparserSpec("kitti", "KITTI tracking sequence in the release layout (image_02/03, velodyne, calib, oxts, "
                   "label_02)", lazy("omnire_kitti.dataparser:KittiConfig")),
    SceneWriterSpec("kitti", "KITTI tracking layout (training/, sequence 0000; rectified image_02, velodyne, oxts, "
                    "label_02)", lazy("omnire_kitti.writer:write_scene")),
)
