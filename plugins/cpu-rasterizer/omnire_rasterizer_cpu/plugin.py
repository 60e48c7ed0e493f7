"""Entry point (``omnire`` group, name ``cpu``): registers the native CPU rasterizer."""
from omnire.api import RasterizerSpec, hookimpl

from omnire_rasterizer_cpu import available


@hookimpl
def omnire_register_rasterizers(registry) -> None:
    # the class itself (importing it builds nothing) so its declared capabilities are checked here
    from omnire_rasterizer_cpu.rasterizer import CpuRasterizer

    registry.register(
        RasterizerSpec(
            name="cpu",
            description="native C++/OpenMP AVX2 tile rasterizer with hand-written backward, camera and LiDAR (CPU); "
            "kwargs: num_threads",
            factory=CpuRasterizer,
            available=available,
            priority=50,
            capabilities=frozenset({"inference", "fused_training", "ssim", "lidar"}),
        )
    )
