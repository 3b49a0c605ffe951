"""RealityAvatar: animatable 3D Gaussian avatars of people in loose clothing from multi-view video."""

__version__ = "0.1.0"
