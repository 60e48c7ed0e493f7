"""The OmniRe method (ICLR 2025): a Gaussian scene graph with every actor type.

Ablations of the paper, as flags:
- no SMPL nodes:            --method.disable smpl        (pedestrians go to the deformable node)
- no deformable nodes:      --method.disable deformable  (their actors stay in the background)
- no body-pose refinement:  --method.nodes.smpl.no-refine-poses
- no box refinement:        --method.nodes.rigid.no-refine-boxes (and .smpl / .deformable likewise)
"""
from omnire.api import CommandSpec, MethodSpec, lazy


def omnire_method():
    from omnire.api import BackgroundConfig, MethodConfig
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


SPECS = (
    MethodSpec("omnire", "OmniRe: sky + background + rigid + SMPL + deformable actors", omnire_method),
    CommandSpec("bench skip", "cost of what a scene does not need: omnire without humans vs a baseline, actors "
                "absent from the rendered frames", lazy("omnire_method.bench_skip:main")),
)
