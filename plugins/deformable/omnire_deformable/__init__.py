from omnire_deformable.node import DeformableConfig, DeformableNode

__all__ = ["DeformableConfig", "DeformableNode"]
