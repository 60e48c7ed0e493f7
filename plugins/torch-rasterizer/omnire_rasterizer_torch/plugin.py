from omnire.api import RasterizerSpec, hookimpl


def _available(device) -> tuple[bool, str]:
    return True, "pure PyTorch, runs on any device"


@hookimpl
def omnire_register_rasterizers(registry) -> None:
    from omnire_rasterizer_torch.rasterizer import TorchRasterizer

    registry.register(
        RasterizerSpec(
            name="torch",
            description="reference tile-based rasterizer in pure PyTorch (autograd); slow, any device",
            factory=TorchRasterizer,
            available=_available,
            priority=0,
        )
    )
