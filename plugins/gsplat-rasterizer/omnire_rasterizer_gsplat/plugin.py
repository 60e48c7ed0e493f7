"""Entry point (``omnire`` group, name ``gsplat``): registers the gsplat CUDA rasterizer."""
from omnire.api import RasterizerSpec, lazy

from omnire_rasterizer_gsplat import available

SPECS = (RasterizerSpec(
    name="gsplat", description="gsplat CUDA rasterizer (needs a GPU and `pip install omnire-rasterizer-gsplat[cuda]`)",
    factory=lazy("omnire_rasterizer_gsplat.rasterizer:GsplatRasterizer"), available=available, priority=100,
    capabilities=frozenset(),  # rasterize only: the runtime concatenates and renders through it
),)
