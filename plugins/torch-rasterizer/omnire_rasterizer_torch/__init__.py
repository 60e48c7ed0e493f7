from omnire_rasterizer_torch.projection import project_gaussians
from omnire_rasterizer_torch.rasterizer import TorchRasterizer

__all__ = ["TorchRasterizer", "project_gaussians"]
