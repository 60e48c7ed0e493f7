"""Entry point of the ``omnire-dataparser-nuplan`` distribution: the ``nuplan`` reader and writer."""
from omnire.api import DataparserSpec, SceneWriterSpec, lazy

SPECS = (
    DataparserSpec("nuplan", "nuPlan log as distributed (SQLite <log>.db + sensor_blobs: 8 cameras, merged LiDAR), "
                   "10 Hz frames on the LiDAR clock", lazy("omnire_nuplan.dataparser:NuPlanConfig")),
    SceneWriterSpec("nuplan", "nuPlan log layout (splits/mini/<log>.db, sensor_blobs/; 20 Hz lidar_pc, 10 Hz images)",
                    lazy("omnire_nuplan.writer:write_scene")),
)
