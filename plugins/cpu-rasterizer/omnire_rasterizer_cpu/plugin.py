"""Entry point (``omnire`` group, name ``cpu``): registers the native CPU rasterizer and its two
C++ extensions."""
from omnire.api import NativeExtensionSpec, RasterizerSpec, hookimpl, lazy

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


@hookimpl
def omnire_register_native_extensions(registry) -> None:
    registry.register(NativeExtensionSpec("omnire_raster_cpu", "the cpu rasterizer's camera kernels and SSIM",
                                          lazy("omnire_rasterizer_cpu._build:load_extension")))
    registry.register(NativeExtensionSpec("omnire_lidar_cpu", "the cpu rasterizer's LiDAR compositing",
                                          lazy("omnire_rasterizer_cpu._build:load_lidar_extension")))
