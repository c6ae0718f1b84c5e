"""A synthetic scene with exact ground truth, ray-cast with open3d's RaycastingScene.

World frame: z up, ground plane z = 0, back wall at y = +WALL_Y facing -y; the objects
(textured boxes and spheres) stand near the origin; cameras sit on an arc (or a spherical
cap) in front (y < 0) and look at the scene centre. Cameras are pinhole, OpenCV axes,
COLMAP pixel centres (see :mod:`camio`).

Shading is view-independent: ``albedo * (ambient + (1 - ambient) * max(0, n . l))`` with one
directional light and no shadows, so a surface point has the same colour in every view (what
3DGS with SH degree 0 can represent exactly). Depth maps are z-depth of the ray through the
pixel centre; ground-truth points lie exactly on the rendered triangles.

Outputs of :func:`write_synthetic_scene` (docs/contracts.md, "Prepared scene")::

    OUT/images/0000.png ...      8-bit RGB renders
    OUT/sparse/0/*.txt           reference COLMAP text model: PINHOLE cameras, GT points
                                 visible in >= 2 views with colours and observations
    OUT/gt/depth/<stem>.npy      [H, W] float32 z-depth, 0 = background
    OUT/gt/points.ply            all GT surface samples (x y z nx ny nz red green blue)
    OUT/split.json               PROTOCOL section 4 split
    OUT/synthetic.json           generator parameters and timing
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime.atomic import atomic_dir, write_json
from camio.cameras import Camera, look_at, project_points
from camio.colmap import write_text_model
from camio.images import write_image
from camio.ply import write_points_ply
from camio.split import make_split, write_split
from camio.textures import SolidTexture, ValueNoise

#: the default camera set of the synthetic scene (``python -m camio synth`` and the workflow's
#: ``synth`` block default to these): views, image width in pixels, the arc they span in degrees
VIEWS = 24
WIDTH = 256
ARC_DEG = 70.0

__all__ = ["SyntheticScene", "build_scene", "make_cameras", "render_view", "cast_pixels",
           "sample_surface_points", "write_synthetic_scene"]

log = logging.getLogger(__name__)

WALL_Y = 5.0
LIGHT_DIR = np.array([0.35, -0.55, 0.76]) / np.linalg.norm([0.35, -0.55, 0.76])
AMBIENT = 0.4
BACKGROUND = np.array([0.55, 0.7, 0.9])  # sky colour where a ray hits nothing


@dataclass
class _Object:
    kind: str  # "box", "sphere", "ground", "wall"
    vertices: np.ndarray  # [V, 3] float64
    triangles: np.ndarray  # [T, 3] int
    texture: SolidTexture
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class SyntheticScene:
    """Objects plus an open3d RaycastingScene over them (geometry id = object index)."""

    objects: list[_Object]
    raycaster: object
    center: np.ndarray

    def shade(self, pts: np.ndarray, normals: np.ndarray, obj_ids: np.ndarray) -> np.ndarray:
        """Colour [N, 3] in [0, 1] of surface points [N, 3] with normals [N, 3] on objects [N]."""
        col = np.zeros((len(pts), 3))
        for k, obj in enumerate(self.objects):
            m = obj_ids == k
            if m.any():
                col[m] = obj.texture(pts[m])
        lam = np.clip(normals @ LIGHT_DIR, 0.0, None)
        return np.clip(col * (AMBIENT + (1 - AMBIENT) * lam)[:, None], 0.0, 1.0)

    def normals_at(self, pts: np.ndarray, face_normals: np.ndarray, obj_ids: np.ndarray) -> np.ndarray:
        """Shading normals: analytic for spheres (smooth), the face normal otherwise."""
        n = face_normals.astype(np.float64).copy()
        for k, obj in enumerate(self.objects):
            m = obj_ids == k
            if obj.kind == "sphere" and m.any():
                d = pts[m] - obj.center
                n[m] = d / np.linalg.norm(d, axis=1, keepdims=True)
        return n


def _box(size: np.ndarray, yaw: float, center_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_box(*size)
    v = np.asarray(m.vertices) - np.array([size[0] / 2, size[1] / 2, 0.0])
    c, s = np.cos(yaw), np.sin(yaw)
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    v = v @ rz.T + np.array([center_xy[0], center_xy[1], 0.0])
    return v, np.asarray(m.triangles)


def _sphere(radius: float, center: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=40)
    return np.asarray(m.vertices) + center, np.asarray(m.triangles)


def _quad(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles over 4 corners given counter-clockwise seen from the front side."""
    return np.asarray(corners, np.float64), np.array([[0, 1, 2], [0, 2, 3]])


def build_scene(seed: int = 0) -> SyntheticScene:
    """The random scene of ``seed``: ground, back wall, 3 boxes, 3 spheres (no overlaps)."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    noise = ValueNoise(rng, channels=3)
    objs: list[_Object] = []
    v, t = _quad(np.array([[-20, -12, 0], [20, -12, 0], [20, WALL_Y, 0], [-20, WALL_Y, 0]]))
    objs.append(_Object("ground", v, t, SolidTexture(rng, noise, checker=True, detail_freq=7.0)))
    v, t = _quad(np.array([[-20, WALL_Y, 0], [20, WALL_Y, 0], [20, WALL_Y, 12], [-20, WALL_Y, 12]]))
    objs.append(_Object("wall", v, t, SolidTexture(rng, noise, checker=False, detail_freq=5.0)))
    placed: list[tuple[np.ndarray, float]] = []

    def place(radius: float) -> np.ndarray:
        for _ in range(200):
            xy = np.array([rng.uniform(-2.2, 2.2), rng.uniform(-1.2, 2.5)])
            if all(np.linalg.norm(xy - q) > radius + r + 0.15 for q, r in placed):
                placed.append((xy, radius))
                return xy
        raise RuntimeError("could not place the synthetic objects without overlap")

    for i in range(3):
        size = rng.uniform([0.6, 0.6, 0.5], [1.2, 1.2, 1.6])
        xy = place(0.5 * float(np.hypot(size[0], size[1])))
        v, t = _box(size, rng.uniform(0, np.pi / 2), xy)
        objs.append(_Object("box", v, t, SolidTexture(rng, noise, checker=bool(i % 2 == 0)),
                            np.array([xy[0], xy[1], size[2] / 2])))
    for i in range(3):
        r = rng.uniform(0.35, 0.7)
        xy = place(r)
        c = np.array([xy[0], xy[1], r + rng.uniform(0.0, 0.4) * (i == 2)])
        v, t = _sphere(r, c)
        objs.append(_Object("sphere", v, t, SolidTexture(rng, noise, checker=bool(i == 1)), c))

    rc = o3d.t.geometry.RaycastingScene()
    for obj in objs:
        rc.add_triangles(o3d.core.Tensor(obj.vertices.astype(np.float32)),
                         o3d.core.Tensor(obj.triangles.astype(np.uint32)))
    return SyntheticScene(objs, rc, np.array([0.0, 0.6, 0.6]))


def make_cameras(
    scene: SyntheticScene, views: int = VIEWS, width: int = WIDTH, height: int | None = None,
    arc_deg: float = ARC_DEG, layout: str = "arc", radius: float = 5.5, fov_deg: float = 60.0,
) -> list[Camera]:
    """Cameras named 0000.png ... looking at the scene centre, ordered along the arc.

    Args:
        views: number of cameras.
        width, height: image size (height defaults to 3/4 of the width).
        arc_deg: azimuth span around the scene centre (centred on the -y direction).
        layout: "arc" (one arc, elevation gently varying 15..25 deg) or "sphere" (a spherical
            cap: Fibonacci-like spread over the azimuth span and 10..45 deg elevation).
        radius: distance from the scene centre; fov_deg: horizontal field of view.
    """
    if views < 1:
        raise ValueError(f"views must be >= 1, got {views}")
    height = int(round(width * 3 / 4)) if height is None else int(height)
    f = width / 2 / np.tan(np.radians(fov_deg) / 2)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    u = (np.arange(views) + 0.5) / views if views > 1 else np.array([0.5])
    az = np.radians((u - 0.5) * arc_deg)
    if layout == "arc":
        el = np.radians(20.0 + 5.0 * np.sin(2 * np.pi * 1.5 * u))
    elif layout == "sphere":
        golden = (np.sqrt(5) - 1) / 2
        el = np.radians(10.0 + 35.0 * ((np.arange(views) * golden) % 1.0))
    else:
        raise ValueError(f"layout must be 'arc' or 'sphere', got {layout!r}")
    cams = []
    for i in range(views):
        eye = scene.center + radius * np.array(
            [np.sin(az[i]) * np.cos(el[i]), -np.cos(az[i]) * np.cos(el[i]), np.sin(el[i])])
        cams.append(Camera(f"{i:04d}.png", width, height, K, look_at(eye, scene.center, up=(0, 0, 1))[:3]))
    return cams


def cast_pixels(scene: SyntheticScene, cam: Camera, uv: np.ndarray) -> dict[str, np.ndarray]:
    """Cast rays through continuous pixel coordinates ``uv`` [N, 2] (COLMAP convention).

    Returns:
        dict with ``depth`` [N] z-depth in the camera frame (inf on a miss), ``points`` [N, 3]
        world hit points, ``normals`` [N, 3] shading normals, ``obj`` [N] object index (-1 on a
        miss), ``rgb`` [N, 3] shaded colour (BACKGROUND on a miss).
    """
    import open3d as o3d

    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    d_cam = np.linalg.solve(cam.K, np.c_[uv, np.ones(len(uv))].T).T  # z = 1 in the camera frame
    d_world = d_cam @ cam.R  # R^T d
    origin = np.broadcast_to(cam.center, d_world.shape)
    rays = np.concatenate([origin, d_world], axis=1).astype(np.float32)
    hit = scene.raycaster.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().astype(np.float64)
    gid = hit["geometry_ids"].numpy().astype(np.int64)
    ok = np.isfinite(t)
    obj = np.where(ok, gid, -1)
    pts = cam.center + t[:, None] * d_world
    pts[~ok] = np.nan
    normals = scene.normals_at(np.where(ok[:, None], pts, 0.0), hit["primitive_normals"].numpy(), obj)
    rgb = np.tile(BACKGROUND, (len(uv), 1))
    if ok.any():
        rgb[ok] = scene.shade(pts[ok], normals[ok], obj[ok])
    return {"depth": t, "points": pts, "normals": normals, "obj": obj, "rgb": rgb}


def render_view(scene: SyntheticScene, cam: Camera, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Render one view.

    Args:
        supersample: s x s rays per pixel for the colour, box-averaged (anti-aliasing); the
            depth always comes from the single ray through the pixel centre.

    Returns:
        rgb [H, W, 3] float32 in [0, 1]; depth [H, W] float32 z-depth, 0 where nothing is hit.
    """
    h, w, s = cam.height, cam.width, int(supersample)
    jj, ii = np.meshgrid(np.arange(w * s), np.arange(h * s))
    uv = np.stack([(jj.ravel() + 0.5) / s, (ii.ravel() + 0.5) / s], axis=1)
    res = cast_pixels(scene, cam, uv)
    rgb = res["rgb"].reshape(h, s, w, s, 3).mean(axis=(1, 3)).astype(np.float32)
    if s == 1:
        depth = res["depth"].reshape(h, w)
    else:
        jj, ii = np.meshgrid(np.arange(w), np.arange(h))
        depth = cast_pixels(scene, cam, np.stack([jj.ravel() + 0.5, ii.ravel() + 0.5], 1))["depth"].reshape(h, w)
    depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    return rgb, depth


def sample_surface_points(scene: SyntheticScene, n: int, rng: np.random.Generator,
                          region: float = 7.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-weighted uniform samples on the object triangles (ground and wall restricted to
    |x| < region, y > -region, z < region so the cloud covers what the cameras see).

    Returns:
        points [n, 3] float64, colours [n, 3] uint8 (the rendered, shaded colour of the
        point), normals [n, 3].
    """
    tris, objs = [], []
    for k, obj in enumerate(scene.objects):
        v = obj.vertices[obj.triangles]  # [T, 3, 3]
        if obj.kind in ("ground", "wall"):
            lo = np.array([-region, -region, -1.0])
            hi = np.array([region, WALL_Y + 1.0, region])
            v = np.clip(v, lo, hi)
        tris.append(v)
        objs.append(np.full(len(v), k))
    tri = np.concatenate(tris)
    obj_of = np.concatenate(objs)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pick = rng.choice(len(tri), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    t = tri[pick]
    pts = t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    normals = scene.normals_at(pts, fn, obj_of[pick])
    rgb = scene.shade(pts, normals, obj_of[pick])
    return pts, np.round(rgb * 255).astype(np.uint8), normals


def _visibility(pts: np.ndarray, cam: Camera, depth: np.ndarray, tol: float = 0.01):
    """Which points [N, 3] are seen by ``cam`` (inside the image, in front, not occluded
    according to the depth map, relative tolerance ``tol``). Returns (mask [N], uv [N, 2])."""
    uv, z = project_points(pts, cam.K, cam.cam_from_world)
    ok = (z > 1e-6) & np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] >= 0.5) & (uv[:, 0] <= cam.width - 0.5) & (uv[:, 1] >= 0.5) & (uv[:, 1] <= cam.height - 0.5)
    idx = np.where(ok)[0]
    j = np.clip(np.round(uv[idx, 0] - 0.5).astype(int), 0, cam.width - 1)
    i = np.clip(np.round(uv[idx, 1] - 0.5).astype(int), 0, cam.height - 1)
    d = depth[i, j]
    ok[idx] = (d > 0) & (np.abs(d - z[idx]) <= tol * z[idx])
    return ok, uv


def write_synthetic_scene(
    out: str | Path, views: int = VIEWS, width: int = WIDTH, seed: int = 0, arc_deg: float = ARC_DEG,
    layout: str = "arc", supersample: int = 1, n_gt_points: int = 60000, n_ref_points: int = 4000,
    ns: tuple[int, ...] = (3, 6, 9, 12),
) -> Path:
    """Generate and write the synthetic scene (layout in the module docstring) atomically.

    Args:
        out: output folder (replaced as a whole if it exists).
        views, width, arc_deg, layout: camera set (see :func:`make_cameras`).
        seed: everything (objects, textures, sampled points) is determined by it.
        supersample: anti-aliasing rays per pixel side.
        n_gt_points: surface samples in gt/points.ply.
        n_ref_points: at most this many of them, seen in >= 2 views, go into sparse/0.
        ns: training-view counts for split.json (those larger than the pool are left out).

    Returns:
        The output folder.
    """
    from runtime.logs import progress

    t0 = time.perf_counter()
    scene = build_scene(seed)
    cams = make_cameras(scene, views, width, arc_deg=arc_deg, layout=layout)
    rng = np.random.default_rng([seed, 1])
    pts, cols, normals = sample_surface_points(scene, n_gt_points, rng)
    seen = np.zeros(len(pts), np.int64)
    obs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    with atomic_dir(out) as tmp:
        for cam in progress(cams, desc="render"):
            rgb, depth = render_view(scene, cam, supersample)
            write_image(tmp / "images" / cam.name, rgb)
            stem = Path(cam.name).stem
            (tmp / "gt" / "depth").mkdir(parents=True, exist_ok=True)
            np.save(tmp / "gt" / "depth" / f"{stem}.npy", depth)
            vis, uv = _visibility(pts, cam, depth)
            seen += vis
            obs[cam.name] = (uv, vis)
        write_points_ply(tmp / "gt" / "points.ply", pts, cols, normals)
        ref = np.where(seen >= 2)[0][:n_ref_points]
        row = np.full(len(pts), -1)
        row[ref] = np.arange(len(ref))
        observations = {}
        for name, (uv, vis) in obs.items():
            keep = np.where(vis & (row >= 0))[0]
            observations[name] = (uv[keep], row[keep])
        write_text_model(tmp / "sparse" / "0", cams, pts[ref], cols[ref], observations)
        pool = views - len(range(0, views, 8))
        split = make_split([c.name for c in cams], tuple(n for n in ns if n <= pool))
        write_split(tmp / "split.json", split)
        write_json(tmp / "synthetic.json", {
            "seed": seed, "views": views, "width": width, "height": cams[0].height,
            "arc_deg": arc_deg, "layout": layout, "supersample": supersample,
            "n_gt_points": len(pts), "n_ref_points": int(len(ref)),
            "light_dir": LIGHT_DIR, "ambient": AMBIENT, "background": BACKGROUND,
            "objects": [o.kind for o in scene.objects], "wall_time_s": time.perf_counter() - t0,
        })
    log.info("synthetic scene (seed %d, %d views, %dx%d, %d ref points) written to %s in %.2f s",
             seed, views, width, cams[0].height, len(ref), out, time.perf_counter() - t0)
    return Path(out)
