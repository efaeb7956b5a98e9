"""Scene data: COLMAP / Blender loaders, undistortion, cached images, synthetic scenes."""
from .errors import SceneError
from .scene import Scene, ViewSource, cameras_extent, load_scene

__all__ = ["Scene", "SceneError", "ViewSource", "cameras_extent", "load_scene"]
