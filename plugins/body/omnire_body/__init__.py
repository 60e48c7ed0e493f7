"""Body templates with the SMPL skeleton and numpy linear blend skinning."""
from omnire_body.lbs import LBSOutput, forward_kinematics, lbs
from omnire_body.template import (
    SMPL_JOINT_NAMES,
    SMPL_PARENTS,
    BodyTemplate,
    BodyTemplateError,
    load_anny_template,
    load_smpl_pickle,
    load_template,
)

__all__ = [
    "BodyTemplate", "BodyTemplateError", "LBSOutput", "SMPL_JOINT_NAMES", "SMPL_PARENTS",
    "forward_kinematics", "lbs", "load_anny_template",
    "load_smpl_pickle", "load_template",
]
