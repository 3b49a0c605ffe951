"""The synthetic loose-clothing scene generator: motions, MuJoCo garments, ray-cast ground truth, I3D-Human layout."""

from realityavatar.data.synthetic.presets import FEATURED, PRESETS, SEQUENCES
from realityavatar.data.synthetic.scene import build_scene, default_root, resolve_params, scene_paths

__all__ = ["FEATURED", "PRESETS", "SEQUENCES", "build_scene", "default_root", "resolve_params", "scene_paths"]
