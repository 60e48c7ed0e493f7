from omnire.api import NodeTypeSpec, hookimpl


@hookimpl
def omnire_register_node_types(registry) -> None:
    from omnire_sky.node import SkyConfig

    registry.register(NodeTypeSpec("sky", "learnable environment map composited under the Gaussians", SkyConfig))
