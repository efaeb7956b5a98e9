"""A deterministic procedural test scene in COLMAP format, rendered by a small ray tracer.

``make_scene(out_dir)`` writes ``sparse/0/{cameras,images,points3D}.bin`` (via pycolmap) and
``images/view_NNN.png``: a textured ground square with spheres, a rotated box and a capped
cylinder, lit by one directional light with hard shadows plus ambient (Lambert), over a smooth
sky gradient. So the images have smooth regions (shading, sky, flat colours) as well as detail
(procedural textures, silhouettes, shadow edges). Cameras sit on a ring at varying elevation and
look at the centre. The point cloud stands in for SfM: points sampled on surfaces seen by the
views, with their shaded colours, plus position and colour noise.

The ray tracer is vectorized numpy in float64 with 2x2 supersampling per pixel; the same seed
gives byte-identical files. ``texture_detail`` scales texture amplitude (up to 1) and frequency;
0 gives flat colours. Any COLMAP camera model can be rendered (rays come from
``pycolmap.Camera.cam_from_img``), which lets tests build distorted or fisheye captures.
"""
from __future__ import annotations

import json
import math
import os
import secrets
import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from baseline.fileio import write_text_atomic
from baseline.guard import check_output, write_marker

from .images import to_uint8, write_png_atomic

SKY_HORIZON = np.array([0.78, 0.84, 0.92])
SKY_ZENITH = np.array([0.35, 0.52, 0.80])
_EPS = 1e-9


def _norm(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


class _Texture:
    """Sum of a few seeded sinusoids plus a checker, scaled by ``detail``; values in [-1, 1]."""

    def __init__(self, rng: np.random.Generator, detail: float, base_freq: float, dims: int):
        self.amp = 0.45 * min(max(detail, 0.0), 1.0)
        fscale = max(detail, 1e-6) * base_freq
        self.freqs = rng.normal(size=(4, dims)) * fscale
        self.phases = rng.uniform(0, 2 * np.pi, size=4)
        self.weights = np.array([0.35, 0.25, 0.2, 0.2])
        self.checker = fscale * rng.uniform(0.8, 1.2)

    def __call__(self, q: np.ndarray) -> np.ndarray:
        """q: [N, dims] texture coordinates -> [N] modulation factor 1 + amp * pattern."""
        if self.amp == 0.0:
            return np.ones(len(q))
        s = np.sin(q @ self.freqs.T + self.phases) @ self.weights
        chk = np.sign(np.prod(np.sin(q * self.checker * np.pi / 2 + 0.3), axis=1))
        return 1.0 + self.amp * (0.55 * s + 0.45 * chk)


@dataclass
class _Prim:
    color: np.ndarray
    tex: _Texture


class _Ground(_Prim):
    def __init__(self, half, color, tex):
        super().__init__(color, tex)
        self.half = half

    def intersect(self, o, d):
        t = np.where(d[:, 2] < -_EPS, -o[:, 2] / np.minimum(d[:, 2], -_EPS), np.inf)
        p = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
        inside = (np.abs(p[:, 0]) <= self.half) & (np.abs(p[:, 1]) <= self.half)
        return np.where(inside & (t > 1e-6), t, np.inf)

    def surface(self, p):
        n = np.zeros_like(p)
        n[:, 2] = 1.0
        return n, self.color * self.tex(p[:, :2])[:, None]


class _Sphere(_Prim):
    def __init__(self, center, radius, color, tex):
        super().__init__(color, tex)
        self.c, self.r = np.asarray(center, float), float(radius)

    def intersect(self, o, d):
        oc = o - self.c
        b = np.einsum("ij,ij->i", oc, d)
        c = np.einsum("ij,ij->i", oc, oc) - self.r ** 2
        disc = b * b - c
        sq = np.sqrt(np.maximum(disc, 0.0))
        t0, t1 = -b - sq, -b + sq
        t = np.where(t0 > 1e-6, t0, np.where(t1 > 1e-6, t1, np.inf))
        return np.where(disc >= 0, t, np.inf)

    def surface(self, p):
        n = (p - self.c) / self.r
        theta = np.arccos(np.clip(n[:, 2], -1, 1))
        phi = np.arctan2(n[:, 1], n[:, 0])
        q = np.stack([theta * self.r * 2, np.sin(phi) * self.r * 2, np.cos(phi) * self.r * 2], 1)
        return n, self.color * self.tex(q)[:, None]


class _Box(_Prim):
    def __init__(self, center, half, angle, color, tex):
        super().__init__(color, tex)
        self.c, self.h = np.asarray(center, float), np.asarray(half, float)
        ca, sa = math.cos(angle), math.sin(angle)
        self.R = np.array([[ca, -sa, 0], [sa, ca, 0], [0, 0, 1.0]])   # local -> world

    def intersect(self, o, d):
        lo = (o - self.c) @ self.R
        ld = d @ self.R
        inv = 1.0 / np.where(np.abs(ld) < _EPS, _EPS, ld)
        ta, tb = (-self.h - lo) * inv, (self.h - lo) * inv
        tmin = np.minimum(ta, tb).max(axis=1)
        tmax = np.maximum(ta, tb).min(axis=1)
        hit = (tmax >= tmin) & (tmax > 1e-6)
        t = np.where(tmin > 1e-6, tmin, tmax)
        return np.where(hit, t, np.inf)

    def surface(self, p):
        lp = (p - self.c) @ self.R
        r = np.abs(lp) / self.h
        axis = np.argmax(r, axis=1)
        nl = np.zeros_like(lp)
        nl[np.arange(len(lp)), axis] = np.sign(lp[np.arange(len(lp)), axis])
        return nl @ self.R.T, self.color * self.tex(lp)[:, None]


class _Cylinder(_Prim):
    """Vertical cylinder, axis through (cx, cy), from z0 to z0 + height, with a top cap."""

    def __init__(self, cxy, z0, radius, height, color, tex):
        super().__init__(color, tex)
        self.cxy, self.z0, self.r, self.hgt = np.asarray(cxy, float), z0, radius, height

    def intersect(self, o, d):
        oc = o[:, :2] - self.cxy
        a = np.einsum("ij,ij->i", d[:, :2], d[:, :2])
        b = np.einsum("ij,ij->i", oc, d[:, :2])
        c = np.einsum("ij,ij->i", oc, oc) - self.r ** 2
        disc = b * b - a * c
        sq = np.sqrt(np.maximum(disc, 0.0))
        a_ = np.maximum(a, _EPS)
        t_side = np.inf * np.ones(len(o))
        for t in ((-b - sq) / a_, (-b + sq) / a_):
            z = o[:, 2] + t * d[:, 2]
            ok = (disc >= 0) & (a > _EPS) & (t > 1e-6) & (z >= self.z0) & (z <= self.z0 + self.hgt)
            t_side = np.where(ok & (t < t_side), t, t_side)
        ztop = self.z0 + self.hgt
        with np.errstate(divide="ignore", invalid="ignore"):
            tc = (ztop - o[:, 2]) / d[:, 2]
        pc = o[:, :2] + np.nan_to_num(tc, posinf=0, neginf=0)[:, None] * d[:, :2]
        okc = (np.abs(d[:, 2]) > _EPS) & (tc > 1e-6) & (((pc - self.cxy) ** 2).sum(1) <= self.r ** 2)
        return np.minimum(t_side, np.where(okc, tc, np.inf))

    def surface(self, p):
        ztop = self.z0 + self.hgt
        cap = np.abs(p[:, 2] - ztop) < 1e-7 * max(1.0, abs(ztop)) + 1e-9
        rel = p[:, :2] - self.cxy
        n = np.zeros_like(p)
        n[:, :2] = rel / self.r
        n[cap] = [0.0, 0.0, 1.0]
        ang = np.arctan2(rel[:, 1], rel[:, 0])
        q = np.stack([ang * self.r, p[:, 2], np.where(cap, np.hypot(*rel.T), 0.0)], 1)
        return n, self.color * self.tex(q)[:, None]


class World:
    """The procedural scene for one seed: primitives, light and sky."""

    def __init__(self, seed: int = 0, texture_detail: float = 1.0):
        rng = np.random.default_rng(seed)
        j = lambda s=0.1: rng.uniform(-s, s)  # noqa: E731
        tex = lambda f, dims=3: _Texture(rng, texture_detail, f, dims)  # noqa: E731
        col = lambda c: np.clip(np.array(c) + rng.uniform(-0.08, 0.08, 3), 0.05, 0.95)  # noqa: E731
        self.prims = [
            _Ground(3.0, col([0.55, 0.50, 0.42]), tex(4.0, 2)),
            _Sphere([-0.55 + j(), -0.35 + j(), 0.45], 0.45, col([0.80, 0.30, 0.25]), tex(5.0)),
            _Sphere([0.75 + j(), -0.65 + j(), 0.25], 0.25, col([0.25, 0.45, 0.80]), tex(7.0)),
            _Box([0.45 + j(), 0.55 + j(), 0.3], [0.3, 0.25, 0.3], rng.uniform(0, np.pi / 2),
                 col([0.30, 0.70, 0.35]), tex(6.0)),
            _Cylinder([-0.55 + j(), 0.8 + j()], 0.0, 0.22, 0.7, col([0.85, 0.75, 0.30]), tex(6.0)),
        ]
        az, el = rng.uniform(0, 2 * np.pi), rng.uniform(0.6, 1.0)
        self.light = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el),
                               math.sin(el)])
        self.ambient = 0.3
        self.target = np.array([0.0, 0.0, 0.35])

    def trace(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Shade rays. o, d: [N, 3] (d unit). Returns (rgb [N, 3], t [N] (inf: sky), points)."""
        ts = np.stack([p.intersect(o, d) for p in self.prims])       # [P, N]
        which = np.argmin(ts, axis=0)
        t = ts[which, np.arange(len(o))]
        hit = np.isfinite(t)
        pts = o + np.where(hit, t, 0.0)[:, None] * d
        rgb = np.empty((len(o), 3))
        sky = np.clip(d[:, 2], 0.0, 1.0)[:, None]
        rgb[:] = SKY_HORIZON * (1 - sky) + SKY_ZENITH * sky
        normal = np.zeros((len(o), 3))
        albedo = np.zeros((len(o), 3))
        for k, prim in enumerate(self.prims):
            m = hit & (which == k)
            if m.any():
                normal[m], albedo[m] = prim.surface(pts[m])
        if hit.any():
            ph, nh = pts[hit], normal[hit]
            lam = np.clip(nh @ self.light, 0.0, None)
            lit = lam > 0                     # only lit-facing points can be shadowed
            so = ph[lit] + nh[lit] * 1e-6
            sd = np.broadcast_to(self.light, so.shape)
            shadow = np.zeros(len(ph), dtype=bool)
            if lit.any():
                shadow[lit] = np.isfinite(np.stack([p.intersect(so, sd) for p in self.prims]).min(0))
            light = self.ambient + (1 - self.ambient) * lam * np.where(shadow, 0.0, 1.0)
            rgb[hit] = np.clip(albedo[hit] * light[:, None], 0.0, 1.0)
        return rgb, np.where(hit, t, np.inf), pts

    def rays(self, cam: "pycolmap.Camera", w2c: np.ndarray, uv: np.ndarray):
        """World rays (origins, unit directions) through continuous pixel coords uv [N, 2]."""
        xy = np.asarray(cam.cam_from_img(np.ascontiguousarray(uv, dtype=np.float64)))
        dc = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        R, t = w2c[:3, :3], w2c[:3, 3]
        d = _norm(dc @ R)                       # R^T dc, row-wise
        o = np.broadcast_to(-R.T @ t, d.shape)
        return np.ascontiguousarray(o), d

    def render(self, cam: "pycolmap.Camera", w2c: np.ndarray, ss: int = 2) -> np.ndarray:
        """Float64 [H, W, 3] image of a COLMAP camera (any model) at pose w2c (OpenCV)."""
        W, H = int(cam.width), int(cam.height)
        off = (np.arange(ss) + 0.5) / ss
        u = (np.arange(W)[:, None] + off[None, :]).ravel()
        v = (np.arange(H)[:, None] + off[None, :]).ravel()
        uu, vv = np.meshgrid(u, v)                                    # [H*ss, W*ss]
        o, d = self.rays(cam, w2c, np.stack([uu.ravel(), vv.ravel()], 1))
        rgb, _, _ = self.trace(o, d)
        return rgb.reshape(H, ss, W, ss, 3).mean(axis=(1, 3))


def look_at(center: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] OpenCV world-to-camera matrix of a camera at ``center`` looking at ``target``."""
    f = _norm(np.asarray(target, float) - center)
    x = _norm(np.cross(f, np.asarray(up, float)))
    y = np.cross(f, x)
    R = np.stack([x, y, f])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ center
    return w2c


def make_camera(model: str, width: int, height: int, focal: float,
                distortion=(), camera_id: int = 1) -> "pycolmap.Camera":
    """A pycolmap camera of any model with the principal point at the centre."""
    cam = pycolmap.Camera.create_from_model_name(camera_id, model, focal, width, height)
    params = np.asarray(cam.params, dtype=np.float64).copy()
    extra = list(cam.extra_params_idxs())
    if len(distortion) > len(extra):
        raise ValueError(f"{model} takes {len(extra)} distortion parameters, got {len(distortion)}")
    for i, val in zip(extra, distortion):
        params[i] = val
    cam.params = params
    return cam


def make_scene(out_dir: str | os.PathLike, n_views: int = 40, width: int = 160, height: int = 120,
               seed: int = 0, texture_detail: float = 1.0, n_points: int = 3000,
               camera_model: str = "PINHOLE", distortion=(), shared_camera: bool = True,
               fov_deg: float = 55.0, overwrite: bool = False) -> Path:
    """Write a synthetic COLMAP scene and return its folder.

    Args:
        out_dir: folder to create (``sparse/0/`` and ``images/`` inside).
        n_views: number of views on the camera ring (names ``view_000.png`` ...).
        width, height: image size.
        seed: everything random (object layout jitter, colours, textures, light, camera jitter,
            point samples) derives from it; equal seeds give byte-identical files.
        texture_detail: texture amplitude (saturating at 1) and frequency scale; 0 = flat colours.
        n_points: number of points in ``points3D.bin``.
        camera_model, distortion: COLMAP model name and its extra parameters (e.g.
            ``"OPENCV", (k1, k2, p1, p2)``); the images are rendered through that model.
        shared_camera: one camera for all views (else one camera id per view, same parameters).
        fov_deg: horizontal field of view of the pinhole part.
        overwrite: replace a scene of the toolkit written with other arguments.

    Every argument is checked against its range first (:data:`RANGES`: finite, bounded views,
    sizes and points). The output is checked by :func:`baseline.guard.check_output`: a new or
    empty folder, or this function's own scene for the same arguments; with ``overwrite`` any
    scene of the toolkit. The scene is written into a temporary sibling folder and renamed onto
    ``out_dir`` at the end (a replaced scene is removed only then): an error, Ctrl-C or SIGTERM
    during the generation leaves no half scene and the old one as it was.
    """
    params = check_scene_args(n_views=n_views, width=width, height=height, seed=seed,
                              texture_detail=texture_detail, n_points=n_points,
                              camera_model=camera_model, distortion=list(distortion),
                              shared_camera=shared_camera, fov_deg=fov_deg)
    final = Path(out_dir)
    exists = check_output(final, command="make-scene", source=params, folder=True,
                          overwrite=overwrite)
    final.parent.mkdir(parents=True, exist_ok=True)
    tag = secrets.token_hex(4)
    out = final.parent / f".{final.name}.partial-{tag}"
    try:
        with _sigterm_as_interrupt():
            _write_scene(out, n_views, width, height, seed, texture_detail, n_points,
                         camera_model, distortion, shared_camera, fov_deg)
            write_marker(out, "make-scene", params)
            if exists:                              # swap: the old scene goes only now
                old = final.parent / f".{final.name}.old-{tag}"
                os.rename(final, old)
                os.rename(out, final)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.rename(out, final)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise
    return final


# make-scene's arguments: (low, high) like the config's RANGES; sizes bound the run time (the
# ray tracer's cost is views x width x height) and what is written
RANGES = {"n_views": (1, 2000), "width": (1, 4096), "height": (1, 4096),
          "seed": (0, 2 ** 63 - 1), "texture_detail": (0.0, 16.0), "n_points": (1, 10_000_000),
          "fov_deg": (1.0, 170.0)}
MAX_PIXELS = 400_000_000           # views x width x height (the default scene: 768,000)
_FLAGS = {"n_views": "--views", "width": "--width", "height": "--height", "seed": "--seed",
          "texture_detail": "--detail"}


def check_scene_args(**kw) -> dict:
    """``kw`` checked against :data:`RANGES` (integers where integers are meant, numbers
    finite) and :data:`MAX_PIXELS`; returns them as the scene's parameters, or raises
    ``ValueError`` naming the argument."""
    for key, (lo, hi) in RANGES.items():
        v = kw[key]
        name = f"make-scene {_FLAGS[key]} ({key})" if key in _FLAGS else f"make-scene {key}"
        integral = isinstance(lo, int)
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise ValueError(  # noqa: TRY004 - a bad argument: one line, exit 2
                f"{name}: expected {'an integer' if integral else 'a number'}, got {v!r}")
        if not math.isfinite(float(v)):
            raise ValueError(f"{name} must be finite, got {v}")
        if integral and not float(v).is_integer():
            raise ValueError(f"{name}: expected an integer, got {v!r}")
        if not lo <= v <= hi:
            raise ValueError(f"{name} = {v} is out of range [{lo}, {hi}]")
        kw[key] = int(v) if integral else float(v)
    px = kw["n_views"] * kw["width"] * kw["height"]
    if px > MAX_PIXELS:
        raise ValueError(f"make-scene: {kw['n_views']} views of {kw['width']} x {kw['height']} "
                         f"are {px} pixels, more than the {MAX_PIXELS} a synthetic scene may have")
    if any(not math.isfinite(float(x)) for x in kw["distortion"]):
        raise ValueError(f"make-scene distortion must be finite, got {kw['distortion']}")
    return kw


@contextmanager
def _sigterm_as_interrupt():
    """SIGTERM raises KeyboardInterrupt while the block runs (in the main thread), so the
    partial scene is removed as it is on Ctrl-C."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _write_scene(out: Path, n_views, width, height, seed, texture_detail, n_points, camera_model,
                 distortion, shared_camera, fov_deg) -> None:
    rng = np.random.default_rng([seed, 1])
    world = World(seed, texture_detail)
    focal = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "sparse" / "0").mkdir(parents=True, exist_ok=True)

    rec = pycolmap.Reconstruction()
    cams = []
    for k in range(n_views if not shared_camera else 1):
        cam = make_camera(camera_model, width, height, focal, distortion, camera_id=k + 1)
        rec.add_camera_with_trivial_rig(cam)
        cams.append(cam)

    per_view = int(math.ceil(n_points / max(n_views, 1) * 1.6)) + 1
    pts, cols = [], []
    for k in range(n_views):
        az = 2 * np.pi * k / n_views + rng.uniform(-0.05, 0.05)
        el = math.radians(22 + 18 * (0.5 + 0.5 * math.sin(2 * np.pi * 3 * k / n_views)))
        rad = 3.6 + rng.uniform(-0.2, 0.2)
        center = np.array([rad * math.cos(az) * math.cos(el), rad * math.sin(az) * math.cos(el),
                           rad * math.sin(el)]) + [0, 0, 0.2]
        w2c = look_at(center, world.target + rng.uniform(-0.05, 0.05, 3))
        cam = cams[0 if shared_camera else k]
        name = f"view_{k:03d}.png"
        write_png_atomic(out / "images" / name, to_uint8(world.render(cam, w2c)))
        img = pycolmap.Image(name=name, camera_id=cam.camera_id, image_id=k + 1)
        rec.add_image_with_trivial_frame(
            img, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3].copy()))
        # surface points seen by this view (stand-in for SfM), shaded colour + noise
        uv = rng.uniform([0, 0], [width, height], size=(per_view, 2))
        o, d = world.rays(cam, w2c, uv)
        rgb, t, p = world.trace(o, d)
        ok = np.isfinite(t)
        pts.append(p[ok] + rng.normal(scale=0.005, size=(ok.sum(), 3)))
        cols.append(np.clip(rgb[ok] + rng.normal(scale=0.02, size=(ok.sum(), 3)), 0, 1))
    pts = np.concatenate(pts)[:n_points]
    cols = np.concatenate(cols)[:n_points]
    for p, c in zip(pts, cols):
        rec.add_point3D(p, pycolmap.Track(), np.round(c * 255).astype(np.uint8))
    rec.write(str(out / "sparse" / "0"))
    meta = {"generator": "baseline.data.synthetic", "seed": seed, "n_views": n_views,
            "width": width, "height": height, "texture_detail": texture_detail,
            "n_points": len(pts), "camera_model": camera_model,
            "distortion": list(distortion), "shared_camera": shared_camera, "fov_deg": fov_deg}
    write_text_atomic(out / "synthetic.json", json.dumps(meta, indent=1))
