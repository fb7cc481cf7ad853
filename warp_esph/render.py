"""Headless software renderer for the USD files ``UsdWriter`` writes (numpy + Pillow only).

No display, no GPU, no OpenGL: every frame is rasterised with vectorised numpy.

- **Particles** are drawn as shaded spheres: each one is splatted as a disc of its
  projected radius; every pixel of the disc gets the depth and normal of the sphere's
  front surface there, and a z-buffer (``np.minimum.at``) keeps the nearest, so
  overlapping spheres intersect correctly.
- **Surfaces**: where the file holds a body's surface mesh at a frame (``warp-esph run
  --surface``, read by ``UsdFrames.surface``), that body is drawn as the mesh instead of its
  particles (``surfaces=False`` / ``render --particles``: particles always). Triangles are
  rasterised at pixel centres (``raster_triangles``: perspective-correct depth and
  barycentrics) into the same z-buffer, shaded with the particles' lighting; normals are
  smooth across a vertex and flat across a crease (``mesh_normals``). Colour by body or
  material as the particles; a primvar colour is carried from the particles to the vertices.
- **Colliders** under ``/World/Colliders`` are ray cast per pixel: planes as a checkered
  floor fading into the background, spheres, axis-aligned boxes.
- **Tools** under ``/World/Tools`` (``SceneBuilder.add_tool``) are drawn at their pose of the
  frame (the file's time-sampled translate and orient): a plane tool as a plane collider
  (left out while the camera is on its solid side, where it would hide everything), the
  other shapes as triangle meshes (``tool_mesh``: boxes, spheres, capsules and cylinders
  tessellated, meshes as stored) rasterised into the particles' z-buffer, in steel grey,
  casting shadows. Pinned sets have no geometry and are not drawn.
- **Lighting**: a key light with a shadow map (particles and surfaces cast shadows on the
  ground, on colliders and on each other, 3 x 3 percentage-closer filtered), a fill light,
  ambient and a specular highlight, shaded in linear RGB and written as sRGB.
- **Camera**: perspective, looking at the bounds of the particles over all rendered frames
  (and the sphere and box colliders) from ``azimuth``/``elevation``; the distance is the
  smallest that keeps those bounds inside the picture. A scene may store a preferred view
  (``warp_esph:view`` in the layer's custom data, written by ``warp-esph run``).
- **Colour**: by body, by material, or a per-particle primvar through a colour map:
  ``alpha`` (accumulated plastic strain) or ``singular_values`` (shown as the elastic
  strain ``max_k |ln sigma_k|``), with a colour bar. The colour range is taken over all
  rendered frames so it does not flicker.

``render_usd(path, output, ...)`` writes PNG frames into a folder, one PNG (several frames
side by side when more than one is chosen), an animated GIF, or an MP4 (where the
``ffmpeg`` program is on the PATH, or the ``mp4`` extra installed the one ``imageio-ffmpeg`` bundles).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import os
import shutil
import subprocess
import time

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from . import checks
# The reader lives beside the writer; re-exported here because the renderer's users get
# frames from it (``warp_esph.render.UsdFrames`` is a published name).
from .usd import Collider, Tool, UsdFrames, parse_frames, quat_matrix

__all__ = [
    "COLOR_MODES", "OUTPUT_EXTENSIONS", "Camera", "Collider", "UsdFrames", "Renderer", "auto_camera", "mesh_normals",
    "parse_frames", "raster_triangles", "render_usd", "tool_mesh", "vertex_values",
]

#: How particles are coloured.
COLOR_MODES = ("body", "material", "alpha", "singular_values")
#: File outputs; any name without an extension is a folder of PNG frames.
OUTPUT_EXTENSIONS = (".png", ".gif", ".mp4")

# Body colours (sRGB): warm, distinct, pleasant on a light grey floor.
BODY_PALETTE = np.array([
    (0.93, 0.62, 0.32), (0.36, 0.58, 0.85), (0.86, 0.36, 0.36), (0.45, 0.72, 0.45),
    (0.72, 0.52, 0.84), (0.95, 0.80, 0.35), (0.35, 0.75, 0.75), (0.85, 0.50, 0.65),
    (0.60, 0.60, 0.40), (0.55, 0.45, 0.35), (0.50, 0.80, 0.95), (0.80, 0.70, 0.60),
], dtype=np.float32)

# Viridis, sampled at 9 points (sRGB); linear interpolation between them.
_VIRIDIS = np.array([
    (0.267, 0.005, 0.329), (0.283, 0.141, 0.458), (0.254, 0.265, 0.530), (0.207, 0.372, 0.553),
    (0.164, 0.471, 0.558), (0.128, 0.567, 0.551), (0.135, 0.659, 0.518), (0.267, 0.749, 0.441),
    (0.478, 0.821, 0.318), (0.741, 0.873, 0.150), (0.993, 0.906, 0.144),
], dtype=np.float32)

_BACKGROUND_TOP = np.array((0.80, 0.84, 0.90), dtype=np.float32)     # sRGB
_BACKGROUND_BOTTOM = np.array((0.97, 0.97, 0.98), dtype=np.float32)
_FLOOR = (np.array((0.86, 0.86, 0.88), dtype=np.float32), np.array((0.76, 0.77, 0.80), dtype=np.float32))
_COLLIDER = np.array((0.55, 0.60, 0.68), dtype=np.float32)
_TOOL = np.array((0.62, 0.64, 0.70), dtype=np.float32)  # the displayColor tools.usd_author writes


def _linear(srgb):
    return np.power(np.asarray(srgb, dtype=np.float32), 2.2)


def _to_srgb8(linear: np.ndarray) -> np.ndarray:
    return (np.power(np.clip(linear, 0.0, 1.0), 1.0 / 2.2) * 255.0 + 0.5).astype(np.uint8)


def colormap(values: np.ndarray) -> np.ndarray:
    """Viridis (sRGB) of ``values`` in [0, 1]."""
    v = np.clip(np.nan_to_num(np.asarray(values, dtype=np.float32), nan=0.0), 0.0, 1.0) * (len(_VIRIDIS) - 1)
    k = np.minimum(v.astype(np.int32), len(_VIRIDIS) - 2)
    f = (v - k)[..., None]
    return _VIRIDIS[k] * (1.0 - f) + _VIRIDIS[k + 1] * f


# ----------------------------------------------------------------------------- camera
#: How far from the origin a camera's eye and target may be (m): the projection squares
#: distances, which overflowed far beyond.
MAX_CAMERA_REACH = 1e15


@dataclasses.dataclass
class Camera:
    """A perspective pinhole camera; ``fov`` is the vertical field of view in degrees."""

    eye: np.ndarray
    target: np.ndarray
    width: int
    height: int
    fov: float = 30.0
    up: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))

    def __post_init__(self):
        # Unchecked, an eye on its target, a NaN or a fov of 0 failed in the first frame
        # ('cannot convert float NaN to integer', ZeroDivisionError), naming none of them.
        self.eye = np.asarray(checks.vector("eye", self.eye), dtype=np.float64)
        self.target = np.asarray(checks.vector("target", self.target), dtype=np.float64)
        self.width = checks.positive_int("width", self.width)
        self.height = checks.positive_int("height", self.height)
        self.fov = checks.positive("fov", self.fov)
        if not self.fov < 170:
            raise ValueError(f"fov = {checks.shorten(self.fov)!r} is not allowed: must be in (0, 170) degrees")
        far = np.abs(np.concatenate([self.eye, self.target])).max()
        if not far <= MAX_CAMERA_REACH:  # the projection squares distances: 1e300 m was NaN pixels
            raise ValueError(f"eye = {tuple(self.eye.tolist())!r}, target = {tuple(self.target.tolist())!r} are not "
                             f"allowed: each coordinate must be within {MAX_CAMERA_REACH:g} m of the origin")
        f = self.target - self.eye
        if not np.linalg.norm(f) > 0.0:
            raise ValueError(f"eye = {checks.shorten(tuple(self.eye.tolist()))!r} is not allowed: it is the target; the camera looks "
                             f"from the eye towards the target, so they must differ")
        self.forward = f / np.linalg.norm(f)
        r = np.cross(self.forward, np.asarray(self.up, dtype=np.float64))
        if np.linalg.norm(r) < 1e-9:  # looking straight up or down
            r = np.cross(self.forward, [0.0, 0.0, 1.0])
        self.right = r / np.linalg.norm(r)
        self.true_up = np.cross(self.right, self.forward)
        self.focal = 0.5 * self.height / math.tan(math.radians(self.fov) / 2.0)

    def project(self, points: np.ndarray):
        """Pixel coordinates (x right, y down; pixel (i, j) spans [i, i+1)) and depth along the view."""
        d = np.asarray(points, dtype=np.float64) - self.eye
        z = d @ self.forward
        zs = np.where(z > 1e-9, z, 1e-9)
        px = 0.5 * self.width + self.focal * (d @ self.right) / zs
        py = 0.5 * self.height - self.focal * (d @ self.true_up) / zs
        return px, py, z

    def pixel_rays(self):
        """Per-pixel ray directions ``dir`` (H, W, 3) scaled so ``eye + z * dir`` is at view depth ``z``."""
        i = (np.arange(self.width, dtype=np.float64) + 0.5 - 0.5 * self.width) / self.focal
        j = (0.5 * self.height - np.arange(self.height, dtype=np.float64) - 0.5) / self.focal
        return (self.forward[None, None, :] + i[None, :, None] * self.right[None, None, :]
                + j[:, None, None] * self.true_up[None, None, :])


def _view_direction(azimuth: float, elevation: float) -> np.ndarray:
    """Unit vector from the target towards the eye: azimuth about +y from +z towards +x."""
    a, e = math.radians(azimuth), math.radians(elevation)
    return np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])


def auto_camera(lo, hi, width: int, height: int, azimuth: float = 30.0, elevation: float = 20.0,
                fov: float = 30.0, zoom: float = 1.0, margin: float = 0.08) -> Camera:
    """A camera that sees the box ``[lo, hi]`` from ``azimuth``/``elevation`` (degrees), filling
    the picture up to ``margin`` (a fraction of it) on the tighter side; ``zoom > 1`` moves closer."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    direction = _view_direction(azimuth, elevation)
    target = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
    limit = 1.0 - 2.0 * margin

    def extent(dist, tgt):
        cam = Camera(tgt + dist * direction, tgt, width, height, fov)
        px, py, z = cam.project(corners)
        if (z <= 1e-6).any():
            return np.inf, cam, px, py
        fx = np.abs(px - 0.5 * width).max() / (0.5 * width)
        fy = np.abs(py - 0.5 * height).max() / (0.5 * height)
        return max(fx, fy), cam, px, py

    for _ in range(3):  # fit the distance, then centre the projected box, and again
        near, far = radius * 1.01, radius * 200.0
        for _ in range(40):
            mid = math.sqrt(near * far)
            if extent(mid, target)[0] > limit:
                near = mid
            else:
                far = mid
        _, cam, px, py = extent(far, target)
        # Move the target so the projected box is centred (a shift in the image plane).
        dx = 0.5 * (px.min() + px.max()) - 0.5 * width
        dy = 0.5 * (py.min() + py.max()) - 0.5 * height
        target = target + (far / cam.focal) * (dx * cam.right - dy * cam.true_up)
    dist = far / checks.positive("zoom", zoom)
    return Camera(target + dist * direction, target, width, height, fov)


# ----------------------------------------------------------------------------- splatting
@functools.cache
def _stencil(r: int):
    """The pixel offsets a disc of radius ``r`` pixels covers. Kept for each ``r`` asked (no
    more than the largest ``max_radius`` given to ``splat_spheres``, plus one), read-only, so
    that no caller's change reaches another's."""
    o = np.arange(-r, r + 1)
    ox, oy = np.meshgrid(o, o)
    keep = ox**2 + oy**2 <= (r + 1) ** 2
    ox, oy = ox[keep].astype(np.int32), oy[keep].astype(np.int32)
    ox.flags.writeable = False
    oy.flags.writeable = False
    return ox, oy


def splat_spheres(px, py, depth, rad_px, rad_depth, width: int, height: int, max_radius: int = 64):
    """Fragments of spheres splatted as discs: ``(pixel, depth, ux, uy, particle)``.

    ``px, py``: centre in pixels; ``rad_px``: projected radius in pixels; ``rad_depth``: the
    sphere's radius in depth units. A fragment's depth is that of the sphere's front surface,
    ``depth - rad_depth * sqrt(1 - |u|^2)``; ``(ux, uy)`` is its offset from the centre in
    units of the radius (x right, y up), which gives the normal.
    """
    rad_eff = np.maximum(rad_px, 0.6)  # a sphere smaller than a pixel still covers one
    R = np.minimum(np.ceil(rad_eff - 0.5).astype(np.int32), max_radius)
    pix, dep, uxs, uys, who = [], [], [], [], []
    for r in np.unique(R):
        sel = np.nonzero(R == r)[0]
        ox, oy = _stencil(int(r))
        cx = np.floor(px[sel]).astype(np.int32)
        cy = np.floor(py[sel]).astype(np.int32)
        X = cx[:, None] + ox[None, :]
        Y = cy[:, None] + oy[None, :]
        inv = (1.0 / rad_eff[sel]).astype(np.float32)[:, None]
        ux = (X + 0.5 - px[sel, None].astype(np.float32)) * inv
        uy = (py[sel, None].astype(np.float32) - (Y + 0.5)) * inv
        q = ux * ux + uy * uy
        m = (q < 1.0) & (X >= 0) & (X < width) & (Y >= 0) & (Y < height)
        if not m.any():
            continue
        rows = np.broadcast_to(sel[:, None], m.shape)[m]
        pix.append((Y[m] * width + X[m]).astype(np.int64))
        dep.append((depth[rows] - rad_depth[rows] * np.sqrt(1.0 - q[m])).astype(np.float32))
        uxs.append(ux[m])
        uys.append(uy[m])
        who.append(rows)
    if not pix:
        e = np.zeros(0)
        return e.astype(np.int64), e.astype(np.float32), e.astype(np.float32), e.astype(np.float32), e.astype(np.int64)
    return np.concatenate(pix), np.concatenate(dep), np.concatenate(uxs), np.concatenate(uys), np.concatenate(who)


def raster_triangles(px, py, depth, triangles, width: int, height: int, perspective: bool = True,
                     chunk: int = 1 << 21):
    """Fragments of triangles: ``(pixel, depth, bary (n, 3), triangle)``, one per pixel centre
    inside a triangle (both windings; a centre on a shared edge goes to both, the z-buffer
    keeps one, so a closed mesh leaves no holes).

    ``px, py``: vertex positions in pixels; ``depth``: vertex depth. ``perspective``: the
    depth is the view depth of a perspective camera, so ``1/depth`` and ``bary/depth`` are
    what is linear in the picture (perspective-correct); otherwise (an orthographic view)
    depth and barycentrics are interpolated linearly.
    """
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    X, Y, Z = (np.asarray(a, dtype=np.float32)[tri] for a in (px, py, depth))  # (T, 3) each
    ok = np.isfinite(X).all(axis=1) & np.isfinite(Y).all(axis=1) & np.isfinite(Z).all(axis=1)
    if perspective:
        ok &= (Z > 1e-6).all(axis=1)
    area = (X[:, 1] - X[:, 0]) * (Y[:, 2] - Y[:, 0]) - (X[:, 2] - X[:, 0]) * (Y[:, 1] - Y[:, 0])
    x0 = np.ceil(np.where(ok, X.min(axis=1), 0.0) - 0.5)
    x1 = np.floor(np.where(ok, X.max(axis=1), -1.0) - 0.5)
    y0 = np.ceil(np.where(ok, Y.min(axis=1), 0.0) - 0.5)
    y1 = np.floor(np.where(ok, Y.max(axis=1), -1.0) - 0.5)
    x0, y0 = np.maximum(x0, 0), np.maximum(y0, 0)
    x1, y1 = np.minimum(x1, width - 1), np.minimum(y1, height - 1)
    ok &= (x1 >= x0) & (y1 >= y0) & (np.abs(area) > 1e-12)
    # Bucket by the bounding box's larger side (rounded up to a power of two): one square
    # stencil per bucket, a few triangles' candidate pixels per chunk.
    side = np.maximum(x1 - x0, y1 - y0) + 1
    bucket = np.where(ok, np.ceil(np.log2(np.maximum(side, 1))).astype(np.int64), -1)
    pix, dep, bary, who = [], [], [], []
    for b in np.unique(bucket[bucket >= 0]):
        S = 1 << int(b)
        o = np.arange(S, dtype=np.float32)
        ox, oy = (g.reshape(-1) for g in np.meshgrid(o, o))
        members = np.nonzero(bucket == b)[0]
        step = max(1, chunk // (S * S))
        for c in range(0, len(members), step):
            t = members[c:c + step]
            cx = x0[t, None] + ox[None, :]
            cy = y0[t, None] + oy[None, :]
            inside = (cx <= x1[t, None]) & (cy <= y1[t, None])
            sx, sy = cx + np.float32(0.5), cy + np.float32(0.5)
            Xt, Yt = X[t], Y[t]
            inv = (1.0 / area[t])[:, None]
            w0 = ((Xt[:, 1, None] - sx) * (Yt[:, 2, None] - sy) - (Xt[:, 2, None] - sx) * (Yt[:, 1, None] - sy)) * inv
            w1 = ((Xt[:, 2, None] - sx) * (Yt[:, 0, None] - sy) - (Xt[:, 0, None] - sx) * (Yt[:, 2, None] - sy)) * inv
            w2 = 1.0 - w0 - w1
            inside &= (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
            rows, cols = np.nonzero(inside)
            if len(rows) == 0:
                continue
            w = np.stack([w0[rows, cols], w1[rows, cols], w2[rows, cols]], axis=1).astype(np.float32)
            tz = Z[t[rows]]
            if perspective:
                w = w / tz
                s = w.sum(axis=1)
                d = 1.0 / s
                w = w * d[:, None]
            else:
                d = (w * tz).sum(axis=1)
            pix.append((cy[rows, cols].astype(np.int64) * width + cx[rows, cols].astype(np.int64)))
            dep.append(d.astype(np.float32))
            bary.append(w)
            who.append(t[rows])
    if not pix:
        return np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
    return np.concatenate(pix), np.concatenate(dep), np.concatenate(bary), np.concatenate(who)


def mesh_normals(vertices, triangles, crease: float = 45.0):
    """Face normals (T, 3) and, per triangle corner, the normal to shade with (T, 3, 3).

    A corner gets its vertex's normal (the mean of the faces around it, each weighted by its
    angle there, so how a polygon was split into triangles does not matter) where that is
    within ``crease`` degrees of the face's own, else the face normal: a marching cubes
    surface is shaded smooth, a cube with shared corners stays flat (the mean of three
    orthogonal faces is 54.7 degrees from each).
    """
    v = np.asarray(vertices, dtype=np.float32)
    tri = np.asarray(triangles, dtype=np.int64)
    cross = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    length = np.linalg.norm(cross, axis=1, keepdims=True)
    face = cross / np.where(length > 0, length, 1.0)
    vn = np.zeros_like(v)
    for k in range(3):
        e1 = v[tri[:, (k + 1) % 3]] - v[tri[:, k]]
        e2 = v[tri[:, (k + 2) % 3]] - v[tri[:, k]]
        angle = np.arctan2(np.linalg.norm(np.cross(e1, e2), axis=1), np.einsum("ij,ij->i", e1, e2))
        np.add.at(vn, tri[:, k], face * angle[:, None])
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-30)
    corner = vn[tri]  # (T, 3, 3)
    sharp = np.einsum("tkj,tj->tk", corner, face) < math.cos(math.radians(crease))
    corner = np.where(sharp[:, :, None], face[:, None, :], corner)
    return face, corner


def vertex_values(vertices, points, values, radius):
    """``values`` of the particles at ``points`` carried to mesh ``vertices``: a weighted mean
    over the particles within ``radius`` (weight ``(1 - d^2/radius^2)^3``, as the surface
    field of ``warp_esph.surface``), binned on a grid of cell ``radius``; the nearest bin's
    mean where none is in reach."""
    p = np.asarray(points, dtype=np.float64)
    q = np.asarray(vertices, dtype=np.float64)
    val = np.asarray(values, dtype=np.float64)
    if len(p) == 0 or len(q) == 0:
        return np.zeros(len(q), np.float32)
    h = max(float(radius), 1e-9)
    lo = p.min(axis=0) - 2 * h
    cells = np.floor((p - lo) / h).astype(np.int64)
    dims = cells.max(axis=0) + 3
    key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    order = np.argsort(key, kind="stable")
    skey = key[order]
    num = np.zeros(len(q))
    den = np.zeros(len(q))
    qc = np.floor((q - lo) / h).astype(np.int64)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                c = qc + (dx, dy, dz)
                valid = ((c >= 0) & (c < dims)).all(axis=1)
                k = (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]
                a = np.searchsorted(skey, k, "left")
                b = np.where(valid, np.searchsorted(skey, k, "right"), a)
                # Visit the particles of each vertex's cell, one slot at a time.
                n = b - a
                for j in range(int(n.max()) if len(n) else 0):
                    has = np.nonzero(n > j)[0]
                    idx = order[a[has] + j]
                    d2 = ((q[has] - p[idx]) ** 2).sum(axis=1)
                    w = np.clip(1.0 - d2 / (h * h), 0.0, None) ** 3
                    num[has] += w * val[idx]
                    den[has] += w
    out = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
    missing = np.nonzero(~(den > 0))[0]
    if len(missing):  # far from every particle (a coarse mesh): the nearest particle
        step = max(1, (1 << 22) // len(p))
        for s in range(0, len(missing), step):
            m = missing[s:s + step]
            out[m] = val[np.argmin(((q[m, None, :] - p[None, :, :]) ** 2).sum(axis=2), axis=1)]
    return out.astype(np.float32)


# ----------------------------------------------------------------------------- tools
def _revolve(profile, segments: int):
    """Triangles of the surface swept by the ``(radius, y)`` polyline ``profile`` about the y
    axis; a repeated profile point starts a new ring there (a crease: flat shading across it)."""
    prof = np.asarray(profile, dtype=np.float64)
    a = np.linspace(0.0, 2.0 * math.pi, segments, endpoint=False)
    ca, sa = np.cos(a), np.sin(a)
    verts = np.stack([prof[:, 0, None] * ca[None, :], np.broadcast_to(prof[:, 1, None], (len(prof), segments)),
                      prof[:, 0, None] * sa[None, :]], axis=2).reshape(-1, 3)
    tris = []
    j = np.arange(segments)
    jn = (j + 1) % segments
    for i in range(len(prof) - 1):
        if np.allclose(prof[i], prof[i + 1]):
            continue
        v00, v01 = i * segments + j, i * segments + jn
        v10, v11 = (i + 1) * segments + j, (i + 1) * segments + jn
        if prof[i, 0] > 0:
            tris.append(np.stack([v00, v01, v11], axis=1))
        if prof[i + 1, 0] > 0:
            tris.append(np.stack([v00, v11, v10], axis=1))
    return verts, np.concatenate(tris)


def tool_mesh(tool: Tool, segments: int = 48) -> tuple[np.ndarray, np.ndarray] | None:
    """``(vertices (V, 3), triangles (T, 3))`` of a tool's surface in its own frame (None for a
    plane, which is drawn as a plane): a box's 12 triangles, a sphere, capsule (along y) and
    capped cylinder (along y) tessellated with ``segments`` around, a mesh as stored."""
    r, hh = float(tool.param[0]), float(tool.param[1])
    if tool.kind == "plane":
        return None
    if tool.kind == "box":
        h = np.asarray(tool.param, dtype=np.float64)
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * h
        # Each face as two triangles, wound outwards (corner index = 4 x + 2 y + z).
        quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        tri = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=np.int64)
        return corners, tri
    if tool.kind in ("sphere", "capsule"):
        lat = np.linspace(0.5 * math.pi, -0.5 * math.pi, segments // 2 + 1)
        shift = hh if tool.kind == "capsule" else 0.0
        upper = [(r * math.cos(t), r * math.sin(t) + shift) for t in lat if t >= 0]
        lower = [(r * math.cos(t), r * math.sin(t) - shift) for t in lat if t <= 0]
        return _revolve(upper + lower, segments)
    if tool.kind == "cylinder":
        return _revolve([(0.0, hh), (r, hh), (r, hh), (r, -hh), (r, -hh), (0.0, -hh)], segments)
    return np.asarray(tool.points, dtype=np.float64), np.asarray(tool.triangles, dtype=np.int64)


def _tool_plane(tool: Tool, p, q) -> Collider:
    """A plane tool at pose ``(p, q)`` as the plane collider the renderer ray casts."""
    n = quat_matrix(q) @ tool.param
    half = 0.5 * float(np.linalg.norm(tool.points[1] - tool.points[0])) if tool.points is not None else 2.0
    return Collider("plane", np.asarray(p, dtype=np.float64), np.array([half, 0.0, 0.0]), n, float(n @ p))


# ----------------------------------------------------------------------------- renderer
#: What a supersampled pixel of a picture takes while it is drawn (measured: 185 B).
BYTES_PER_PIXEL = 200


def _machine_memory() -> int | None:
    """The memory a picture is drawn in, in bytes, or None where not known: the host's available
    memory as a model's is weighed (``builder._host_memory``: a container's room where lower;
    the machine's let a container kill a drawing it could not hold)."""
    from .builder import _host_memory  # noqa: PLC0415

    return _host_memory()


def _same_name(name: str) -> str:
    return name


def _check_pixels(o: "RenderOptions", flag=_same_name) -> None:
    """Refuse a picture whose drawing would not fit in the machine's memory, before it is
    drawn: measured at about 185 B a supersampled pixel (rays, z-buffers, normals, colours),
    8192 x 8192 at supersample 2 needed some 50 GiB and was killed part way."""
    pixels = o.width * o.height * o.supersample**2
    need, have = pixels * BYTES_PER_PIXEL, _machine_memory()
    if have is not None and need > have:
        raise ValueError(f"{flag('width')} x {flag('height')} = {o.width} x {o.height} at {flag('supersample')} = "
                         f"{o.supersample} is not allowed on "
                         f"this machine: its {pixels:.3g} pixels (supersampled) need about {need / 2**30:.3g} GiB "
                         f"({BYTES_PER_PIXEL} B a pixel), more than the {have / 2**30:.3g} GiB available; use a smaller picture or "
                         f"supersample")


@dataclasses.dataclass
class RenderOptions:
    width: int = 800
    height: int = 600
    color: str = "body"
    supersample: int = 2
    radius_scale: float = 1.0
    azimuth: float | None = None
    elevation: float | None = None
    zoom: float = 1.0
    fov: float = 30.0
    label: bool = True
    shadows: bool = True
    surfaces: bool = True
    #: How a refusal names an option (``flag("radius_scale")``): the CLI passes its own
    #: (``--radius-scale``), so a message names what the user typed; not kept.
    flag: dataclasses.InitVar[object] = None

    def __post_init__(self, flag=None):
        flag = flag or _same_name
        self.width = checks.positive_int(flag("width"), self.width)
        self.height = checks.positive_int(flag("height"), self.height)
        if not (16 <= self.width <= 8192 and 16 <= self.height <= 8192):
            raise ValueError(f"{flag('width')} x {flag('height')} = {self.width} x {self.height} is not allowed: "
                             "each must be in [16, 8192]")
        checks.choice(flag("color"), self.color, COLOR_MODES)
        self.supersample = checks.positive_int(flag("supersample"), self.supersample)
        if self.supersample > 4:
            raise ValueError(f"{flag('supersample')} = {checks.shorten(self.supersample)!r} is not allowed: must be 1, 2, 3 or 4")
        # Beyond these a particle is far below a pixel or covers the picture; 1e300 overflowed
        # the float32 radii and failed as 'cannot convert float NaN to integer'.
        self.radius_scale = checks.in_range(flag("radius_scale"), self.radius_scale, 1e-3, 1e3)
        # Beyond these the camera stands inside the scene or so far that it is one pixel, and
        # its distance overflowed (1e308) or its picture's size did (1e-308).
        self.zoom = checks.in_range(flag("zoom"), self.zoom, 1e-3, 1e3)
        for name in ("surfaces", "label", "shadows"):  # label='no' drew the label
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{flag(name)} = {checks.shorten(getattr(self, name))!r} is not allowed: must be True or False")
        self.fov = checks.positive(flag("fov"), self.fov)
        if not self.fov < 170:
            raise ValueError(f"{flag('fov')} = {checks.shorten(self.fov)!r} is not allowed: must be in (0, 170) degrees")
        for name in ("azimuth", "elevation"):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, checks.number(flag(name), value))
        if self.elevation is not None and not -89.0 <= self.elevation <= 89.0:
            raise ValueError(f"{flag('elevation')} = {checks.shorten(self.elevation)!r} is not allowed: must be in [-89, 89] degrees")


class Renderer:
    """Renders frames of a ``UsdFrames`` with one camera and one colour range for all of them."""

    def __init__(self, data: UsdFrames, frames, options: RenderOptions | None = None, camera: Camera | None = None,
                 color_range: tuple[float, float] | None = None):
        """``frames``: the frames to frame (and colour-range) together, as ``parse_frames`` takes
        them (a spec, or any iterable of frame numbers: a range, a numpy array; ``None``: all). ``camera``: use this camera (its size must be the picture size times ``supersample``)
        instead of framing the bounds of ``frames`` automatically. ``color_range``: the values
        mapped to the ends of the colour map (default: 0 and the 99.5th percentile over ``frames``)."""
        self.data = data
        self.options = options or RenderOptions()
        o = self.options
        # The file's frames, at least one: none framed the bounds of nothing (a picture of
        # whatever an infinite box looked like), and a frame the file lacks failed at its render.
        self.frames = parse_frames(frames, data.frames, repeats=True)  # the frames framed: a repeat frames nothing new
        if camera is not None and not isinstance(camera, Camera):
            raise ValueError(f"camera = {checks.shorten(camera)!r} is not allowed: must be a warp_esph.render.Camera or None")
        _check_pixels(o)
        lo, hi = data.bounds(self.frames)
        self.particle_bounds = (lo.copy(), hi.copy())
        for c in data.colliders:  # spheres and boxes are part of the picture; planes are not
            if c.kind in ("sphere", "box"):
                lo, hi = np.minimum(lo, c.center - c.size), np.maximum(hi, c.center + c.size)
        self._tool_shapes = [(k, tool_mesh(t)) for k, t in enumerate(data.tools)]
        # Tools over the chosen frames, as far as they are near the material: a tool that
        # starts a metre away (or a long rail) would otherwise shrink the material to a dot.
        plo, phi = self.particle_bounds
        reach = np.maximum(phi - plo, 1e-3).max() if np.isfinite(plo).all() else np.inf
        for f in self.frames:
            for v, _ in self.tool_meshes(f):
                tlo = np.maximum(v.min(axis=0), plo - reach)
                thi = np.minimum(v.max(axis=0), phi + reach)
                if (tlo <= thi).all():
                    lo, hi = np.minimum(lo, tlo), np.maximum(hi, thi)
        self.bounds = (lo, hi)
        view = data.view or (30.0, 20.0)
        azimuth = o.azimuth if o.azimuth is not None else view[0]
        elevation = o.elevation if o.elevation is not None else view[1]
        ss = o.supersample
        if camera is not None:
            if (camera.width, camera.height) != (o.width * ss, o.height * ss):
                raise ValueError(f"camera of {camera.width} x {camera.height} pixels is not allowed: the picture is "
                                 f"{o.width * ss} x {o.height * ss} (width x height x supersample)")
            self.camera = camera
        else:
            self.camera = auto_camera(lo, hi, o.width * ss, o.height * ss, azimuth, elevation, o.fov, o.zoom)
        # Lights (world space): a key light from above, over the camera's left shoulder; a fill.
        cam = self.camera
        flat_fwd = cam.forward * np.array([1.0, 0.0, 1.0])
        flat_fwd = flat_fwd / (np.linalg.norm(flat_fwd) or 1.0)
        key = -0.55 * cam.right - 0.45 * flat_fwd + np.array([0.0, 1.0, 0.0])
        self.key = key / np.linalg.norm(key)
        fill = 0.8 * cam.right - 0.6 * flat_fwd + np.array([0.0, 0.35, 0.0])
        self.fill = fill / np.linalg.norm(fill)
        scalar = o.color in ("alpha", "singular_values")
        self.color_range = (color_range or self._color_range()) if scalar else None
        self._rays = cam.pixel_rays()
        self._rays32 = self._rays.reshape(-1, 3).astype(np.float32)
        self._static_cache = None
        size = float(np.linalg.norm(self.particle_bounds[1] - self.particle_bounds[0]))
        self.scene_size = max(size, 1e-3)
        self.scene_center = 0.5 * (self.particle_bounds[0] + self.particle_bounds[1])

    # ------------------------------------------------------------------ colours
    def _color_range(self) -> tuple[float, float]:
        key = self.options.color
        values = [self.data.particles(f)[key] for f in self.frames]
        v = np.concatenate(values) if values else np.zeros(1)
        v = v[np.isfinite(v)]
        if v.size == 0:
            return 0.0, 1.0
        top = float(np.percentile(v, 99.5))
        return 0.0, top if top > 1e-6 else 1.0

    def _particle_colors(self, parts: dict) -> np.ndarray:
        mode = self.options.color
        if mode == "body":
            return BODY_PALETTE[parts["body"] % len(BODY_PALETTE)]
        if mode == "material":
            cols = np.array(self.data.display_colors, dtype=np.float32)
            return cols[parts["body"]]
        lo, hi = self.color_range
        return colormap((parts[mode] - lo) / (hi - lo))

    # ------------------------------------------------------------------ shadows
    def _shadow_map(self, pts, rad, meshes=(), median_rad=None):
        """Depth seen from the key light (orthographic) of the particles ``pts`` (spheres of
        radius ``rad``) and the surfaces ``meshes`` ((vertices, triangles) pairs)."""
        L = self.key
        a = np.cross(L, [0.0, 0.0, 1.0] if abs(L[2]) < 0.9 else [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(L, a)
        u, v, d = pts @ a, pts @ b, -(pts @ L)
        mu = [m[0] @ a for m in meshes]
        mv = [m[0] @ b for m in meshes]
        md = [-(m[0] @ L) for m in meshes]
        rmax = float(rad.max()) if len(rad) else 0.0
        median_rad = float(np.median(rad)) if median_rad is None else median_rad
        texel = max(median_rad * 0.5, 1e-6)
        uall, vall = np.concatenate([u, *mu]), np.concatenate([v, *mv])
        u0, v0 = uall.min() - 2 * rmax - texel, vall.min() - 2 * rmax - texel
        u1, v1 = uall.max() + 2 * rmax + texel, vall.max() + 2 * rmax + texel
        nu = int(min(2048, math.ceil((u1 - u0) / texel) + 1))
        nv = int(min(2048, math.ceil((v1 - v0) / texel) + 1))
        texel = max((u1 - u0) / (nu - 1), (v1 - v0) / (nv - 1), texel)
        zbuf = np.full(nu * nv, np.inf, dtype=np.float32)
        if len(pts):
            px, py = (u - u0) / texel, (v - v0) / texel
            pix, dep, _, _, _ = splat_spheres(px, py, d, rad / texel, rad, nu, nv, max_radius=32)
            np.minimum.at(zbuf, pix, dep)
        for (_, tri), mu_k, mv_k, md_k in zip(meshes, mu, mv, md):
            pix, dep, _, _ = raster_triangles((mu_k - u0) / texel, (mv_k - v0) / texel, md_k, tri, nu, nv,
                                              perspective=False)
            np.minimum.at(zbuf, pix, dep)
        zpad = np.full((nv + 2, nu + 2), np.inf, dtype=np.float32)
        zpad[1:-1, 1:-1] = zbuf.reshape(nv, nu)
        return {"a": a, "b": b, "u0": u0, "v0": v0, "texel": texel, "shape": (nv, nu), "zpad": zpad.reshape(-1),
                "zmin": float(zbuf.min())}

    def _lit_fraction(self, smap, P, bias):
        """Fraction of the key light reaching world points ``P`` (3 x 3 PCF on the shadow map)."""
        lit = np.ones(len(P), dtype=np.float32)
        if smap is None or len(P) == 0:
            return lit
        x = (P @ smap["a"] - smap["u0"]) / smap["texel"]
        y = (P @ smap["b"] - smap["v0"]) / smap["texel"]
        d = -(P @ self.key) - bias
        nv, nu = smap["shape"]
        # Only points over the map and behind its nearest particle can be in shadow.
        cand = np.nonzero((x > -1) & (x < nu + 1) & (y > -1) & (y < nv + 1) & (d > smap["zmin"]))[0]
        if len(cand) == 0:
            return lit
        xi = np.floor(x[cand]).astype(np.int64)
        yi = np.floor(y[cand]).astype(np.int64)
        dc = d[cand]
        zpad = smap["zpad"]  # the map with a border of +inf, so the 3 x 3 taps need no tests
        xi = np.clip(xi + 1, 0, nu + 1)
        yi = np.clip(yi + 1, 0, nv + 1)
        count = np.zeros(len(cand), dtype=np.float32)
        for dy in (-1, 0, 1):
            rows = np.clip(yi + dy, 0, nv + 1) * (nu + 2)
            for dx in (-1, 0, 1):
                count += dc <= zpad[rows + np.clip(xi + dx, 0, nu + 1)]
        lit[cand] = count / 9.0
        return lit

    def _collider_shadow(self, P):
        """1 where the key light reaches ``P`` past the sphere and box colliders, else 0."""
        L = self.key
        lit = np.ones(len(P), dtype=bool)
        for c in self.data.colliders:
            if c.kind == "sphere":
                oc = P - c.center
                b = oc @ L
                cc = np.einsum("ij,ij->i", oc, oc) - c.size[0] ** 2
                disc = b * b - cc
                t = -b + np.sqrt(np.maximum(disc, 0.0))
                lit &= ~((disc > 0) & (t > 1e-4) & (cc > 1e-6))
            elif c.kind == "box":
                with np.errstate(divide="ignore", invalid="ignore"):
                    inv = 1.0 / np.where(np.abs(L) > 1e-12, L, 1e-12)
                t1 = (c.center - c.size - P) * inv
                t2 = (c.center + c.size - P) * inv
                tn = np.minimum(t1, t2).max(axis=1)
                tf = np.maximum(t1, t2).min(axis=1)
                lit &= ~((tf >= np.maximum(tn, 1e-4)))
        return lit.astype(np.float32)

    # ------------------------------------------------------------------ tools
    def tool_meshes(self, frame: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """``(world vertices (V, 3) float32, triangles)`` of each non-plane tool at ``frame``."""
        out = []
        for k, shape in self._tool_shapes:
            if shape is None:
                continue
            p, q = self.data.tools[k].pose(frame)
            v = shape[0] @ quat_matrix(q).T + p
            out.append((v.astype(np.float32), shape[1]))
        return out

    def tool_planes(self, frame: int) -> list[Collider]:
        """The plane tools at ``frame``, as plane colliders."""
        return [_tool_plane(t, *t.pose(frame)) for t in self.data.tools if t.kind == "plane"]

    # ------------------------------------------------------------------ one frame
    def _static(self, planes=()):
        """The colliders (and ``planes``: plane tools at this frame), ray cast: everything but
        the particles' shadows. Kept while the planes stay where they are (a static floor tool
        is ray cast once per renderer, a moving plate every frame)."""
        plane_key = tuple((tuple(c.center), tuple(c.normal)) for c in planes)
        if getattr(self, "_static_cache", None) is not None and self._static_key == plane_key:
            return self._static_cache
        cam = self.camera
        W, H = cam.width, cam.height
        rays = self._rays.reshape(-1, 3).astype(np.float32)
        tgrad = np.linspace(0.0, 1.0, H, dtype=np.float32)[:, None, None]
        bg = _linear(_BACKGROUND_TOP) * (1 - tgrad) + _linear(_BACKGROUND_BOTTOM) * tgrad
        background = np.ascontiguousarray(np.broadcast_to(bg, (H, W, 3)).reshape(-1, 3))
        zbuf = np.full(H * W, np.inf, dtype=np.float32)
        # Per pixel hit by a collider: its kind's surface point, normal, colour and fade.
        hits = []
        for c in [*self.data.colliders, *planes]:
            hit = self._plane_hits(c, rays, zbuf) if c.kind == "plane" else self._solid_hits(c, rays, zbuf)
            if hit is not None:
                hits.append(hit)
        owner = np.full(H * W, -1, dtype=np.int32)
        for k, (idx, z, *_rest) in enumerate(hits):
            closer = z < zbuf[idx]
            zbuf[idx[closer]] = z[closer]
            owner[idx[closer]] = k
        image = background.copy()
        idx_all, P_all, ambient_all, key_all, fade_all = [], [], [], [], []
        for k, (idx, z, P, normal, base, fade, specular) in enumerate(hits):
            keep = owner[idx] == k
            idx, P, base, fade = idx[keep], P[keep], base[keep], fade[keep]
            normal = normal if normal.ndim == 1 else normal[keep]
            if len(idx) == 0:
                continue
            eye_dir = cam.eye.astype(np.float32) - P
            eye_dir /= np.linalg.norm(eye_dir, axis=1, keepdims=True)
            ambient, key = self._shade_parts(base, normal, eye_dir, specular)
            key = key * self._collider_shadow(P)[:, None]
            f = fade[:, None]
            image[idx] = (ambient + key) * (1 - f) + background[idx] * f
            idx_all.append(idx)
            P_all.append(P)
            ambient_all.append(ambient)
            key_all.append(key * (1 - f))
            fade_all.append(f)
        cat = (lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape, np.float32))
        static = {
            "background": background, "image": image, "zbuf": zbuf,
            "idx": cat(idx_all, (0,)).astype(np.int64), "P": cat(P_all, (0, 3)), "key": cat(key_all, (0, 3)),
        }
        self._static_cache, self._static_key = static, plane_key
        return static

    def surfaces(self, frame: int) -> dict:
        """``{body: (vertices, triangles)}`` of the bodies drawn as surfaces at ``frame``: those
        whose file holds a non-empty surface there, unless ``options.surfaces`` is off."""
        if not self.options.surfaces:
            return {}
        out = {}
        for k in range(len(self.data.bodies)):
            mesh = self.data.surface(frame, k)
            if mesh is not None:
                out[k] = mesh
        return out

    def _mesh_colors(self, body: int, vertices, parts) -> np.ndarray:
        """sRGB per vertex (V, 3) of body ``body``'s surface, as its particles are coloured."""
        mode = self.options.color
        if mode == "body":
            return np.broadcast_to(BODY_PALETTE[body % len(BODY_PALETTE)], vertices.shape)
        if mode == "material":
            return np.broadcast_to(np.asarray(self.data.display_colors[body], np.float32), vertices.shape)
        mine = parts["body"] == body
        rad = parts["radius"][mine]
        reach = 4.0 * float(np.median(rad)) if len(rad) else 1.0  # the surface field's support, 2 spacings
        lo, hi = self.color_range
        return colormap((vertex_values(vertices, parts["points"][mine], parts[mode][mine], reach) - lo) / (hi - lo))

    def render(self, frame: int) -> Image.Image:
        """The picture of ``frame`` (a frame index of the file)."""
        o, cam = self.options, self.camera
        W, H = cam.width, cam.height
        frame = self.data.resolve(frame)
        parts = self.data.particles(frame)
        meshes = self.surfaces(frame)
        tool_meshes = self.tool_meshes(frame)
        static = self._static(self.tool_planes(frame))
        zbuf = static["zbuf"].copy()
        image = static["image"].copy()
        rad_all = (parts["radius"] * o.radius_scale).astype(np.float32)
        # A body with a surface is drawn as that surface instead of its particles.
        drawn = ~np.isin(parts["body"], list(meshes)) if meshes else np.ones(len(rad_all), bool)
        pts = parts["points"][drawn].astype(np.float32)
        rad = rad_all[drawn]
        median_rad = float(np.median(rad_all)) if len(rad_all) else 0.0
        casters = list(meshes.values()) + tool_meshes
        smap = self._shadow_map(pts, rad, casters, median_rad) if (o.shadows and (len(pts) or casters)) else None
        bias = 1.5 * median_rad

        # ---- the particles' shadows on the colliders: take the key light away where blocked
        if smap is not None and len(static["idx"]):
            sidx, P = static["idx"], static["P"]
            lit = self._lit_fraction(smap, P, 0.25 * bias)
            dark = lit < 1.0
            image[sidx[dark]] -= static["key"][dark] * (1.0 - lit[dark])[:, None]

        # ---- fragments: particles splatted, surfaces rasterised; one z-buffer for both
        sphere_frags = None
        if len(pts):
            px, py, z = cam.project(pts)
            idx = np.nonzero(z > 1e-3)[0]
            zi = z[idx].astype(np.float32)
            rp = (cam.focal * rad[idx] / zi).astype(np.float32)
            pix, dep, ux, uy, who = splat_spheres(px[idx], py[idx], zi, rp, rad[idx], W, H)
            np.minimum.at(zbuf, pix, dep)
            sphere_frags = (pix, dep, ux, uy, idx[who])
        mesh_frags = []
        for body, (v, tri) in meshes.items():
            px, py, z = cam.project(v)
            pix, dep, bary, t = raster_triangles(px, py, z, tri, W, H)
            np.minimum.at(zbuf, pix, dep)
            mesh_frags.append((body, v, tri, pix, dep, bary, t))
        for v, tri in tool_meshes:
            px, py, z = cam.project(v)
            pix, dep, bary, t = raster_triangles(px, py, z, tri, W, H)
            np.minimum.at(zbuf, pix, dep)
            mesh_frags.append((None, v, tri, pix, dep, bary, t))

        rays = self._rays32
        eye = cam.eye.astype(np.float32)

        def light(pix, dep, normal, base, specular, normal_offset=0.0):
            P = eye + dep[:, None] * rays[pix]
            eye_dir = -rays[pix]
            eye_dir /= np.linalg.norm(eye_dir, axis=1, keepdims=True)
            ambient, key = self._shade_parts(base, normal, eye_dir, specular)
            if smap is not None:
                # A flat surface at a grazing angle to the light crosses the shadow map's depth
                # steps (stripes, "shadow acne"): look it up a little way out along its normal.
                lit = self._lit_fraction(smap, P + np.float32(normal_offset * smap["texel"]) * normal, bias)
            else:
                lit = np.ones(len(P), np.float32)
            if self.data.colliders:
                lit = lit * self._collider_shadow(P)
            image[pix] = ambient + key * lit[:, None]

        if sphere_frags is not None:
            pix, dep, ux, uy, who = sphere_frags
            win = dep <= zbuf[pix]
            pix, dep, ux, uy, who = pix[win], dep[win], ux[win], uy[win], who[win]
            uz = np.sqrt(np.clip(1.0 - ux * ux - uy * uy, 0.0, 1.0))
            right, up, fwd = (v.astype(np.float32) for v in (cam.right, cam.true_up, cam.forward))
            normal = ux[:, None] * right + uy[:, None] * up - uz[:, None] * fwd
            base = _linear(self._particle_colors({k: a[drawn] for k, a in parts.items()}))[who]
            light(pix, dep, normal, base, 0.25)
        for body, v, tri, pix, dep, bary, t in mesh_frags:
            win = dep <= zbuf[pix]
            pix, dep, bary, t = pix[win], dep[win], bary[win], t[win]
            face, corner = mesh_normals(v, tri)
            normal = np.einsum("nk,nkj->nj", bary, corner[t])
            normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
            # Seen from behind (an open or inside-out mesh): shade the side that faces the eye.
            back = np.einsum("nj,nj->n", face[t], rays[pix]) > 0
            normal[back] = -normal[back]
            if body is None:  # a tool: steel, a sharper highlight
                base = np.broadcast_to(_linear(_TOOL), (len(pix), 3)).astype(np.float32)
                light(pix, dep, normal.astype(np.float32), base, 0.35, normal_offset=2.0)
                continue
            colors = _linear(self._mesh_colors(body, v, parts)).astype(np.float32)
            base = np.einsum("nk,nkj->nj", bary, colors[tri[t]])
            light(pix, dep, normal.astype(np.float32), base.astype(np.float32), 0.25, normal_offset=2.0)

        img = Image.fromarray(_to_srgb8(image.reshape(H, W, 3)), "RGB")
        if o.supersample > 1:
            img = img.reduce(o.supersample)
        if o.label or self.color_range is not None:
            self._annotate(img, frame)
        return img

    def _shade_parts(self, base, normal, eye_dir, specular, shininess=40.0):
        """Linear RGB of surface points in two parts: what the key light adds, and the rest."""
        key_dir = self.key.astype(np.float32)
        h = key_dir + eye_dir
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        if normal.ndim == 1:  # one normal for all points (a plane)
            nk = np.float32(max(normal @ key_dir, 0.0))
            nf = np.float32(max(normal @ self.fill.astype(np.float32), 0.0))
            sky = np.float32(0.5 + 0.5 * normal[1])
            spec = np.power(np.clip(h @ normal, 0.0, 1.0), shininess)
            ambient = base * np.float32(0.22 + 0.13 * sky + 0.18 * nf)
            key = base * np.float32(0.75 * nk) + specular * spec[:, None]
            return ambient.astype(np.float32), key.astype(np.float32)
        nk = np.clip(normal @ key_dir, 0.0, 1.0)
        nf = np.clip(normal @ self.fill.astype(np.float32), 0.0, 1.0)
        sky = 0.5 + 0.5 * normal[:, 1]  # hemisphere ambient
        spec = np.power(np.clip(np.einsum("ij,ij->i", normal, h), 0.0, 1.0), shininess)
        ambient = base * (0.22 + 0.13 * sky + 0.18 * nf)[:, None]
        key = base * (0.75 * nk)[:, None] + specular * spec[:, None]
        return ambient.astype(np.float32), key.astype(np.float32)

    def _plane_hits(self, c: Collider, rays, zbuf):
        cam = self.camera
        n = c.normal
        if n @ cam.eye <= c.offset:  # the camera is inside the solid: the plane would hide all
            return None
        # Component arrays: (N,) operations are much faster than (N, 3) @ (3,) here.
        rx, ry, rz = (np.ascontiguousarray(rays[:, k]) for k in range(3))
        denom = rx * np.float32(n[0]) + ry * np.float32(n[1]) + rz * np.float32(n[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.float32(c.offset - n @ cam.eye) / denom
        idx = np.nonzero(np.isfinite(z) & (z > 1e-4))[0]
        z = z[idx]
        e = cam.eye.astype(np.float32)
        Px, Py, Pz = e[0] + z * rx[idx], e[1] + z * ry[idx], e[2] + z * rz[idx]
        cc = c.center.astype(np.float32)
        half = np.float32(c.size[0] * 1.001 + 1e-9)
        inside = (np.abs(Px - cc[0]) <= half) & (np.abs(Py - cc[1]) <= half) & (np.abs(Pz - cc[2]) <= half)  # the USD quad
        # Fade into the background away from the scene.
        sc = self.scene_center.astype(np.float32)
        dx, dy, dz = Px - sc[0], Py - sc[1], Pz - sc[2]
        dn = dx * np.float32(n[0]) + dy * np.float32(n[1]) + dz * np.float32(n[2])
        r = np.sqrt(np.maximum(dx * dx + dy * dy + dz * dz - dn * dn, 0.0))
        r0, r1 = 0.9 * self.scene_size, 2.2 * self.scene_size
        f = np.clip((r - np.float32(r0)) / np.float32(r1 - r0), 0.0, 1.0)
        fade = f * f * (3 - 2 * f)
        keep = inside & (fade < 0.999)
        idx, z, fade = idx[keep], z[keep], fade[keep].astype(np.float32)
        Px, Py, Pz = Px[keep], Py[keep], Pz[keep]
        # Checker in the plane's own coordinates, tiles of a round size ~ 1/8 of the scene.
        t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 0.0, 1.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        tile = _nice(self.scene_size / 8.0)
        u1, u2 = (t1 / tile).astype(np.float32), (t2 / tile).astype(np.float32)
        a = np.floor(Px * u1[0] + Py * u1[1] + Pz * u1[2]).astype(np.int64)
        b = np.floor(Px * u2[0] + Py * u2[1] + Pz * u2[2]).astype(np.int64)
        even = ((a + b) % 2 == 0)[:, None]
        base = np.where(even, _linear(_FLOOR[0]), _linear(_FLOOR[1])).astype(np.float32)
        P = np.stack([Px, Py, Pz], axis=1)
        return idx, z, P, n.astype(np.float32), base, fade, 0.05

    def _solid_hits(self, c: Collider, rays, zbuf):
        e = self.camera.eye
        if c.kind == "sphere":
            oc = e - c.center
            A = np.einsum("ij,ij->i", rays, rays)
            B = 2.0 * (rays @ oc.astype(np.float32))
            C = oc @ oc - c.size[0] ** 2
            disc = B * B - 4 * A * C
            idx = np.nonzero(disc > 0)[0]
            z = (-B[idx] - np.sqrt(disc[idx])) / (2 * A[idx])
            keep = z > 1e-4
            idx, z = idx[keep], z[keep]
            P = e.astype(np.float32) + z[:, None] * rays[idx]
            normal = ((P - c.center) / c.size[0]).astype(np.float32)
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / np.where(np.abs(rays) > 1e-12, rays, 1e-12)
            t1 = (c.center - c.size - e).astype(np.float32) * inv
            t2 = (c.center + c.size - e).astype(np.float32) * inv
            tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
            tn, tf = tmin.max(axis=1), tmax.min(axis=1)
            idx = np.nonzero((tf >= tn) & (tn > 1e-4))[0]
            z = tn[idx]
            axis = tmin[idx].argmax(axis=1)
            P = e.astype(np.float32) + z[:, None] * rays[idx]
            rows = np.arange(len(idx))
            normal = np.zeros((len(idx), 3), np.float32)
            normal[rows, axis] = np.sign(P[rows, axis] - c.center[axis])
        if len(idx) == 0:
            return None
        base = np.broadcast_to(_linear(_COLLIDER), P.shape).astype(np.float32)
        return idx, z.astype(np.float32), P, normal, base, np.zeros(len(idx), np.float32), 0.3

    def _annotate(self, img: Image.Image, frame: int):
        draw = ImageDraw.Draw(img)
        font = _font(max(10, img.height // 40))
        if self.options.label:
            text = f"t = {frame / self.data.fps:.2f} s  (frame {frame})"
            draw.text((8, 6), text, fill=(40, 40, 48), font=font)
        if self.color_range is not None:
            lo, hi = self.color_range
            bw, bh = max(10, img.width // 60), img.height // 3
            x0, y0 = img.width - bw - 12, img.height - bh - 16
            ramp = colormap(np.linspace(1.0, 0.0, bh))
            bar = (np.repeat(ramp[:, None, :], bw, axis=1) * 255).astype(np.uint8)
            img.paste(Image.fromarray(bar, "RGB"), (x0, y0))
            draw.rectangle([x0 - 1, y0 - 1, x0 + bw, y0 + bh], outline=(60, 60, 60))
            name = "alpha" if self.options.color == "alpha" else "max|ln s|"
            for value, y in ((hi, y0), (lo, y0 + bh)):
                label = f"{value:.3g}"
                w = draw.textlength(label, font=font)
                draw.text((x0 - 6 - w, y - font.size // 2), label, fill=(40, 40, 48), font=font)
            w = draw.textlength(name, font=font)
            draw.text((x0 + bw - w, y0 - font.size - 6), name, fill=(40, 40, 48), font=font)


def _nice(x: float) -> float:
    """1, 2 or 5 times a power of ten, near ``x``."""
    if not x > 0:
        return 1.0
    e = math.floor(math.log10(x))
    m = x / 10**e
    return (1 if m < 1.5 else 2 if m < 3.5 else 5 if m < 7.5 else 10) * 10**e


def _font(size: int):
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: a fixed bitmap font
        return ImageFont.load_default()


# ----------------------------------------------------------------------------- frames / output
def output_kind(output, what: str = "output") -> str:
    """'png', 'gif', 'mp4' or 'dir' from an output name (no extension: a folder); ``what``
    names it in a refusal."""
    name = os.fspath(output)
    ext = os.path.splitext(name)[1].lower()
    if not ext or name.endswith(os.sep):
        return "dir"
    if ext not in OUTPUT_EXTENSIONS:
        raise ValueError(f"{what} = {name!r} is not allowed: the extension must be one of {', '.join(OUTPUT_EXTENSIONS)}, "
                         f"or no extension for a folder of PNG frames")
    return ext[1:]


def ffmpeg_path() -> str | None:
    """The ``ffmpeg`` on the PATH, else the one the ``imageio-ffmpeg`` wheel bundles
    (``pip install 'warp-esph[mp4]'``), else ``None``."""
    found = shutil.which("ffmpeg")
    if found is not None:
        return found
    try:
        import imageio_ffmpeg  # noqa: PLC0415
    except ImportError:
        return None
    try:
        return imageio_ffmpeg.get_ffmpeg_exe()
    except RuntimeError:  # the wheel has no binary for this platform
        return None


def _sheet(images: list[Image.Image], columns: int) -> Image.Image:
    w, h = images[0].size
    rows = math.ceil(len(images) / columns)
    sheet = Image.new("RGB", (columns * w, rows * h), (255, 255, 255))
    for k, im in enumerate(images):
        sheet.paste(im, ((k % columns) * w, (k // columns) * h))
    return sheet


#: The shortest GIF frame most viewers show as given (shorter ones are slowed, often to 100 ms).
GIF_MIN_FRAME_MS = 20


def gif_durations(count: int, fps: float, what: str = "fps") -> list[int]:
    """Each GIF frame's duration (ms) for playback at ``fps``: a GIF stores centiseconds, so
    one duration for all (33 ms at 30 fps, stored 30) played 11 % fast; the frames' ends
    rounded to 10 ms instead keep the rate on average (30, 40, 30, ...). Above 50 fps a
    frame would be shorter than ``GIF_MIN_FRAME_MS``: it plays at 50 fps, and a warning
    says so (an .mp4 keeps any rate); ``what`` names the rate in it."""
    import warnings  # noqa: PLC0415

    frame_ms = 1000.0 / fps
    if frame_ms < GIF_MIN_FRAME_MS:
        warnings.warn(f"{what} = {fps:g}: a GIF's frames last at least {GIF_MIN_FRAME_MS} ms, so it plays at "
                      f"{1000.0 / GIF_MIN_FRAME_MS:g} fps, {1000.0 / GIF_MIN_FRAME_MS / fps:.2f} x the rate asked "
                      "(write .mp4 to keep it)", RuntimeWarning, stacklevel=3)
        return [GIF_MIN_FRAME_MS] * count
    ends = [10 * round(k * frame_ms / 10.0) for k in range(count + 1)]
    return [max(GIF_MIN_FRAME_MS, b - a) for a, b in zip(ends, ends[1:])]


@dataclasses.dataclass
class RenderResult:
    output: str
    kind: str
    frames: list[int]
    files: list[str]
    seconds: float
    particles: int
    #: Bodies drawn as surface meshes in the first frame (0: particles only).
    surface_bodies: int = 0

    @property
    def seconds_per_frame(self) -> float:
        return self.seconds / max(len(self.frames), 1)


#: Playback rates a GIF or MP4 can hold (``render_usd(fps=...)``, ``warp-esph render --fps``).
FPS_RANGE = (0.01, 1000.0)
#: The largest contact sheet (a .png of several frames) in pixels: 6e8 bytes of RGB.
MAX_SHEET_PIXELS = 2.0e8


def render_usd(path, output=None, frames=None, *, color: str = "body", width: int = 800, height: int = 600,
               supersample: int = 2, radius_scale: float = 1.0, azimuth: float | None = None,
               elevation: float | None = None, zoom: float = 1.0, fov: float = 30.0, label: bool = True,
               shadows: bool = True, columns: int | None = None, fps: float | None = None, fit: str = "all",
               surfaces: bool = True, progress=None, flag=None, clear: bool = False) -> RenderResult:
    """Render frames of a ``UsdWriter`` file.

    ``output``: a folder (no extension; PNG per frame, ``frame_00012.png``; created, but not its
    parents: a missing parent folder is a ``ValueError``, as for a file), a ``.png``
    (one frame; several frames side by side, ``columns`` per row), a ``.gif`` or an
    ``.mp4`` (needs ``ffmpeg`` on the PATH; H.264 needs an even width and height, so an odd one is
    padded by one pixel, a copy of the last column or row). Default: ``<file>.png`` beside the USD file (``a.usdc.png``).
    ``frames``: see ``parse_frames``; default all frames, or the last one for a ``.png``; a
    frame named twice is refused except in a ``.gif`` or ``.mp4``, which holds it.
    ``fps``: playback rate of a GIF/MP4 (default: the file's). ``fit``: ``"all"`` frames the
    bounds of all chosen frames with one camera (the default: motion reads correctly),
    ``"each"`` frames every picture on its own (the same view direction, its own
    distance). ``surfaces``: draw a body's surface mesh (``warp-esph run --surface``) instead
    of its particles where the file holds one (``False``: always particles). ``progress(k, n)``
    is called after each frame. ``flag(name)``: how a refusal names the option ``name``
    (default: the parameter's name; the CLI's ``--radius-scale`` for ``radius_scale``). A Ctrl-C
    raises a ``KeyboardInterrupt`` whose ``kept`` says which pictures are written whole
    (``checks.interrupted``). ``clear`` (the CLI's): for a folder, first remove the
    ``frame_NNNNN.png`` an earlier render left there (no other file), once the options are
    checked, so that the folder holds this render's pictures alone.
    """
    flag = flag or _same_name
    data = UsdFrames(path)
    given = output is not None
    if output is None:
        output = data.path + ".png"  # the whole name: a.usdc and a.usda must not share a.png
    if not isinstance(output, (str, os.PathLike)):  # 123: a TypeError before
        raise ValueError(f"{flag('output')} = {checks.shorten(output)!r} is not allowed: must be a path")
    out = os.fspath(output)
    if progress is not None and not callable(progress):  # 5 failed after the first frame was written
        raise ValueError(f"progress = {checks.shorten(progress)!r} is not allowed: must be callable as progress(k, n)")
    kind = output_kind(out, flag("output"))
    if kind == "mp4" and ffmpeg_path() is None:
        raise ValueError(f"{flag('output')} = {checks.shown_path(out)} is not allowed: writing .mp4 needs the ffmpeg program, which is not on "
                         f"this machine's PATH (install it, e.g. 'apt-get install ffmpeg', or pip install 'warp-esph[mp4]'); write a .gif or a folder "
                         f"of PNG frames instead")
    # Options of another kind of output: refused, not ignored (a .png took --fps, a .gif
    # --columns, and drew as without them). An output not given is not named as if it had
    # been ('with --output = ...' to a command line that typed no --output).
    named = f"{flag('output')} = {checks.shown_path(out)}" if given else f"the default output {checks.shown_path(out, False)}"
    if fps is not None and kind not in ("gif", "mp4"):
        raise ValueError(f"{flag('fps')} = {checks.shorten(fps)!r} is not allowed with {named}: it is the playback rate of a .gif or "
                         f".mp4, and {'a folder of PNG frames' if kind == 'dir' else 'a .png'} has none")
    if columns is not None and kind != "png":
        raise ValueError(f"{flag('columns')} = {checks.shorten(columns)!r} is not allowed with {named}: it lays several frames out "
                         f"side by side in one .png, and a {'folder' if kind == 'dir' else '.' + kind} holds them "
                         f"one after another")
    given_frames = frames is not None
    if frames is None and kind == "png":
        frames = "last"
    # An animation may repeat a frame on purpose (holding it); a sheet or a folder of pictures
    # drew it twice, or wrote it once while the rest was drawn as asked.
    chosen = parse_frames(frames, data.frames, flag("frames"), repeats=kind in ("gif", "mp4"))
    options = RenderOptions(width=width, height=height, color=color, supersample=supersample, radius_scale=radius_scale,
                            azimuth=azimuth, elevation=elevation, zoom=zoom, fov=fov, label=label, shadows=shadows,
                            surfaces=surfaces, flag=flag)
    # A GIF frame lasts at most 655.35 s and an MP4's rate must be one ffmpeg can hold:
    # 1e-9 fps ended in an OverflowError inside the GIF writer.
    playback = checks.in_range(flag("fps"), fps, FPS_RANGE[0], FPS_RANGE[1]) if fps is not None else data.fps
    if columns is not None:
        columns = checks.positive_int(flag("columns"), columns)
        if len(chosen) == 1:
            # A sheet of one frame: '-o grid.png --columns 3' drew the last frame alone, as
            # without the option, and said it had written the picture asked for.
            # A file of one frame has no several to choose: '--frames all' was told to give
            # '--frames all' for several.
            if len(data.frames) == 1:
                which = f"the file holds one frame (frame {chosen[0]}); leave {flag('columns')} out"
            elif given_frames:
                which = (f"{flag('frames')} = {checks.shorten(frames)!r} chooses one (frame {chosen[0]}); choose several "
                         f"(e.g. {flag('frames')} all)")
            else:
                which = (f"a .png without {flag('frames')} is the last frame alone (frame {chosen[0]}); give {flag('frames')} "
                         f"for several (e.g. {flag('frames')} all)")
            raise ValueError(f"{flag('columns')} = {checks.shorten(columns)!r} is not allowed with one frame: it lays several frames "
                             f"out side by side, and {which}")
    sheet_columns = min(columns or 4, len(chosen))
    if kind == "png" and len(chosen) > 1:
        # One picture holds them all: refused before drawing where it would not fit in memory
        # (a million columns asked for a sheet of 8e8 x 600 pixels).
        rows = math.ceil(len(chosen) / sheet_columns)
        size = (sheet_columns * options.width, rows * options.height)
        if size[0] * size[1] > MAX_SHEET_PIXELS:
            raise ValueError(f"{flag('frames')} = {checks.shorten(frames)!r} is not allowed in one .png: {len(chosen)} frames of {options.width} x "
                             f"{options.height} in {sheet_columns} columns make a {size[0]} x {size[1]} picture, more than "
                             f"{MAX_SHEET_PIXELS:.0e} pixels; choose fewer frames, or write a folder, a .gif or an .mp4")
    _check_pixels(options, flag)
    if kind == "gif":
        # Every frame is held until the file is written (RGB, then its palette copy): 10000
        # frames of 800 x 600 asked 19 GiB, after all of them had been drawn.
        need, have = len(chosen) * options.width * options.height * 4, _machine_memory()
        if have is not None and need > have:
            raise ValueError(f"{flag('frames')} = {checks.shorten(frames)!r} is not allowed in one .gif: {len(chosen)} frames of "
                             f"{options.width} x {options.height} are held together until it is written, about "
                             f"{need / 2**30:.3g} GiB, more than the {have / 2**30:.3g} GiB available; choose fewer frames "
                             f"or a smaller picture, or write a folder or an .mp4")
    # Before any frame is drawn: a folder in the way, or a place that takes no file.
    checks.output_place(flag("output"), out, folder=kind == "dir")
    if kind == "dir":
        checks.output_files(flag("output"), out, [f"frame_{f:05d}.png" for f in chosen])
        os.makedirs(out, exist_ok=True)

    checks.choice(flag("fit"), fit, ("all", "each"))
    t0 = time.perf_counter()
    renderer = Renderer(data, chosen, options)
    shared_range = renderer.color_range
    if clear and kind == "dir":
        # Once every option is checked: a refused render left the earlier pictures as they were.
        checks.remove_frame_files(out, "png")
    files: list[str] = []
    images: list[Image.Image] = []
    count = 0
    surface_bodies = 0
    writer = None
    # The movie is written beside its name and renamed over it once ffmpeg has finished (an
    # error or interrupt removes it): written in place, an interrupted render left a shorter
    # movie over an earlier one.
    f = None
    with contextlib.ExitStack() as movie:
        try:
            for k, f in enumerate(chosen):
                if fit == "each" and len(chosen) > 1:
                    renderer = Renderer(data, [f], options, color_range=shared_range)
                img = renderer.render(f)
                if k == 0:
                    count = len(data.particles(f)["points"])
                    surface_bodies = len(renderer.surfaces(f))
                if kind == "dir":
                    # Each picture whole or not at all: Ctrl-C inside a save left a truncated PNG,
                    # over the same frame of an earlier render too.
                    file = os.path.join(out, f"frame_{f:05d}.png")
                    try:
                        with checks.replaced_atomically(file) as part:
                            _save_image(img, part, format="PNG", optimize=True)
                    except OSError as e:
                        # A full disk: exit 2, 'bad input', with the bare errno, before.
                        raise checks.OutputWriteError(f"cannot write {checks.shown_path(file, False)}: {e.strerror or e} ({len(files)} of the "
                                                      f"{len(chosen)} frames are written whole in {checks.shown_path(out, False)})", e) from e
                    files.append(file)
                elif kind == "mp4":
                    if writer is None:
                        writer = _Mp4Writer(movie.enter_context(checks.replaced_atomically(out)), img.size, playback)
                    writer.write(img)
                else:
                    images.append(img)
                if progress is not None:
                    progress(k + 1, len(chosen))
        except BaseException as e:
            # ffmpeg gets the terminal's Ctrl-C too and fails its close: the interrupt (or the
            # first error) is what happened, not 'ffmpeg failed:'.
            if writer is not None:
                with contextlib.suppress(OSError):
                    writer.close()
            if isinstance(e, KeyboardInterrupt) and getattr(e, "kept", None) is None:
                raise checks.interrupted(_kept(kind, out, files, chosen)) from e
            checks.stopped_writing(e, _kept(kind, out, files, chosen), f)
            raise
        if writer is not None:
            writer.close()
    try:
        if kind == "png":
            img = images[0] if len(images) == 1 else _sheet(images, sheet_columns)
            with checks.replaced_atomically(out) as part:
                _save_image(img, part, format="PNG", optimize=True)
            files.append(out)
        elif kind == "gif":
            pal = [im.quantize(colors=255, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE) for im in images]
            with checks.replaced_atomically(out) as part:
                _save_image(pal[0], part, format="GIF", save_all=True, append_images=pal[1:],
                            duration=gif_durations(len(pal), playback, flag("fps") if fps is not None else "the file's fps"),
                            loop=0, optimize=False, disposal=1)
            files.append(out)
    except KeyboardInterrupt as e:
        raise checks.interrupted(_kept(kind, out, files, chosen)) from e
    except OSError as e:
        raise checks.OutputWriteError(f"cannot write {checks.shown_path(out, False)}: {e.strerror or e} (not written; a file of that name is left as "
                                      "it was)", e) from e
    except Exception as e:
        checks.stopped_writing(e, _kept(kind, out, files, chosen))
        raise
    if kind == "mp4":
        files.append(out)
    return RenderResult(out, kind, chosen, files, time.perf_counter() - t0, count, surface_bodies)


def _save_image(img: Image.Image, path: str, **options) -> None:
    # PIL closes a file it opened itself only on an Exception: a Ctrl-C inside the encoder
    # left the working file open for the garbage collector ('unclosed file <...part.png>').
    with open(path, "wb") as fh:
        img.save(fh, **options)


def _kept(kind: str, out: str, files: list[str], chosen: list[int]) -> str:
    """What an interrupted render leaves: the pictures of a folder written whole, or one file
    not written (each is renamed over its name only once whole)."""
    if kind == "dir":
        return f"{len(files)} of the {len(chosen)} frames are written whole in {out}"
    return f"{out} is not written (a file of that name is left as it was)"


class _Mp4Writer:
    """Pipes RGB frames into ffmpeg (H.264, yuv420p). yuv420p needs an even width and height:
    an odd one is padded by a copy of the last column or row (cropped before, which dropped
    the picture's edge without a word, a label or colour bar there too)."""

    def __init__(self, path: str, size, fps: float):
        w, h = size
        self.size = (w + w % 2, h + h % 2)
        cmd = [ffmpeg_path(), "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{self.size[0]}x{self.size[1]}",
               "-r", f"{fps:g}", "-i", "-", "-c:v", "libx264", "-pix_fmt", "yuv420p", "-crf", "20",
               # Absolute: ffmpeg takes what precedes a colon in a relative name as a protocol
               # ('take:1.mp4' was 'Protocol not found'), where an absolute path names a file.
               os.path.abspath(path)]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stderr=subprocess.PIPE)

    def write(self, img: Image.Image):
        data = np.asarray(img)
        if img.size != self.size:
            data = np.pad(data, ((0, self.size[1] - img.size[1]), (0, self.size[0] - img.size[0]), (0, 0)), mode="edge")
        try:
            self.proc.stdin.write(np.ascontiguousarray(data).tobytes())
        except BrokenPipeError:  # ffmpeg stopped: its own message says why (close)
            self._failed()

    def close(self):
        if self.proc.stderr.closed:  # closed already (_failed)
            return
        try:
            self.proc.stdin.close()
        except BrokenPipeError:
            self._failed()
        err = self.proc.stderr.read().decode(errors="replace")
        self.proc.stderr.close()
        if self.proc.wait() != 0:
            raise OSError(f"ffmpeg failed: {' '.join(err.split())[:300]}")

    def _failed(self):
        """ffmpeg left before taking every frame: its error, not the pipe's (which would read
        as the command's own output closed)."""
        try:
            self.proc.stdin.close()
        except OSError:  # the frames still buffered for the pipe that is gone
            pass
        err = self.proc.stderr.read().decode(errors="replace")
        self.proc.stderr.close()
        code = self.proc.wait()
        raise OSError(f"ffmpeg failed: {' '.join(err.split())[:300] or f'it exited {code}'}")
