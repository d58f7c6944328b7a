"""The training cameras' image thumbnails as ONE scene node: a texture atlas on a mesh of
quads, one quad on each frustum's image rectangle (a GLB written here: no extra dependency).

Hundreds of separate textured frustum nodes make the browser decode hundreds of images and
mount hundreds of scene objects, each arrival costing a redraw of the whole map (seconds per
frame where WebGL runs in software). One node is decoded and drawn at once; a click on it is
resolved on the server by intersecting the click's ray with the quads."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamreloc.geometry import Rigid3

ATLAS_MAX_SIDE = 2048  # pixels; every WebGL implementation takes textures this large
JPEG_QUALITY = 85


@dataclass
class ImageQuads:
    """Quads in world coordinates (camera image rectangles) with their atlas cells."""

    corners: np.ndarray  # (N, 4, 3): image top-left, top-right, bottom-right, bottom-left
    atlas: np.ndarray  # (H, W, 3) uint8
    cells: np.ndarray  # (N, 4) pixel box of each image in the atlas: x0, y0, x1, y1

    def __len__(self) -> int:
        return len(self.corners)

    def pick(self, origin: np.ndarray, direction: np.ndarray) -> int | None:
        """Index of the nearest quad the ray hits (or passes closest to, within a quad's
        size), None when it misses them all."""
        if not len(self):
            return None
        o, d = np.asarray(origin, float), np.asarray(direction, float)
        d = d / max(np.linalg.norm(d), 1e-12)
        c = self.corners
        ex, ey = c[:, 1] - c[:, 0], c[:, 3] - c[:, 0]  # along image x and y
        normal = np.cross(ex, ey)
        denom = normal @ d
        safe = np.where(np.abs(denom) < 1e-12, 1e-12, denom)
        t = np.einsum("nj,nj->n", normal, c[:, 0] - o) / safe
        hit = o + t[:, None] * d
        u = np.einsum("nj,nj->n", hit - c[:, 0], ex) / np.einsum("nj,nj->n", ex, ex)
        v = np.einsum("nj,nj->n", hit - c[:, 0], ey) / np.einsum("nj,nj->n", ey, ey)
        # distance outside the rectangle, in quad sizes (0 inside)
        outside = np.hypot(np.clip(np.abs(u - 0.5) - 0.5, 0, None),
                           np.clip(np.abs(v - 0.5) - 0.5, 0, None))
        ok = (t > 0) & (np.abs(denom) > 1e-9) & (outside < 0.25)
        if not ok.any():
            return None
        score = np.where(ok, t * (1 + outside), np.inf)  # in front first, inside before near
        return int(np.argmin(score))


def image_corners(poses: list[Rigid3], fx: float, fy: float, width: float, height: float,
                  scale: float) -> np.ndarray:
    """(N, 4, 3) world corners of each camera's image rectangle at depth `scale` (the base of
    the frustum drawn by `layers.frustum_segments`), from the image's top-left clockwise."""
    hw, hh = width / 2 / fx * scale, height / 2 / fy * scale
    local = np.array([[-hw, -hh, scale], [hw, -hh, scale], [hw, hh, scale], [-hw, hh, scale]])
    rot = np.stack([p.rotation for p in poses]).reshape(-1, 3, 3)
    t = np.stack([p.translation for p in poses]).reshape(-1, 3)
    return np.einsum("nij,kj->nki", rot, local) + t[:, None]


def build_atlas(images: list[np.ndarray], max_side: int = ATLAS_MAX_SIDE
                ) -> tuple[np.ndarray, np.ndarray]:
    """Tile RGB images into one atlas (cells of one size, at most max_side pixels a side).
    Returns (atlas, cells (N, 4) x0 y0 x1 y1)."""
    import cv2

    n = len(images)
    h0, w0 = images[0].shape[:2]
    cols = int(np.ceil(np.sqrt(n * h0 / w0)))  # roughly square atlas
    rows = int(np.ceil(n / cols))
    cw = max(1, min(w0, max_side // cols, int(max_side // rows * w0 / h0)))
    ch = max(1, round(cw * h0 / w0))
    atlas = np.zeros((rows * ch, cols * cw, 3), np.uint8)
    cells = np.zeros((n, 4), np.int64)
    for i, img in enumerate(images):
        r, c = divmod(i, cols)
        x0, y0 = c * cw, r * ch
        atlas[y0:y0 + ch, x0:x0 + cw] = cv2.resize(np.ascontiguousarray(img[..., :3]), (cw, ch),
                                                   interpolation=cv2.INTER_AREA)
        cells[i] = x0, y0, x0 + cw, y0 + ch
    return atlas, cells


def image_quads(poses: list[Rigid3], images: list[np.ndarray], fx: float, fy: float,
                width: float, height: float, scale: float) -> ImageQuads:
    atlas, cells = build_atlas(images)
    return ImageQuads(image_corners(poses, fx, fy, width, height, scale), atlas, cells)


def quads_glb(quads: ImageQuads) -> bytes:
    """A binary glTF of the quads textured from the atlas (JPEG), unlit (KHR_materials_unlit:
    three.js draws it with the same basic material as viser's own frustum images, whose
    shader compiles fast in software WebGL) and double-sided."""
    import io

    from PIL import Image

    n = len(quads)
    positions = quads.corners.reshape(-1, 3).astype(np.float32)
    base = 4 * np.arange(n, dtype=np.uint32)[:, None]
    indices = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=1).astype(np.uint32)
    h, w = quads.atlas.shape[:2]
    x0, y0, x1, y1 = (quads.cells[:, k, None].astype(np.float64) for k in range(4))
    inset = 0.5  # half a texel: no bleeding from the neighbouring cell
    xs = np.hstack([x0 + inset, x1 - inset, x1 - inset, x0 + inset]) / w
    ys = np.hstack([y0 + inset, y0 + inset, y1 - inset, y1 - inset]) / h
    uv = np.stack([xs, ys], axis=-1).reshape(-1, 2).astype(np.float32)  # glTF: v down
    jpeg = io.BytesIO()
    Image.fromarray(quads.atlas).save(jpeg, format="JPEG", quality=JPEG_QUALITY)
    return glb_bytes(positions, uv, indices.reshape(-1), jpeg.getvalue())


def glb_bytes(positions: np.ndarray, uv: np.ndarray, indices: np.ndarray, jpeg: bytes) -> bytes:
    """One textured triangle mesh as GLB (glTF 2.0 binary): float32 positions and uvs, uint32
    indices, an embedded JPEG, an unlit double-sided material."""
    import json
    import struct

    blobs = [positions.astype("<f4").tobytes(), uv.astype("<f4").tobytes(),
             indices.astype("<u4").tobytes(), jpeg]
    views, offset = [], 0
    for blob, target in zip(blobs, (34962, 34962, 34963, None), strict=True):  # vertex, index
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob)}
                     | ({"target": target} if target else {}))
        offset += (len(blob) + 3) // 4 * 4
    binary = b"".join(b + b"\0" * (-len(b) % 4) for b in blobs)
    gltf = {
        "asset": {"version": "2.0", "generator": "slamreloc viewer"},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1},
                                    "indices": 2, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0},
                                                "metallicFactor": 0.0, "roughnessFactor": 1.0},
                       "doubleSided": True, "extensions": {"KHR_materials_unlit": {}}}],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
        "textures": [{"source": 0, "sampler": 0}],
        "images": [{"bufferView": 3, "mimeType": "image/jpeg"}],
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": views,
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(positions), "type": "VEC3",
             "min": positions.min(axis=0).tolist(), "max": positions.max(axis=0).tolist()},
            {"bufferView": 1, "componentType": 5126, "count": len(uv), "type": "VEC2"},
            {"bufferView": 2, "componentType": 5125, "count": len(indices), "type": "SCALAR"}],
    }
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    chunks = (struct.pack("<II", len(text), 0x4E4F534A) + text
              + struct.pack("<II", len(binary), 0x004E4942) + binary)
    return struct.pack("<III", 0x46546C67, 2, 12 + len(chunks)) + chunks
