"""Silhouette targets: binary masks from calibrated cameras against a differentiable soft
silhouette of the particles.

Cameras are pinholes in the OpenCV convention: a world point ``X`` is at ``x = R X + t`` in
camera coordinates (``z > 0`` in front, ``y`` down the image), and at pixel
``u = fx x / z + cx``, ``v = fy y / z + cy`` (pixel centres at integer coordinates; the
pixel in row ``j``, column ``i`` of a mask is at ``(u, v) = (i, j)``).

Each particle is a Gaussian splat of opacity ``a0`` and world radius ``radius``: at pixel
``q`` it covers ``a_k(q) = a0 exp(-|q - u_k|^2 / (2 s_k^2))`` with ``s_k = radius sqrt(fx fy)
/ z_k`` pixels, and the soft silhouette is the occupancy

    O(q) = 1 - prod_k (1 - a_k(q)) = 1 - exp(sum_k log(1 - a_k(q)))

(transmittance through independent splats: any number of particles behind one another
saturate at 1, as a mask does). Each particle adds ``log(1 - a_k)`` to the pixels within
4 ``s_k`` of it (beyond, ``a_k < 3.4e-4 a0``), one thread per particle and pixel offset, so
the cost is particles x window area, not particles x pixels. The loss is

    weight * mean over frames of mean over cameras of mean over pixels (O(q) - M(q))^2.

Both kernels are taped; the window (which pixels a particle touches) is an integer choice
without gradient, and a pixel leaving it changes the loss by less than ``(3.4e-4 a0)^2``.

Camera file (JSON)::

    {"cameras": [{"name": "front", "width": 64, "height": 48,
                  "fx": 80, "fy": 80, "cx": 31.5, "cy": 23.5,      # or "K": 3x3
                  "R": [[1,0,0],[0,-1,0],[0,0,-1]], "t": [0, 0.1, 0.6]}],
     "radius": 0.01, "opacity": 0.9}                                 # optional

Masks: an image (PNG, ...) or ``.npy`` ``(height, width)`` for one camera (nonzero or
> 0.5 of the maximum: inside; all zeros: an empty view), or an ``.npz`` with one array per
camera and frame named ``<camera>_<frame>`` (rendered frame index). An image is read by its
grey level (colours: their mean), or by its alpha channel where that varies (a cut-out on a
transparent background); a palette image by its colours. Non-finite values, negative ones
with nothing positive, and a mask of another size than its camera are refused by file name;
so are masks every pixel of which is inside, in every view and frame (no outline anywhere:
they ask only that the body fill every view, whatever its shape). One view the body fills (a
camera close to it) beside others that show its outline is a mask like any other. Splats
that cover every pixel of a camera's image at its first evaluation are refused, naming the
radius (and its camera file), where the radius exceeds the particles' spacing (it is about
half of it): a body that fills a close camera's view with splats of the right size is not.
"""


import dataclasses
import functools
import math
import os
import types
from collections.abc import Mapping, Sequence

import numpy as np
import warp as wp

from . import checks
from ._types import type_set
from .losses import Loss, _frames, _scalar_of

__all__ = ["PinholeCamera", "SilhouetteLoss", "load_cameras", "load_masks", "soft_silhouette", "load_silhouette_target",
           "read_silhouette_masks", "silhouette_target"]

#: Splat window half-width in splat standard deviations.
WINDOW_SIGMAS = 4.0
#: Largest window half-width in pixels (a particle nearer than this blurs over the image).
MAX_WINDOW = 64
#: Splat opacity: a body a few particles thick must reach full occupancy inside, or the
#: loss rewards a wider, softer body (docs/fitting.md, silhouette fits).
DEFAULT_OPACITY = 0.9


@dataclasses.dataclass
class PinholeCamera:
    """A calibrated pinhole camera (see the module doc for the conventions)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray
    t: np.ndarray
    name: str = "camera"

    def __post_init__(self):
        self.width = checks.positive_int("width", self.width)
        self.height = checks.positive_int("height", self.height)
        for k in ("fx", "fy"):
            setattr(self, k, checks.positive(k, getattr(self, k)))
        self.cx, self.cy = checks.number("cx", self.cx), checks.number("cy", self.cy)
        for key in ("R", "t"):
            try:
                setattr(self, key, np.asarray(getattr(self, key), dtype=np.float64))
            except checks.ARRAY_ERRORS:  # numpy's own message named no key
                raise ValueError(f"camera {self.name!r}: {key} = {checks.shorten(getattr(self, key))!r} is not allowed: "
                                 "must be numbers") from None
        self.t = self.t.reshape(-1)
        if self.R.shape != (3, 3) or not np.isfinite(self.R).all():
            raise ValueError(f"camera {self.name!r}: R with shape {self.R.shape} is not allowed: must be a finite 3x3 rotation")
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-6) or np.linalg.det(self.R) < 0.0:
            # det -1: a reflection, which mirrors the world (it passed as a rotation)
            raise ValueError(f"camera {self.name!r}: R is not allowed: it is not a rotation (R R^T != I or det R < 0)")
        if self.t.shape != (3,) or not np.isfinite(self.t).all():
            raise ValueError(f"camera {self.name!r}: t with shape {self.t.shape} is not allowed: must be 3 finite numbers")

    @classmethod
    def from_dict(cls, d: Mapping) -> "PinholeCamera":
        if not isinstance(d, Mapping):
            raise ValueError(f"camera {checks.shorten(d)!r} is not allowed: must be an object with keys "
                             f"{', '.join(CAMERA_KEYS)}")
        d = dict(d)
        name = str(d.get("name", "camera"))
        unknown = sorted(set(d) - set(CAMERA_KEYS))
        if unknown:
            # A misspelt key ("fov", "cx ") was ignored without a word.
            raise ValueError(f"camera {name!r}: key {unknown[0]!r} is not allowed: the keys are {', '.join(CAMERA_KEYS)}")
        if "K" in d:
            both = [k for k in ("fx", "fy", "cx", "cy") if k in d]
            if both:  # K won without a word
                raise ValueError(f"camera {name!r}: K and {', '.join(both)} are not allowed together: give one of them")
            try:
                K = np.asarray(d["K"], dtype=np.float64)
            except checks.ARRAY_ERRORS:  # numpy's own message for text or ragged rows
                K = np.full(1, np.nan)
            if K.shape != (3, 3) or not np.isfinite(K).all():
                raise ValueError(f"camera {name!r}: K = {checks.shorten(d['K'])!r} is not allowed: must be 3x3 finite numbers")
            tol = 1e-9 * max(abs(K[0, 0]), abs(K[1, 1]), 1.0)  # a calibration tool's round-off passes
            if abs(K[0, 1]) > tol or abs(K[1, 0]) > tol or not np.allclose(K[2], [0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
                # the skew and the bottom row were ignored
                raise ValueError(f"camera {name!r}: K = {K.tolist()} is not allowed: the pinhole model has no skew and "
                                 "a bottom row (0, 0, 1)")
            d.update(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
        missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy", "R", "t") if k not in d]
        if missing:
            raise ValueError(f"camera {name!r} is not allowed: it lacks {', '.join(missing)}")
        for key in ("R", "t"):
            try:
                d[key] = np.asarray(d[key], dtype=np.float64)
            except checks.ARRAY_ERRORS:  # numpy's own message named no key
                raise ValueError(f"camera {name!r}: {key} = {checks.shorten(d[key])!r} is not allowed: must be "
                                 "numbers") from None
        # Whole numbers as they are (int() took 16.9 as 16 and true as 1); 32.0 is 32.
        for key in ("width", "height"):
            if isinstance(d[key], float) and d[key].is_integer():
                d[key] = int(d[key])
        return cls(d["width"], d["height"], d["fx"], d["fy"], d["cx"], d["cy"], d["R"], d["t"], name)

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel coordinates ``u, v`` and depth ``z`` of world points ``(N, 3)``."""
        x = np.asarray(X, dtype=np.float64) @ self.R.T + self.t
        z = x[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.fx * x[:, 0] / z + self.cx, self.fy * x[:, 1] / z + self.cy, z



#: Keys of a camera in a camera file (``K`` may stand for ``fx, fy, cx, cy``).
CAMERA_KEYS = ("name", "width", "height", "fx", "fy", "cx", "cy", "K", "R", "t")


def load_cameras(path) -> tuple[list[PinholeCamera], dict]:
    """Cameras and options (``radius``, ``opacity``) from a JSON camera file."""
    p = os.fspath(path)
    doc = checks.json_file("camera file", p)
    cams = doc.get("cameras") if isinstance(doc, dict) else None
    if not isinstance(cams, list) or not cams:
        raise ValueError(f"camera file {checks.shown_path(p, False)} is not allowed: it needs a non-empty 'cameras' list")
    unknown = sorted(set(doc) - {"cameras", "radius", "opacity"})
    if unknown:
        raise ValueError(f"camera file {checks.shown_path(p, False)}: key {unknown[0]!r} is not allowed: the keys are cameras, radius, opacity")
    for key in ("radius", "opacity"):
        if key in doc:
            checks.positive(f"camera file {checks.shown_path(p, False)}: {key}", doc[key])  # 'x' was a float() error naming nothing
    if "opacity" in doc:  # 1.0 was refused by SilhouetteLoss, naming no file
        checks.in_range(f"camera file {checks.shown_path(p, False)}: opacity", doc["opacity"], 1e-6, 0.999)
    cameras = [PinholeCamera.from_dict(c) for c in cams]
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise ValueError(f"camera file {checks.shown_path(p, False)} is not allowed: camera names must be distinct ({names})")
    options = {k: doc[k] for k in ("radius", "opacity") if k in doc}
    return cameras, options


def _mask_array(a, where: str) -> np.ndarray:
    """The binary mask (1 inside) of an image or array read from ``where``. All zeros is an
    empty silhouette (the body out of view); NaN, inf, or negative values with nothing
    positive (whose inside cannot be told: a signed distance? a [-1, 1] image?) are refused."""
    try:
        a = np.asarray(a, dtype=np.float64)
    except checks.ARRAY_ERRORS:
        raise ValueError(f"mask {where} is not allowed: it is not an array of numbers") from None
    if a.ndim == 3:
        a = a[..., :3].mean(axis=2)
    if a.ndim != 2 or a.size == 0:
        raise ValueError(f"mask {where} with shape {a.shape} is not allowed: must be (height, width)")
    bad = ~np.isfinite(a)
    if bad.any():
        # NaN compares False with the threshold: the mask was read as empty.
        j, i = (int(k) for k in np.argwhere(bad)[0])
        raise ValueError(f"mask {where} is not allowed: it has {int(bad.sum())} non-finite values (first {float(a[j, i])!r} "
                         f"at row {j}, column {i}); must be finite numbers")
    top = float(a.max())
    if top <= 0.0 and float(a.min()) < 0.0:
        raise ValueError(f"mask {where} is not allowed: its values are all <= 0 and some negative (max {top:g}), so "
                         "nothing is inside by the rule 'nonzero or > 0.5 of the maximum'; an empty silhouette is all zeros")
    return (a > 0.5 * top).astype(np.float64) if top > 0 else np.zeros_like(a)


def load_masks(path, cameras: Sequence[PinholeCamera], frame: int | None = None) -> dict[int | None, list[np.ndarray]]:
    """``{rendered frame: [mask per camera]}`` from a mask file (see the module doc); a
    single image applies to the only camera at ``frame``."""
    p = os.fspath(path)
    if not os.path.isfile(p):
        raise FileNotFoundError(f"mask file {checks.shown_path(p, False)} does not exist")
    ext = os.path.splitext(p)[1].lower()
    from .fit import read_arrays, unreadable_arrays  # noqa: PLC0415

    if ext == ".npz":
        try:
            data = read_arrays(p)
        except Exception as e:  # noqa: BLE001 (zipfile, zlib and numpy raise many kinds)
            raise unreadable_arrays("mask file", p, e) from None
        if not isinstance(data, dict):
            raise ValueError(f"mask file {checks.shown_path(p, False)} is not allowed: it holds one array, not <camera>_<frame> arrays")
        out: dict[int, dict[str, np.ndarray]] = {}
        names = {c.name for c in cameras}
        for key in data:
            cam, _, f = key.rpartition("_")
            if cam not in names or not (f.isascii() and f.isdigit()):  # '²' passed isdigit() and failed int()
                raise ValueError(f"mask {key!r} in {checks.shown_path(p, False)} is not allowed: name arrays <camera>_<frame> with cameras {sorted(names)}")
            if cam in out.get(int(f), {}):  # front_1 and front_01: the last read won
                raise ValueError(f"mask {key!r} in {checks.shown_path(p, False)} is not allowed: camera {cam!r} already has a mask for frame {int(f)}")
            out.setdefault(int(f), {})[cam] = _fitting_mask(_mask_array(data[key], f"{checks.shown_path(p, False)}:{key}"), f"{checks.shown_path(p, False)}:{key}",
                                                            cameras[[c.name for c in cameras].index(cam)])
        result = {}
        for f, by in out.items():
            if set(by) != names:
                raise ValueError(f"{checks.shown_path(p, False)}: frame {f} has masks for {sorted(by)}, the cameras are {sorted(names)}")
            result[f] = [by[c.name] for c in cameras]
        _refuse_all_inside(p, (m for ms in result.values() for m in ms))
        return result
    if len(cameras) != 1:
        raise ValueError(f"mask file {checks.shown_path(p, False)} holds one image, for {len(cameras)} cameras: use an .npz with <camera>_<frame> arrays")
    if ext == ".npy":
        try:
            a = read_arrays(p)
        except Exception as e:  # noqa: BLE001
            raise unreadable_arrays("mask file", p, e) from None
        if isinstance(a, dict):
            raise ValueError(f"mask file {checks.shown_path(p, False)} is not allowed: it is a zip of arrays, not one .npy image")
    else:
        try:
            a = _image_mask(p)
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"mask {checks.shown_path(p, False)} cannot be read as an image: {e}") from None
    mask = _fitting_mask(_mask_array(a, p), p, cameras[0])
    _refuse_all_inside(p, [mask])
    return {frame: [mask]}


def _fitting_mask(mask: np.ndarray, where: str, camera: PinholeCamera) -> np.ndarray:
    """``mask``, refused by its file where it is not the camera's size (it was refused later
    as the mask 'at step 34', by the step it was compared at, naming no file)."""
    if mask.shape != (camera.height, camera.width):
        raise ValueError(f"mask {where} with shape {mask.shape} is not allowed: camera {camera.name!r} is "
                         f"{camera.height} x {camera.width} (height x width)")
    return mask


def _refuse_all_inside(where: str, masks) -> None:
    """Refuse masks every pixel of which is inside, in every view and frame: they ask only that
    the body fill every view, whatever its shape (a uniform grey image, an all-ones array). One
    such view beside others is kept: a camera close enough that the body fills its view sees
    exactly that, and the other views show the outline."""
    masks = list(masks)
    if not all(m.all() for m in masks):
        return
    what = "every pixel is inside" if len(masks) == 1 else f"every pixel of its {len(masks)} masks is inside"
    raise ValueError(f"mask {where} is not allowed: {what} (nonzero, or > 0.5 of its maximum), so it shows no outline of "
                     "the body and constrains nothing but that the body fill every view; a mask is nonzero inside the "
                     "body's silhouette and zero around it (an empty view is all zeros)")


def _image_mask(path: str) -> np.ndarray:
    """The values of an image mask whose inside ``_mask_array`` tells: its grey levels or
    colours, or its alpha channel where that varies (a silhouette cut out on a transparent
    background, whose colour may be the same everywhere). A palette image is read by its
    colours: its pixels are palette indices, which read as values inverted a mask whose
    palette put white first."""
    from PIL import Image  # noqa: PLC0415

    with Image.open(path) as img:
        frames = getattr(img, "n_frames", 1)
        if frames > 1:
            # Only the first was read: a GIF or TIFF of a mask sequence fitted its first mask alone.
            raise ValueError(f"it holds {frames} images (an animation or a multi-page file); a mask image is one "
                             "view at one frame: give masks of several frames as an .npz of <camera>_<frame> arrays")
        if img.mode not in ("1", "L", "LA", "I", "F", "RGB", "RGBA") and not img.mode.startswith("I;"):
            img = img.convert("RGBA")  # a palette (its transparency as alpha), CMYK, ...
        bands = img.getbands()
        a = np.asarray(img)
    if "A" not in bands:
        return a
    alpha = a[..., bands.index("A")]
    if alpha.min() != alpha.max():
        return alpha
    return np.delete(a, bands.index("A"), axis=2)  # an alpha of one value draws no silhouette


def soft_silhouette(X: np.ndarray, camera: PinholeCamera, radius: float, opacity: float = DEFAULT_OPACITY) -> np.ndarray:
    """The soft silhouette ``O`` ``(height, width)`` of points ``X`` (numpy, float64;
    the same splats and window as the loss's kernels)."""
    u, v, z = camera.project(X)
    S = np.zeros((camera.height, camera.width))
    f = math.sqrt(camera.fx * camera.fy)
    for uk, vk, zk in zip(u, v, z):
        if not zk > 1e-6:
            continue
        s = radius * f / zk
        w = min(int(math.ceil(WINDOW_SIGMAS * s)), MAX_WINDOW)
        cu, cv = int(math.floor(uk + 0.5)), int(math.floor(vk + 0.5))
        i0, i1 = max(cu - w, 0), min(cu + w, camera.width - 1)
        j0, j1 = max(cv - w, 0), min(cv + w, camera.height - 1)
        if i0 > i1 or j0 > j1:
            continue
        ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1))
        a = opacity * np.exp(-((ii - uk) ** 2 + (jj - vk) ** 2) / (2 * s * s))
        S[j0: j1 + 1, i0: i1 + 1] += np.log1p(-a)
    return 1.0 - np.exp(S)


@functools.cache
def _kernels(scalar):
    T = type_set(scalar)
    vec3, mat33 = T.vec3, T.mat33

    @wp.kernel(module="unique")
    def splat(
        x: wp.array(dtype=vec3),
        R: mat33,
        t: vec3,
        fx: scalar,
        fy: scalar,
        cx: scalar,
        cy: scalar,
        width: int,
        height: int,
        window: int,
        radius: scalar,
        opacity: scalar,
        log_t: wp.array(dtype=scalar),
    ):
        # One thread per (particle, pixel offset in the window): no loop, so no
        # accumulator is read back inside the kernel (docs/method.md, Warp pitfall 1).
        i, k = wp.tid()
        p = R * x[i] + t
        z = p[2]
        if z <= scalar(1.0e-6):
            return
        u = fx * p[0] / z + cx
        v = fy * p[1] / z + cy
        s = radius * wp.sqrt(fx * fy) / z
        w = wp.min(int(wp.ceil(scalar(4.0) * s)), window)
        side = 2 * window + 1
        di = k % side - window
        dj = k // side - window
        if di < -w or di > w or dj < -w or dj > w:
            return
        qi = int(wp.floor(u + scalar(0.5))) + di
        qj = int(wp.floor(v + scalar(0.5))) + dj
        if qi < 0 or qi >= width or qj < 0 or qj >= height:
            return
        du = scalar(qi) - u
        dv = scalar(qj) - v
        a = opacity * wp.exp(-(du * du + dv * dv) / (scalar(2.0) * s * s))
        wp.atomic_add(log_t, qj * width + qi, wp.log(scalar(1.0) - a))

    @wp.kernel(module="unique")
    def compare(log_t: wp.array(dtype=scalar), mask: wp.array(dtype=scalar), w: scalar, out: wp.array(dtype=scalar)):
        q = wp.tid()
        r = scalar(1.0) - wp.exp(log_t[q]) - mask[q]
        wp.atomic_add(out, 0, w * r * r)

    return types.SimpleNamespace(splat=splat, compare=compare)


class SilhouetteLoss(Loss):
    """Soft-silhouette loss against binary masks (see the module doc).

    ``masks``: for each frame (step index) one mask ``(height, width)`` per camera:
    ``{step: [mask, ...]}``, or a list of per-camera lists with ``frames``. ``cameras``:
    ``PinholeCamera`` list (or a camera JSON file). ``radius`` (m): splat radius, about
    half a particle spacing; ``opacity`` in (0, 1), default 0.9 (with 0.5 a body a few particles
    thick never fills its mask, so a softer, wider body always lowers the loss: docs/fitting.md). ``noise``: the residual noise for
    ``warp_esph.diagnostics``, in occupancy units (default 0.1). ``camera_file``: the file
    the cameras and radius came from (set where ``cameras`` is one), named by the refusals.
    """
    _CACHES = ("_buffers", "_covered_checked")


    def __init__(self, masks, cameras, radius: float, frames=None, opacity: float = DEFAULT_OPACITY, weight: float = 1.0,
                 particles=None, noise: float = 0.1, camera_file=None):
        #: The file the cameras and radius were read from, named where the radius is refused.
        self.camera_file = None if camera_file is None else os.fspath(camera_file)
        if isinstance(cameras, (str, os.PathLike)):
            self.camera_file = os.fspath(cameras)
            cameras, _ = load_cameras(cameras)
        if isinstance(cameras, PinholeCamera):
            cameras = [cameras]  # one camera (a TypeError: not iterable)
        self.cameras = list(cameras) if hasattr(cameras, "__iter__") and not isinstance(cameras, (str, bytes)) else []
        if not self.cameras or not all(isinstance(c, PinholeCamera) for c in self.cameras):
            raise ValueError("cameras is not allowed: give a list of PinholeCamera (or a camera JSON file)")
        if isinstance(masks, Mapping):
            per = {f: masks[f] for f in _frames(list(masks))}
            if frames is not None and set(_frames(frames)) != set(per):  # frames was ignored
                raise ValueError(f"masks are given for steps {sorted(per)} but frames = {list(_frames(frames))}")
        else:
            if frames is None:
                raise ValueError("frames is required: say at which step indices the masks apply")
            fr = _frames(frames)
            masks = list(masks)
            if len(masks) != len(fr):
                raise ValueError(f"masks: {len(masks)} frames of masks given for {len(fr)} frames")
            per = dict(zip(fr, masks))
        super().__init__(list(per), weight, particles)
        self.radius = checks.positive("radius", radius)
        self.opacity = checks.in_range("opacity", opacity, 1e-6, 0.999)
        self.noise = checks.noise("noise", noise)
        self.masks = {}
        for f, ms in per.items():
            ms = [ms] if isinstance(ms, np.ndarray) and ms.ndim == 2 else list(ms)
            if len(ms) != len(self.cameras):
                raise ValueError(f"masks at step {f}: {len(ms)} given for {len(self.cameras)} cameras")
            out = []
            for m, c in zip(ms, self.cameras):
                try:
                    if np.iscomplexobj(m):  # its real part was taken with a ComplexWarning
                        raise TypeError
                    m = np.asarray(m, dtype=np.float64)
                except checks.ARRAY_ERRORS:
                    raise ValueError(f"mask of camera {c.name!r} at step {f} is not allowed: it is not an array of "
                                     "numbers") from None
                if m.shape != (c.height, c.width):
                    raise ValueError(f"mask of camera {c.name!r} at step {f} with shape {m.shape} is not allowed: "
                                     f"the camera is {c.height} x {c.width} (height x width)")
                # Compared with an occupancy in [0, 1] as given: a NaN made the loss NaN, a raw
                # 0/255 image a loss that no body can lower (load_masks binarises images).
                outside = ~((m >= 0.0) & (m <= 1.0))
                if outside.any():
                    j, i = (int(k) for k in np.argwhere(outside)[0])
                    raise ValueError(f"mask of camera {c.name!r} at step {f} is not allowed: it has {int(outside.sum())} "
                                     f"values outside [0, 1] (first {float(m[j, i])!r} at row {j}, column {i}); a mask is an "
                                     "occupancy in [0, 1], 1 inside (load_masks binarises an image)")
                out.append(m)
            self.masks[f] = out
        full = [(f, c.name) for f, ms in self.masks.items() for m, c in zip(ms, self.cameras) if (m >= 1.0).all()]
        if len(full) == len(self.masks) * len(self.cameras):
            # Refused as a mask file is; one full view beside others is a close camera's.
            f, name = full[0]
            also = ", as in every other view and step" if len(full) > 1 else ""
            raise ValueError(f"mask of camera {name!r} at step {f} is not allowed: every pixel is 1 (inside){also}, so the "
                             "masks show no outline of the body and constrain nothing but that it fill every view; a mask "
                             "is the body's silhouette, 1 inside and 0 around it")
        self._buffers = {}
        self._covered_checked = set()

    def target_items(self, prefix: str = "target") -> dict:
        out = {**super().target_items(prefix), f"{prefix}.radius": self.radius, f"{prefix}.opacity": self.opacity}
        for f, ms in self.masks.items():
            out.update({f"{prefix}.masks[{f}][{c.name!r}]": m for m, c in zip(ms, self.cameras)})
        return out

    def _window(self, x: wp.array) -> int:
        X = x.numpy().astype(np.float64)
        w = 1
        for c in self.cameras:
            _, _, z = c.project(X)
            z = z[z > 1e-6]
            if len(z):
                w = max(w, int(math.ceil(WINDOW_SIGMAS * self.radius * math.sqrt(c.fx * c.fy) / float(z.min()))))
        return min(w, MAX_WINDOW)

    def _launch(self, frame, x, out, scale):
        S = _scalar_of(x)
        k = _kernels(S)
        dev = x.device
        window = self._window(x)
        side = 2 * window + 1
        for ci, c in enumerate(self.cameras):
            key = (frame, ci, x.dtype, str(dev))
            buf = self._buffers.get(key)
            if buf is None:
                buf = (wp.zeros(c.width * c.height, dtype=S, device=dev, requires_grad=True),
                       wp.array(self.masks[frame][ci].reshape(-1), dtype=S, device=dev))
                self._buffers[key] = buf
            log_t, mask = buf
            log_t.zero_()
            wp.launch(k.splat, (x.shape[0], side * side),
                      [x, T_mat(S, c.R), T_vec(S, c.t), S(c.fx), S(c.fy), S(c.cx), S(c.cy), c.width, c.height, window,
                       S(self.radius), S(self.opacity)], [log_t], device=dev)
            if key not in self._covered_checked:
                self._covered_checked.add(key)
                self._refuse_covered(frame, ci, x, log_t)
            wp.launch(k.compare, c.width * c.height, [log_t, mask, S(scale / (len(self.cameras) * c.width * c.height))],
                      [out], device=dev)

    #: A view whose every pixel lets through less than this fraction (occupancy above 1 minus
    #: it) is covered: its silhouette has no outline and next to no gradient.
    COVERED = 1e-3

    def _refuse_covered(self, frame, ci, x, log_t):
        """Refuse, at a camera's first evaluation at ``frame``, splats that cover every pixel of
        its image where the radius is to blame: larger than the particles' spacing (it is about
        half of it; a radius in centimetres), the soft silhouette is 1 everywhere whatever the
        body's shape. A body that fills the view with splats of the right size (a camera close
        to it, or a guess larger than the view) is not refused: its outline shows as it moves."""
        if not (log_t.numpy() < math.log(self.COVERED)).all():
            return
        X = x.numpy().astype(np.float64)
        apart = _spacing(X)
        if self.radius <= apart:
            return
        c = self.cameras[ci]
        _, _, z = c.project(X)
        z = z[z > 1e-6]
        narrowest = self.radius * math.sqrt(c.fx * c.fy) / float(z.max()) if len(z) else math.inf
        where = f"camera file {self.camera_file}: " if self.camera_file is not None else ""
        apart_text = f"the particles lie about {apart:.3g} m apart" if math.isfinite(apart) else "the body is one particle"
        raise ValueError(f"{where}radius = {self.radius:g} is not allowed with camera {c.name!r}: at step {frame} the "
                         f"particles' splats (standard deviation {narrowest:.3g} pixels and more) cover every pixel of its "
                         f"{c.width} x {c.height} image, so the silhouette shows no outline and constrains nothing; the "
                         f"radius is in metres, about half a particle spacing, and {apart_text}")

    def out_of_reach(self) -> str | None:
        """Where no particle's splat fell on any pixel of any camera in any frame of the last
        evaluation (cameras facing away, or a body placed elsewhere): the rendered
        silhouettes are empty whatever the parameters, and the gradient is 0."""
        if not self._buffers or any(np.any(log_t.numpy()) for log_t, _ in self._buffers.values()):
            return None
        return ("no particle is in view of any camera in any frame (cameras facing away from the body, or placed "
                "in other units than metres?)")

    # ------------------------------------------------------------ statistics
    def residual_scale(self) -> float:
        pixels = np.mean([c.width * c.height for c in self.cameras])
        return len(self.frames) * len(self.cameras) * pixels / self.weight

    def observation_count(self) -> int:
        return int(len(self.frames) * sum(c.width * c.height for c in self.cameras))

    def residuals(self, positions) -> np.ndarray:
        """``O - M`` at every pixel of every camera and frame (numpy, from ``{step: (n, 3)}``),
        scaled by ``sqrt(mean pixels / camera pixels)`` so that ``sum r^2 = residual_scale *
        value`` exactly when the cameras differ in size (the loss averages per camera)."""
        out = []
        mean_pixels = np.mean([c.width * c.height for c in self.cameras])
        for f in self.frames:
            X = np.asarray(positions[f], dtype=np.float64)
            if self.particles is not None:
                X = X[self.particles]
            for c, m in zip(self.cameras, self.masks[f]):
                k = math.sqrt(mean_pixels / (c.width * c.height))
                out.append(k * (soft_silhouette(X, c, self.radius, self.opacity) - m).ravel())
        return np.concatenate(out)

    def correlated_pixels(self, positions) -> float:
        """Pixels per independent observation: the area ``pi (2 s)^2`` of a splat (``s`` its
        pixel radius at the particles' median depth), averaged over cameras. A particle moves
        its whole splat, so the residuals within it rise and fall together; counting each
        pixel as an independent observation overstates what the masks say by about this factor."""
        X = np.concatenate([np.asarray(positions[f], dtype=np.float64).reshape(-1, 3) for f in self.frames])
        areas = []
        for c in self.cameras:
            _, _, z = c.project(X)
            z = z[z > 1e-9]
            if len(z):
                s = self.radius * math.sqrt(c.fx * c.fy) / float(np.median(z))
                areas.append(math.pi * (2.0 * s) ** 2)
        return max(float(np.mean(areas)), 1.0) if areas else 1.0

    def __repr__(self):
        return (f"SilhouetteLoss(frames={list(self.frames)}, cameras={[c.name for c in self.cameras]}, "
                f"radius={self.radius:g}, weight={self.weight:g})")


def _spacing(X: np.ndarray, probes: int = 64) -> float:
    """The particles' typical spacing: the median distance from up to ``probes`` of them (evenly
    strided, so the same every call) to their nearest neighbour; inf for a single particle."""
    X = X[np.isfinite(X).all(axis=1)]
    if len(X) < 2:
        return math.inf
    near = []
    for i in np.unique(np.linspace(0, len(X) - 1, min(probes, len(X))).astype(np.int64)):
        d = np.einsum("ij,ij->i", X - X[i], X - X[i])
        d[i] = np.inf
        near.append(float(d.min()))
    return math.sqrt(float(np.median(near)))


def T_mat(S, R):
    return (wp.mat33d if S is wp.float64 else wp.mat33f)(*np.asarray(R, dtype=np.float64).ravel().tolist())


def T_vec(S, t):
    return (wp.vec3d if S is wp.float64 else wp.vec3f)(*np.asarray(t, dtype=np.float64).tolist())


def read_silhouette_masks(cameras_path, masks_path, frames_spec) -> tuple[list, dict, dict]:
    """``(cameras, options, masks)`` of a silhouette target of the ``warp-esph fit`` command:
    cameras and options from ``cameras_path``, masks ``{rendered frame: [mask per camera]}``
    from ``masks_path`` (an image: at ``frames_spec``, or at frame None, the run's last frame,
    where it is not given; an ``.npz``: its own frames, ``frames_spec`` choosing among them).
    The run's frames are not needed: a fit runs to its targets' last frame, the masks' too."""
    cameras, options = load_cameras(cameras_path)
    if str(masks_path).lower().endswith(".npz"):
        masks = load_masks(masks_path, cameras)
        if frames_spec is not None:
            # It was ignored: every frame of the file was fitted, whatever --target-frames said.
            from .usd import parse_frames  # noqa: PLC0415

            try:
                chosen = parse_frames(frames_spec, sorted(masks), "--target-frames")
            except ValueError as e:
                raise ValueError(f"{e}; the mask file {masks_path} holds frames "
                                 f"{', '.join(map(str, sorted(masks)))}") from None
            masks = {f: masks[f] for f in chosen}
    else:
        try:
            frame = int(frames_spec) if frames_spec is not None else None
        except (TypeError, ValueError):
            # '2,3' or 'last' was an int() error: an image is one frame.
            raise ValueError(f"--target-frames = {checks.shorten(frames_spec)!r} is not allowed with the mask image {masks_path}: an image "
                             "is one rendered frame, give one frame index") from None
        masks = load_masks(masks_path, cameras, frame)
    if "radius" not in options:
        raise ValueError(f"camera file {cameras_path} is not allowed: give the splat 'radius' in m (about half a particle spacing)")
    return cameras, options, masks


def silhouette_target(read, frames: int, substeps: int, source: str = "--frames", camera_file=None,
                      particles=None) -> SilhouetteLoss:
    """The ``SilhouetteLoss`` of ``read`` (``read_silhouette_masks``) for a run of ``frames``
    frames (``source`` names what set it) at ``substeps`` steps per frame; ``camera_file``:
    the file ``read`` took the cameras and radius from, named where the radius is refused;
    ``particles``: those the masks show (the loss's)."""
    cameras, options, masks = read
    masks = {frames if f is None else f: m for f, m in masks.items()}
    bad = [f for f in masks if f > frames or f <= 0]
    if bad:
        # It said '(--frames)' also where --frames was not given (the run's frames were the
        # targets' last frame, or the scene's).
        raise ValueError(f"masks at frame {bad[0]} are not allowed: frames are 1..{frames} ({source})")
    return SilhouetteLoss({f * substeps: m for f, m in masks.items()}, cameras, radius=float(options["radius"]),
                          opacity=float(options.get("opacity", DEFAULT_OPACITY)), camera_file=camera_file,
                          particles=particles)


def load_silhouette_target(cameras_path, masks_path, frames_spec, frames: int, substeps: int) -> SilhouetteLoss:
    """The silhouette loss of the ``warp-esph fit`` command: cameras from ``cameras_path``,
    masks from ``masks_path`` at rendered frames (an image: ``frames_spec`` or the last
    frame; an ``.npz``: its own, ``frames_spec`` choosing among them), with ``substeps``
    steps per frame. The splat radius is the file's ``radius`` (required: about half a
    particle spacing) and the opacity its ``opacity`` (default 0.9)."""
    return silhouette_target(read_silhouette_masks(cameras_path, masks_path, frames_spec), frames, substeps,
                             camera_file=cameras_path)
