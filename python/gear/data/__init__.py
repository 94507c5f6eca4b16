"""Scenes on disk (docs/scenes.md): load and validate every layout, write the ArtGS/GEAR one."""

from gear.data.load import load_scene, validate_scene
from gear.data.scene import GroundTruth, GtJoint, Scene, SceneError, View
from gear.data.write import write_scene

__all__ = [
    "GroundTruth",
    "GtJoint",
    "Scene",
    "SceneError",
    "View",
    "load_scene",
    "validate_scene",
    "write_scene",
]
