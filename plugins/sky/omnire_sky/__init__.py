from omnire_sky.node import SkyConfig, SkyNode, view_directions

__all__ = ["SkyConfig", "SkyNode", "view_directions"]
