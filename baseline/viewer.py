"""``pgs view``: a web viewer of a decoded model (viser + nerfview, as gsplat's example viewer).

A Scaffold-GS model is view-dependent (which Gaussians are drawn, their opacity, colour, scale
and rotation depend on the camera), so no PLY viewer shows what the codec decodes. Here every
frame the browser asks for is rendered by the toolkit itself, through the same path as
``pgs render`` (:meth:`baseline.run.Renderable.render`): the decoded ``.pgs`` file (baked where
that is faster, a feature provider's decoded-model cache on), or a run folder's coded state. nerfview serves the
frames and lowers their resolution while the camera moves, from the rays per second it
measures (on the CPU that is a few tens of pixels high); a still camera gets a full frame, up
to the largest training image. The training and test cameras are drawn as frustums (grey /
orange).

Needs the ``viewer`` extra (``pip install -e .[viewer]``: viser, nerfview and what nerfview
imports).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from baseline.camera import Camera

VIEWER_MISSING = ("pgs view needs the viewer extra: pip install -e .[viewer] (viser, nerfview, "
                  "splines, imageio, jaxtyping)")
TRAIN_COLOR = (140, 140, 140)
TEST_COLOR = (255, 140, 0)


def _modules():
    try:
        import nerfview
        import viser
    except ImportError:
        raise ValueError(VIEWER_MISSING) from None
    return viser, nerfview


def camera_to_world(cam: Camera) -> np.ndarray:
    """[4, 4] float64 camera-to-world matrix of ``cam`` (OpenCV axes, as viser's cameras)."""
    return np.linalg.inv(cam.viewmat.detach().cpu().double().numpy())


def camera_state_of(cam: Camera):
    """The nerfview camera state that looks through ``cam``: its pose, vertical field of view
    and aspect (a symmetric pinhole, as the browser's camera is)."""
    _, nerfview = _modules()
    return nerfview.CameraState(fov=2.0 * math.atan(cam.height / (2.0 * cam.fy)),
                                aspect=cam.width / cam.height, c2w=camera_to_world(cam))


def camera_from_state(state, width: int, height: int, near: float = 0.2) -> Camera:
    """The toolkit's :class:`Camera` for a nerfview camera state rendered at ``width`` x
    ``height``: intrinsics from its vertical field of view (nerfview's ``get_K``), the world-to-
    camera matrix the inverse of its pose, inverted in float64."""
    K = state.get_K((width, height))
    w2c = np.linalg.inv(np.asarray(state.c2w, dtype=np.float64))
    return Camera(viewmat=torch.from_numpy(w2c).float(), fx=float(K[0, 0]), fy=float(K[1, 1]),
                  cx=float(K[0, 2]), cy=float(K[1, 2]), width=int(width), height=int(height),
                  near=near, name="viewer")


class ModelViewer:
    """A viser server showing one model: :meth:`render` is nerfview's render callback.

    ``renderable``: a :class:`baseline.run.Renderable` (a run folder or a decoded ``.pgs``
    file with its scene). Call :meth:`start` to serve it on ``host:port``."""

    def __init__(self, renderable, host: str = "0.0.0.0", port: int = 8080):
        self.r = renderable
        self.host, self.port = host, port
        self.server = None
        self.viewer = None
        cams = renderable.scene.train_cameras + renderable.scene.test_cameras
        self.near = cams[0].near if cams else 0.2
        self.max_res = max((max(c.width, c.height) for c in cams), default=800)

    @torch.no_grad()
    def render(self, camera_state, size) -> np.ndarray:
        """One frame [H, W, 3] uint8 for nerfview: ``size`` is nerfview's render-tab state
        (``viewer_width``, ``viewer_height``) or a ``(width, height)`` pair (its older API)."""
        from baseline.eval.metrics import to_uint8

        if hasattr(size, "viewer_width"):
            w, h = size.viewer_width, size.viewer_height
        else:
            w, h = size
        cam = camera_from_state(camera_state, int(w), int(h), self.near)
        return to_uint8(self.r.render(cam))

    def start(self) -> str:
        """Start the server (in its own threads) and return its URL."""
        viser, nerfview = _modules()
        import viser.transforms as vt

        self.server = viser.ViserServer(host=self.host, port=self.port, verbose=False)
        self.port = self.server.get_port()
        scene = self.r.scene
        cams = scene.train_cameras + scene.test_cameras
        c2w = [camera_to_world(c) for c in cams]
        centers = np.array([m[:3, 3] for m in c2w]) if cams else np.zeros((1, 3))
        extent = float(np.linalg.norm(centers - centers.mean(0), axis=1).max()) if cams else 1.0
        scale = 0.05 * max(extent, 1e-3)       # frustums a twentieth of the camera spread
        for split, group, color in (("train", scene.train_cameras, TRAIN_COLOR),
                                    ("test", scene.test_cameras, TEST_COLOR)):
            for i, c in enumerate(group):
                m = camera_to_world(c)
                self.server.scene.add_camera_frustum(
                    f"/cameras/{split}/{i:04d}", fov=2.0 * math.atan(c.height / (2.0 * c.fy)),
                    aspect=c.width / c.height, scale=scale, thickness=0.02 * scale,
                    color=color, wxyz=vt.SO3.from_matrix(m[:3, :3]).wxyz, position=m[:3, 3])
        if cams:
            # the scene's up: the mean of the cameras' up vectors (OpenCV: -y)
            up = -np.mean([m[:3, 1] for m in c2w], axis=0)
            up = up / max(np.linalg.norm(up), 1e-12)
            self.server.scene.set_up_direction(tuple(float(x) for x in up))
            # start just behind the first training camera, looking where it looks
            first = c2w[0]
            eye = first[:3, 3] - first[:3, 2] * 0.1 * max(extent, 1e-3)
            self.server.initial_camera.position = tuple(float(x) for x in eye)
            self.server.initial_camera.look_at = tuple(
                float(x) for x in first[:3, 3] + first[:3, 2] * max(extent, 1e-3))
            self.server.initial_camera.up = tuple(float(x) for x in up)
        self.viewer = nerfview.Viewer(server=self.server, render_fn=self.render,
                                      mode="rendering")
        # a still frame at most the largest training image (its detail ends there); nerfview
        # renders smaller ones while the camera moves
        self.viewer.render_tab_state.viewer_res = self.max_res
        slider = getattr(self.viewer, "_rendering_tab_handles", {}).get("viewer_res_slider")
        if slider is not None:
            slider.value = self.max_res
        return self.url

    @property
    def url(self) -> str:
        shown = "localhost" if self.host in ("0.0.0.0", "127.0.0.1", "::") else self.host
        return f"http://{shown}:{self.port}"

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()
            self.server = None


def serve(target: str | Path, scene: str | None = None, host: str = "0.0.0.0",
          port: int = 8080, device: str | None = None) -> ModelViewer:
    """Load ``target`` (a ``.pgs`` file or a run folder) and start its viewer."""
    from baseline.run import Renderable

    _modules()                              # a missing extra: said before anything is loaded
    v = ModelViewer(Renderable(target, scene, device=device), host=host, port=port)
    v.start()
    return v
