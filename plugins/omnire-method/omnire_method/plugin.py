"""The OmniRe method (ICLR 2025): a Gaussian scene graph with every actor type.

Ablations of the paper, as flags:
- no SMPL nodes:            --method.disable smpl        (pedestrians go to the deformable node)
- no deformable nodes:      --method.disable deformable  (their actors stay in the background)
- no body-pose refinement:  --method.nodes.smpl.no-refine-poses
- no box refinement:        --method.nodes.rigid.no-refine-boxes (and .smpl / .deformable likewise)
"""
from omnire.hookspecs import hookimpl
from omnire.registry import MethodSpec


def omnire_method():
    from omnire.method import MethodConfig
    from omnire.nodes.background import BackgroundConfig
    from omnire_deformable.node import DeformableConfig
    from omnire_rigid.node import RigidConfig
    from omnire_sky.node import SkyConfig
    from omnire_smpl.node import SMPLConfig

    return MethodConfig(
        nodes={"background": BackgroundConfig(), "rigid": RigidConfig(), "smpl": SMPLConfig(),
               "deformable": DeformableConfig(), "sky": SkyConfig()},
        loss_weights={"l1": 0.8, "dssim": 0.2, "depth": 0.1, "opacity": 0.05},
        regularization_weights={"pose_smoothness": 0.01, "deformable_box": 0.1},
        dynamic_pixel_weight=5.0,
    )


@hookimpl
def omnire_register_methods(registry) -> None:
    registry.register(MethodSpec("omnire", "OmniRe: sky + background + rigid + SMPL + deformable actors", omnire_method))
