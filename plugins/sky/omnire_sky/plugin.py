from omnire.hookspecs import hookimpl
from omnire.registry import NodeTypeSpec


@hookimpl
def omnire_register_node_types(registry) -> None:
    from omnire_sky.node import SkyConfig

    registry.register(NodeTypeSpec("sky", "learnable environment map composited under the Gaussians", SkyConfig))
