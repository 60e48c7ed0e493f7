from omnire.api import MethodSpec, NodeTypeSpec, hookimpl, usable_track


def accepts(track, scene) -> bool:
    """Vehicles with a usable box (the core keeps actors training never sees in the background)."""
    return usable_track(track)


@hookimpl
def omnire_register_node_types(registry) -> None:
    from omnire_rigid.node import RigidConfig

    registry.register(NodeTypeSpec("rigid", "rigid actors in box-local space with per-frame box poses (refined)",
                                   RigidConfig, categories=frozenset({"vehicle"}), priority=10, accepts=accepts))


def streetgs_method():
    """StreetGS as the OmniRe paper reimplements it: background + rigid vehicles + sky."""
    from omnire.api import BackgroundConfig, MethodConfig
    from omnire_rigid.node import RigidConfig
    from omnire_sky.node import SkyConfig

    return MethodConfig(
        nodes={"background": BackgroundConfig(), "rigid": RigidConfig(), "sky": SkyConfig()},
        loss_weights={"l1": 0.8, "dssim": 0.2, "depth": 0.1, "opacity": 0.05},
        dynamic_pixel_weight=5.0,
    )


@hookimpl
def omnire_register_methods(registry) -> None:
    registry.register(MethodSpec("streetgs", "StreetGS: background + rigid vehicles (box refinement) + sky",
                                 streetgs_method))
