"""Entry point of the ``omnire-dataparser-nuscenes`` distribution: the ``nuscenes`` reader and writer."""
from omnire.api import DataparserSpec, SceneWriterSpec, lazy

SPECS = (
    DataparserSpec("nuscenes", "nuScenes scene in the release layout (v1.0-* JSON tables, samples/, sweeps/), "
                   "10 Hz frames on the LiDAR clock", lazy("omnire_nuscenes.dataparser:NuScenesConfig")),
    SceneWriterSpec("nuscenes", "nuScenes release layout (v1.0-mini tables, samples/, sweeps/; 2 Hz keyframes)",
                    lazy("omnire_nuscenes.writer:write_scene")),
)
