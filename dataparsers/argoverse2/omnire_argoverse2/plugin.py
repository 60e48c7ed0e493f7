"""Entry point of the ``omnire-dataparser-argoverse2`` distribution: the ``argoverse2`` reader and writer."""
from omnire.api import DataparserSpec, SceneWriterSpec, lazy

SPECS = (
    DataparserSpec("argoverse2", "Argoverse 2 sensor log in AV2's own layout (feather files through pyarrow: ring "
                   "cameras, LiDAR, cuboids)", lazy("omnire_argoverse2.dataparser:Argoverse2Config")),
    SceneWriterSpec("argoverse2", "a synthetic scene as an AV2 sensor log (feather files in AV2's schema, "
                    "ring-camera jpgs)", lazy("omnire_argoverse2.writer:write_scene")),
)
