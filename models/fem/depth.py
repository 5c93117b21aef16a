"""A virtual RGB-D camera for the association model's cases (seed 000, 2.3 and 3): a pinhole camera,
depth images rendered from a mesh, and a depth-noise model. Real depth images and point clouds are read
by :mod:`knee.foundations.pointclouds`.

Camera conventions: a pinhole camera with intrinsics ``K`` (3, 3) (pixels); the pose ``T_world_cam``
(4, 4) gives the camera's axes in the world (x right, y down, z forward: the optical axis); a depth
image holds, per pixel, the depth along the optical axis in mm (0 where nothing was seen). Pixel (u, v)
(column, row) has its centre at ``(u, v)``, the coordinates ``K`` projects to (OpenCV's and librealsense's
convention, :mod:`knee.foundations.pointclouds`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy import ndimage

from knee.foundations.errors import KneeInputError


@dataclass
class Camera:
    """A pinhole depth camera.

    Attributes
    ----------
    K : (3, 3) float
        Intrinsics in pixels.
    width, height : int
    T_world_cam : (4, 4) float
        Camera pose in the world (mm).
    """

    K: np.ndarray
    width: int
    height: int
    T_world_cam: np.ndarray

    @classmethod
    def looking_at(cls, eye, target, up=(0.0, 1.0, 0.0), width=1280, height=720, hfov_deg=69.0):
        """A camera at ``eye`` looking at ``target`` (mm), image-up roughly along ``up``; the default
        matches an RGB-D camera's colour stream (1280 x 720, 69 degrees horizontal field of view)."""
        eye, target, up = (np.asarray(v, float) for v in (eye, target, up))
        z = target - eye
        if np.linalg.norm(z) < 1e-9:
            raise KneeInputError("camera eye and target coincide")
        z /= np.linalg.norm(z)
        x = np.cross(z, up)  # image right
        if np.linalg.norm(x) < 1e-9:
            raise KneeInputError("camera 'up' is parallel to the viewing direction")
        x /= np.linalg.norm(x)
        y = np.cross(z, x)  # image down
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x, y, z])
        T[:3, 3] = eye
        f = 0.5 * width / np.tan(np.radians(hfov_deg) / 2)
        K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
        return cls(K, int(width), int(height), T)

    @property
    def T_cam_world(self) -> np.ndarray:
        T = np.eye(4)
        R = self.T_world_cam[:3, :3]
        T[:3, :3] = R.T
        T[:3, 3] = -R.T @ self.T_world_cam[:3, 3]
        return T


def render_depth(vertices, faces, camera: Camera) -> np.ndarray:
    """Depth image (height, width) in mm of a triangle mesh seen by ``camera`` (0 = no surface)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(faces, np.uint32)))
    # open3d casts pixel u's ray through u + 0.5 in its intrinsics' coordinates: the principal point moved by
    # half a pixel makes that ray pass through u in ours (pixel centres at whole coordinates)
    K = np.array(camera.K, float)
    K[:2, 2] += 0.5
    rays = scene.create_rays_pinhole(o3d.core.Tensor(K), o3d.core.Tensor(camera.T_cam_world),
                                     camera.width, camera.height)
    t = scene.cast_rays(rays)["t_hit"].numpy().astype(float)
    t[~np.isfinite(t)] = 0.0
    return t


#: A step (mm) between neighbouring pixels of a rendered depth image taken for an edge where flying pixels
#: arise (:class:`DepthNoise`): a surface's outline over what lies behind it.
FLYING_EDGE_MM = 20.0


@dataclass
class DepthNoise:
    """Depth noise of a stereo RGB-D camera: zero-mean Gaussian with ``sigma = sigma_at_ref *
    (z / ref_depth)^2`` (error growing with the square of the depth), and a fraction of pixels lost.
    Defaults: 1 mm at 400 mm, 2% dropout, each pixel's error and loss drawn on its own.

    A stereo camera matches windows of pixels, so neighbouring pixels err together and lose their depth
    together (a patch with too little texture, a glint). With ``correlation_px`` > 0 the error is white noise
    smoothed by a Gaussian of that many pixels (its standard deviation), rescaled so that each pixel's
    ``sigma`` is the same as without: thinning a cloud to voxels then no longer averages the error away.
    With ``hole_px`` > 0 the lost pixels come in blobs about that many pixels across instead of one by one:
    the pixels where such a smoothed field is highest, ``dropout`` of the image.

    With ``flying`` > 0, flying pixels too: that share of the pixels within ``flying_band`` pixels of a depth
    edge (a seen pixel next to an unseen one, or stepping over :data:`FLYING_EDGE_MM` to a neighbour), on
    either side of it, return a blend: a depth drawn evenly between the nearer surface's and the one behind
    (the deeper neighbour's; where nothing lies behind in the render, ``flying_behind_mm`` further). Drawn
    after the noise and the dropout, which stay as they are without it."""

    sigma_at_ref: float = 1.0
    ref_depth: float = 400.0
    dropout: float = 0.02
    flying: float = 0.0
    flying_band: int = 2
    flying_behind_mm: float = 300.0
    correlation_px: float = 0.0
    hole_px: float = 0.0

    def __post_init__(self):
        for name in ("sigma_at_ref", "dropout", "flying", "flying_band", "flying_behind_mm", "correlation_px",
                     "hole_px"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0.0):
                raise KneeInputError(f"the depth noise's {name} must be a finite number >= 0, got {v!r}")
        if not (np.isfinite(self.ref_depth) and self.ref_depth > 0.0):
            raise KneeInputError(f"the depth noise's ref_depth must be a positive number, got {self.ref_depth!r}")
        for name in ("dropout", "flying"):
            if getattr(self, name) > 1.0:
                raise KneeInputError(f"the depth noise's {name} is a share from 0 to 1, got {getattr(self, name)!r}")

    def apply(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        d = np.array(depth, dtype=float, copy=True)
        seen = d > 0
        sigma = self.sigma_at_ref * (d[seen] / self.ref_depth) ** 2
        if self.correlation_px > 0.0:
            d[seen] += _smooth_field(rng, d.shape, self.correlation_px)[seen] * sigma
        else:
            d[seen] += rng.normal(size=sigma.size) * sigma
        if self.hole_px > 0.0:
            field = _smooth_field(rng, d.shape, self.hole_px / 2.0)
            lost = field > np.quantile(field, 1.0 - self.dropout) if self.dropout > 0.0 else np.zeros(d.shape, bool)
        else:
            lost = rng.random(d.shape) < self.dropout
        d[lost] = 0.0
        if self.flying > 0.0:
            d = self._blend_edges(np.asarray(depth, float), d, rng)
        return d

    def _blend_edges(self, clean: np.ndarray, d: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        seen = clean > 0
        size = 2 * self.flying_band + 1
        near = ndimage.minimum_filter(np.where(seen, clean, np.inf), size=3)
        far = ndimage.maximum_filter(np.where(seen, clean, 0.0), size=3)
        edge = seen & ((ndimage.minimum_filter(seen, size=3) == 0) | (far - clean > FLYING_EDGE_MM)
                       | (clean - near > FLYING_EDGE_MM))
        band = ndimage.binary_dilation(edge, iterations=self.flying_band)
        front = ndimage.minimum_filter(np.where(seen, clean, np.inf), size=size)  # the nearer surface
        back = ndimage.maximum_filter(np.where(seen, clean, 0.0), size=size)  # the one behind, if seen
        back = np.where(back - front > FLYING_EDGE_MM, back, front + self.flying_behind_mm)
        hit = band & np.isfinite(front) & (rng.random(d.shape) < self.flying)
        d[hit] = front[hit] + rng.random(int(hit.sum())) * (back[hit] - front[hit])
        return d


def _smooth_field(rng: np.random.Generator, shape, width_px: float) -> np.ndarray:
    """White noise over an image of ``shape`` smoothed by a Gaussian of ``width_px`` pixels (its standard
    deviation), rescaled to unit variance: the exact variance of the smoothed noise away from the borders,
    (sum of the 1-D kernel's squares)^2, not the sample's, so that every draw has the same scale."""
    radius = int(4.0 * width_px + 0.5)  # scipy's own truncation at 4 widths
    x = np.arange(-radius, radius + 1, dtype=float)
    k = np.exp(-0.5 * (x / width_px) ** 2)
    k /= k.sum()
    field = ndimage.gaussian_filter(rng.normal(size=shape), width_px, mode="wrap", truncate=4.0)
    return field / float(np.sum(k ** 2))


def default_camera(distance: float = 350.0, azimuth_deg: float = 35.0, elevation_deg: float = 30.0,
                   target=(0.0, -20.0, 0.0)) -> Camera:
    """An oblique camera ``distance`` mm from the knee, anterior, turned ``azimuth`` towards lateral and
    raised ``elevation`` towards proximal (femur frame)."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    d = np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
    t = np.asarray(target, float)
    return Camera.looking_at(t + distance * d, t, up=(0.0, 1.0, 0.0))


#: Named camera placements: azimuth towards lateral (deg), 350 mm away, raised 30 deg.
CAMERA_PLACEMENTS = {"oblique": 35.0, "frontal": 0.0, "lateral": 70.0}


def camera_from_spec(text: str) -> Camera:
    """A camera from a placement name (``oblique``, ``frontal``, ``lateral``: 350 mm away, raised 30 deg)
    or ``AZIMUTH,ELEVATION,DISTANCE`` (deg, deg, mm)."""
    t = str(text).strip().lower()
    if t in CAMERA_PLACEMENTS:
        return default_camera(azimuth_deg=CAMERA_PLACEMENTS[t])
    try:
        az, el, dist = (float(v) for v in t.split(","))
    except ValueError:
        raise KneeInputError(f"camera must be one of {', '.join(CAMERA_PLACEMENTS)} or AZIMUTH,ELEVATION,DISTANCE "
                             f"(deg, deg, mm), got {text!r}") from None
    if not (np.isfinite([az, el, dist]).all() and 100.0 <= dist <= 2000.0 and -80.0 <= el <= 80.0):
        raise KneeInputError(f"camera distance must be 100-2000 mm and elevation within +-80 deg, got {text!r}")
    return default_camera(distance=dist, azimuth_deg=az, elevation_deg=el)
