"""omnire plugin: registers the ``processed`` dataparser."""
from omnire.api import DataparserSpec, lazy

SPECS = (DataparserSpec("processed", "Scenes in the reference implementation's processed format (Waymo, nuScenes, "
                        "NuPlan, Argoverse2, PandaSet, KITTI), converted to omnire conventions",
                        lazy("omnire_processed.reader:ProcessedDataparserConfig")),)
