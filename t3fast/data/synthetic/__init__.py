"""Procedural driving towns at Occ3D geometry (see ``scene`` for the pipeline)."""

from t3fast.data.synthetic.dataset import SyntheticDriving, SyntheticFrames, SyntheticScenes, scene_seed
from t3fast.data.synthetic.scene import SyntheticScene, generate_scene

__all__ = ["SyntheticDriving", "SyntheticFrames", "SyntheticScene", "SyntheticScenes", "generate_scene", "scene_seed"]
