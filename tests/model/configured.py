"""Components built from their config files, as a run builds them: the YAML holds every default, a test changes
only the arguments it is about."""

from __future__ import annotations

from hydra.errors import InstantiationException
from hydra.utils import instantiate

from realityavatar.config import compose


def component(group: str, option: str | None = None, *overrides: str, **kwargs):
    """The component of `group` (its option `option`, default: train.yaml's) with config `overrides`
    (`"skinning.voxel_size=0.04"`) and constructor arguments `kwargs` replacing the file's. A constructor's own
    error (ValueError naming the key) is raised as the class raised it, not wrapped by hydra."""
    cfg = compose([*([f"{group}={option}"] if option else []), *overrides])
    try:
        return instantiate(cfg[group], **kwargs)
    except InstantiationException as e:
        raise (e.__cause__ or e) from None
