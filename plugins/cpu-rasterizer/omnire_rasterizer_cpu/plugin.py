"""Entry point (``omnire`` group, name ``cpu``): registers the native CPU rasterizer."""
from omnire.api import RasterizerSpec, hookimpl

from omnire_rasterizer_cpu import available


def _factory(**kwargs):
    from omnire_rasterizer_cpu.rasterizer import CpuRasterizer

    return CpuRasterizer(**kwargs)


@hookimpl
def omnire_register_rasterizers(registry) -> None:
    registry.register(
        RasterizerSpec(
            name="cpu",
            description="native C++/OpenMP AVX2 tile rasterizer with hand-written backward (CPU); "
            "kwargs: num_threads",
            factory=_factory,
            available=available,
            priority=50,
        )
    )
