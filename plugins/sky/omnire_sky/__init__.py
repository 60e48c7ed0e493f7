from omnire_sky.node import SkyConfig, SkyNode, equirect_coordinates

__all__ = ["SkyConfig", "SkyNode", "equirect_coordinates"]
