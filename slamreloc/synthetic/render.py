"""Ray-cast rendering of a `Room` with open3d's RaycastingScene (Embree, multi-threaded).

One ray per pixel centre: pixel (u, v) has camera ray ((u - cx) / fx, (v - cy) / fy, 1), so the
hit parameter t of the unnormalised ray is directly the z-depth in the camera frame (metres).
Colours are bilinear lookups (cv2.remap) in the hit face's texture, packed into one atlas
image; shading is baked into the textures.
"""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d

from slamreloc.geometry import Rigid3
from slamreloc.synthetic.room import TEXEL_M, Room
from slamreloc.types import Camera

ATLAS_WIDTH = 4096  # texels; cv2.remap needs both atlas sides < 32767


def pack_atlas(textures: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Shelf-pack textures into one image; returns (atlas (H, W, 3) uint8, (F, 2) x, y origins)."""
    order = sorted(range(len(textures)), key=lambda i: -textures[i].shape[0])
    origins = np.zeros((len(textures), 2), np.int64)
    x = y = shelf = 0
    for i in order:
        h, w = textures[i].shape[:2]
        if x + w > ATLAS_WIDTH:
            x, y, shelf = 0, y + shelf + 1, 0
        origins[i] = (x, y)
        x, shelf = x + w + 1, max(shelf, h)
    atlas = np.zeros((y + shelf + 1, ATLAS_WIDTH, 3), np.uint8)
    for (ox, oy), tex in zip(origins, textures):
        atlas[oy:oy + tex.shape[0], ox:ox + tex.shape[1]] = tex
    return atlas, origins


class RenderScene:
    """Triangulated room (2 triangles per face; `tri_face` maps triangle -> face) + atlas."""

    def __init__(self, room: Room) -> None:
        self.room = room
        self.atlas, origins = pack_atlas([f.texture for f in room.faces])
        verts, tri_uv = [], []
        for f, origin in zip(room.faces, origins):
            su, sv = f.size
            verts += [f.origin, f.origin + su * f.axis_u,
                      f.origin + su * f.axis_u + sv * f.axis_v, f.origin + sv * f.axis_v]
            uv = np.array([[0, 0], [su, 0], [su, sv], [0, sv]]) / TEXEL_M + origin
            tri_uv += [uv[[0, 1, 2]], uv[[0, 2, 3]]]
        n_faces = len(room.faces)
        tris = (4 * np.arange(n_faces)[:, None, None] + np.array([[0, 1, 2], [0, 2, 3]]))
        self.tri_face = np.repeat(np.arange(n_faces), 2)  # (T,) face index of each triangle
        self.tri_uv = np.asarray(tri_uv, np.float32)  # (T, 3, 2) atlas texel coords of corners
        self.raycaster = o3d.t.geometry.RaycastingScene()
        self.raycaster.add_triangles(o3d.core.Tensor(np.asarray(verts, np.float32)),
                                     o3d.core.Tensor(tris.reshape(-1, 3).astype(np.uint32)))
        self._rays_cam: dict[Camera, np.ndarray] = {}

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (m) from (N, 3) world points to the nearest surface."""
        pts = o3d.core.Tensor(np.asarray(points, np.float32).reshape(-1, 3))
        return self.raycaster.compute_distance(pts).numpy()

    def rays_cam(self, camera: Camera) -> np.ndarray:
        """(H*W, 2) float32 (x, y) of the camera-frame rays (x, y, 1), row-major over pixels
        (through the lens model of a distorted camera)."""
        if camera not in self._rays_cam:
            u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
            pixels = camera.undistort(np.stack([u.ravel(), v.ravel()], 1).astype(np.float64))
            rays = (pixels - [camera.cx, camera.cy]) / [camera.fx, camera.fy]
            self._rays_cam[camera] = rays.astype(np.float32)
        return self._rays_cam[camera]


def render_frame(scene: RenderScene, camera: Camera, world_from_cam: Rigid3,
                 noise_seed: int | tuple[int, ...] | None = None,
                 noise_sigma: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """(rgb (H, W, 3) uint8, depth (H, W) float32 z-depth in metres, inf where nothing is hit).

    Gaussian pixel noise of `noise_sigma` grey levels is added when `noise_seed` is given.
    """
    rays_cam = scene.rays_cam(camera)
    n = len(rays_cam)
    rays = np.empty((n, 6), np.float32)
    rays[:, :3] = world_from_cam.translation
    rot = world_from_cam.rotation.astype(np.float32)
    # R @ (x, y, 1) written out elementwise: a BLAS matmul here would fight Embree for cores
    np.multiply(rays_cam[:, :1], rot[:, 0], out=rays[:, 3:])
    rays[:, 3:] += rays_cam[:, 1:2] * rot[:, 1] + rot[:, 2]
    hit = scene.raycaster.cast_rays(o3d.core.Tensor(rays))
    depth = hit["t_hit"].numpy()
    valid = np.isfinite(depth)
    prim = hit["primitive_ids"].numpy()[valid].astype(np.int64)
    bary = hit["primitive_uvs"].numpy()[valid]
    corners = scene.tri_uv[prim]  # (M, 3, 2)
    uv = (corners[:, 0] + bary[:, :1] * (corners[:, 1] - corners[:, 0])
          + bary[:, 1:] * (corners[:, 2] - corners[:, 0]))
    h, w = camera.height, camera.width
    maps = np.full((n, 2), -10.0, np.float32)  # outside the atlas: black
    maps[valid] = uv
    maps = maps.reshape(h, w, 2)
    rgb = cv2.remap(scene.atlas, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    if noise_seed is not None:
        rng = np.random.default_rng(noise_seed)
        noisy = rgb + rng.standard_normal((h, w, 3), np.float32) * np.float32(noise_sigma)
        rgb = np.clip(noisy + 0.5, 0, 255).astype(np.uint8)
    return rgb, depth.reshape(h, w)
