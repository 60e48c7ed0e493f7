"""Entry point (``omnire`` group, name ``torch``): registers the reference PyTorch rasterizer."""
from omnire.api import RasterizerSpec

from omnire_rasterizer_torch.rasterizer import TorchRasterizer


def _available(device) -> tuple[bool, str]:
    return True, "pure PyTorch, runs on any device"


SPECS = (RasterizerSpec(name="torch", description="reference tile-based rasterizer in pure PyTorch (autograd); slow, "
                        "any device", factory=TorchRasterizer, available=_available, priority=0,
                        capabilities=frozenset({"lidar"})),)
