from crowdbench.data.scenes import SCENES, Scene, load_scene, scene_names

__all__ = ["SCENES", "Scene", "load_scene", "scene_names"]
