"""Entry point (``omnire`` group, name ``gsplat``): registers the gsplat CUDA rasterizer."""
from omnire.api import RasterizerSpec, hookimpl

from omnire_rasterizer_gsplat import available


def _factory(**kwargs):
    from omnire_rasterizer_gsplat.rasterizer import GsplatRasterizer

    return GsplatRasterizer(**kwargs)


@hookimpl
def omnire_register_rasterizers(registry) -> None:
    registry.register(
        RasterizerSpec(
            name="gsplat",
            description="gsplat CUDA rasterizer (needs a GPU and `pip install omnire-rasterizer-gsplat[cuda]`)",
            factory=_factory,
            available=available,
            priority=100,
            capabilities=frozenset(),  # rasterize only: the runtime concatenates and renders through it
        )
    )
