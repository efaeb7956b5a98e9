"""Scene data: COLMAP / Blender loaders, undistortion, cached images, synthetic scenes."""
from .errors import SceneError
from .scene import Scene, cameras_extent, load_scene

__all__ = ["Scene", "SceneError", "cameras_extent", "load_scene"]
