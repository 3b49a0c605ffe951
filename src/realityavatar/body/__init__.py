"""Body models behind one interface: the mannequin-x mannequin (default) and SMPL (user-provided files)."""

from __future__ import annotations

from realityavatar.body.base import (
    NUM_JOINTS,
    SMPL_JOINT_NAMES,
    SMPL_PARENTS,
    BodyModel,
    canonical_pose,
    rh_th_to_smpl,
)
from realityavatar.body.mannequin import MannequinBody

BODIES = ("mannequin", "smpl")


def build_body(name: str = "mannequin", **kw) -> BodyModel:
    """Build a body model by name: "mannequin" (default, ships with mannequin-x) or "smpl" (needs user model files)."""
    if name == "mannequin":
        return MannequinBody(**kw)
    if name == "smpl":
        from realityavatar.body.smpl import (
            SMPLBody,  # lazy: pulls in smplx and needs the user's model directory
        )

        return SMPLBody(**kw)
    raise ValueError(f"body: unknown body model {name!r}; expected one of {BODIES}")


__all__ = [
    "BODIES", "NUM_JOINTS", "SMPL_JOINT_NAMES", "SMPL_PARENTS", "BodyModel", "MannequinBody", "build_body",
    "canonical_pose", "rh_th_to_smpl",
]
