"""omnire export: standard 3DGS PLY files of a reconstructed scene (see README.md)."""
from omnire_export.compose import Part, Pose, compose, scene_parts
from omnire_export.export import export, export_per_node, export_scene
from omnire_export.loading import load_reconstruction
from omnire_export.ply import PLY_PROPERTIES, PlyStreamWriter, pack_rows

__all__ = ["PLY_PROPERTIES", "Part", "PlyStreamWriter", "Pose", "compose", "export", "export_per_node",
           "export_scene", "load_reconstruction", "pack_rows", "scene_parts"]
