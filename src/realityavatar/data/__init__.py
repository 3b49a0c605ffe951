"""Scenes and datasets: the synthetic loose-clothing generator, readers (I3D-Human, ZJU-MoCap), the DataModule."""
