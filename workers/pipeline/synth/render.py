"""CPU ray-cast rendering of one capture with Open3D's RaycastingScene.

Per pixel: the first hit's surface colour (solid texture, UV texture or marker print),
Lambertian shading from one directional light plus ambient, and the visible instance.
With a lens distortion each pixel's ray is the undistorted direction of that pixel, so the
image is the distorted one a real lens gives; per-view gains and motion blur apply to the
linear image before the sensor noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from workers.pipeline.errors import ShapeError
from workers.pipeline.geometry import Mat4, as_mat4, invert_rigid
from workers.pipeline.synth.markers import MarkerSheet
from workers.pipeline.synth.options import CameraOptions, LookOptions
from workers.pipeline.synth.scene import Placement, StaticSurface
from workers.pipeline.synth.shapes import Mesh
from workers.pipeline.synth.texture import F32

_BACKGROUND = np.float32(0.2)


@dataclass(frozen=True, eq=False)
class RenderedView:
    """One rendered view: ``image`` (H, W, 3) uint8 RGB; ``instance`` (H, W) int32 index into
    the capture's placements, −1 where no object is visible; ``depth_m`` (H, W) float32 ray
    length to the hit (inf where nothing is hit); ``env_from_cam`` 4×4."""

    image: NDArray[np.uint8]
    instance: NDArray[np.int32]
    depth_m: F32
    env_from_cam: Mat4


@dataclass(frozen=True, eq=False)
class _Geometry:
    """One mesh of the ray-casting scene: environment-frame copy, vertex normals (V, 3), and
    what it is (a room surface or a placed object)."""

    mesh_env: Mesh
    normals_env: NDArray[np.float32]
    static: StaticSurface | None
    placement: Placement | None
    object_from_env: Mat4


@dataclass(frozen=True, eq=False)
class ViewEffects:
    """Camera effects of one view: ``gain_rgb`` (3,) multiplies the linear image (exposure
    × white balance); ``blur_kernel`` (n, n) float32 summing to 1, or None."""

    gain_rgb: NDArray[np.float32]
    blur_kernel: NDArray[np.float32] | None = None


def motion_blur_kernel(length_px: float, angle_rad: float) -> NDArray[np.float32]:
    """(n, n) kernel of a straight motion of ``length_px`` pixels at ``angle_rad``: 64
    points along the segment splatted bilinearly, normalised to sum 1."""
    half = int(np.ceil(length_px / 2.0)) + 1
    n = 2 * half + 1
    kernel = np.zeros((n, n), np.float64)
    s = np.linspace(-length_px / 2.0, length_px / 2.0, 64)
    xs, ys = half + s * np.cos(angle_rad), half + s * np.sin(angle_rad)
    x0, y0 = np.floor(xs).astype(int), np.floor(ys).astype(int)
    fx, fy = xs - x0, ys - y0
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy)):
        np.add.at(kernel, (y0 + dy, x0 + dx), w)
    np.add.at(kernel, (y0 + 1, x0 + 1), fx * fy)
    out: NDArray[np.float32] = (kernel / kernel.sum()).astype(np.float32)
    return out


def _pixel_rays(
    k: NDArray[np.float64],
    width: int,
    height: int,
    distortion: tuple[float, ...] | None = None,
) -> F32:
    """(H, W, 3) camera-frame ray directions (z = 1) through the pixel centres, which sit at
    integer coordinates (OpenCV convention). With ``distortion`` (OpenCV's k1, k2, p1, p2,
    k3) each pixel is undistorted first (iterated to 1e-12), so a point seen along the ray
    of pixel (u, v) projects through K and the distortion to (u, v)."""
    u = np.arange(width, dtype=np.float64)
    v = np.arange(height, dtype=np.float64)
    out = np.empty((height, width, 3), np.float32)
    out[..., 2] = 1.0
    if distortion is None:
        out[..., 0] = ((u - k[0, 2]) / k[0, 0])[None, :]
        out[..., 1] = ((v - k[1, 2]) / k[1, 1])[:, None]
        return out
    xd = ((u - k[0, 2]) / k[0, 0])[None, :].repeat(height, 0)
    yd = ((v - k[1, 2]) / k[1, 1])[:, None].repeat(width, 1)
    x, y = _undistort_normalised(xd, yd, distortion)
    out[..., 0], out[..., 1] = x, y
    return out


def distort_normalised(
    x: NDArray[np.float64], y: NDArray[np.float64], distortion: tuple[float, ...]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """OpenCV's lens model on normalised coordinates: (k1, k2, p1, p2, k3) applied to (x, y)."""
    k1, k2, p1, p2, k3 = distortion
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def _undistort_normalised(
    xd: NDArray[np.float64], yd: NDArray[np.float64], distortion: tuple[float, ...]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Invert :func:`distort_normalised` by fixed-point iteration; ShapeError when it does
    not converge to 1e-9 (a lens too strong for this image)."""
    x, y = xd.copy(), yd.copy()
    for _ in range(200):
        ex, ey = distort_normalised(x, y, distortion)
        x, y = x - (ex - xd), y - (ey - yd)
    ex, ey = distort_normalised(x, y, distortion)
    if not np.all(np.abs(ex - xd) + np.abs(ey - yd) < 1e-9):
        raise ShapeError(f"lens distortion {distortion} cannot be inverted over the image")
    return x, y


class Renderer:
    """Renders views of one capture; the ray-casting scene is built once in ``__init__``."""

    def __init__(
        self,
        room: tuple[StaticSurface, ...],
        placements: tuple[Placement, ...],
        markers: MarkerSheet,
        camera: CameraOptions,
        look: LookOptions,
        k: NDArray[np.float64],
        distortion: tuple[float, ...] | None = None,
    ) -> None:
        self.camera, self.look, self.markers, self.k = camera, look, markers, k
        self.placements = placements
        self.scene = o3d.t.geometry.RaycastingScene()
        self.geometries: list[_Geometry] = []
        for surface in room:
            self._add(surface.mesh, np.eye(4), surface, None)
        for placement in placements:
            self._add(placement.model.mesh, placement.env_from_object, None, placement)
        self._rays_cam = _pixel_rays(k, camera.width, camera.height, distortion)
        light = np.asarray(look.light_dir, np.float32)
        self._light = light / np.linalg.norm(light)
        self._focal = np.float32(k[0, 0])
        self._ray_len = np.linalg.norm(self._rays_cam.reshape(-1, 3), axis=1)

    def _add(
        self,
        mesh: Mesh,
        env_from_mesh: Mat4,
        static: StaticSurface | None,
        placement: Placement | None,
    ) -> None:
        verts = mesh.vertices @ env_from_mesh[:3, :3].T + env_from_mesh[:3, 3]
        gid = self.scene.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(verts, np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(mesh.triangles, np.uint32)),
        )
        if gid != len(self.geometries):
            raise ShapeError(f"unexpected geometry id {gid}")
        normals = (mesh.vertex_normals @ env_from_mesh[:3, :3].T).astype(np.float32)
        self.geometries.append(
            _Geometry(
                Mesh(verts, mesh.triangles), normals, static, placement, invert_rigid(env_from_mesh)
            )
        )

    def render(
        self, env_from_cam: Mat4, rng: np.random.Generator, effects: ViewEffects | None = None
    ) -> RenderedView:
        """Render the view of a camera at ``env_from_cam`` (4×4, OpenCV axes) with the
        camera ``effects`` of this view (none when None)."""
        env_from_cam = as_mat4(env_from_cam, "env_from_cam")
        h, w = self.camera.height, self.camera.width
        rot = env_from_cam[:3, :3].astype(np.float32)
        origin = env_from_cam[:3, 3].astype(np.float32)
        # columns instead of a (N, 3) @ (3, 3) BLAS call, which is erratic beside Open3D threads
        cam = self._rays_cam.reshape(-1, 3)
        dirs = cam[:, 0:1] * rot[:, 0] + cam[:, 1:2] * rot[:, 1] + rot[:, 2]
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = dirs
        hit = self.scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
        t_hit = hit["t_hit"].numpy()
        gids = hit["geometry_ids"].numpy().astype(np.int64)
        prims = hit["primitive_ids"].numpy().astype(np.int64)
        bary = hit["primitive_uvs"].numpy()
        face_normals = hit["primitive_normals"].numpy()
        valid = np.isfinite(t_hit)
        depth = np.where(valid, t_hit * self._ray_len, np.float32(np.inf))
        albedo = np.full((len(dirs), 3), _BACKGROUND, np.float32)
        shade = np.ones(len(dirs), np.float32)
        instance = np.full(len(dirs), -1, np.int32)
        points = np.zeros((len(dirs), 3), np.float32)
        n_static = len(self.geometries) - len(self.placements)
        for gid, geom in enumerate(self.geometries):
            sel = np.flatnonzero(gids == gid)
            if len(sel) == 0:
                continue
            unit = dirs[sel] / self._ray_len[sel, None]
            points[sel] = origin + unit * depth[sel, None]
            if geom.placement is None:
                normal = face_normals[sel]
            else:  # smooth shading: barycentric interpolation of vertex normals
                tri = geom.mesh_env.triangles[prims[sel]]
                b1, b2 = bary[sel, 0:1], bary[sel, 1:2]
                nrm = geom.normals_env
                normal = (1 - b1 - b2) * nrm[tri[:, 0]] + b1 * nrm[tri[:, 1]] + b2 * nrm[tri[:, 2]]
                normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-6)
            cos_view = np.einsum("ij,ij->i", normal, unit)
            towards_light = (normal @ self._light) * -np.sign(cos_view)
            shade[sel] = self.look.ambient + self.look.diffuse * np.clip(towards_light, 0.0, 1.0)
            slant = np.maximum(np.abs(cos_view), np.float32(0.2))
            footprint = depth[sel] / self._focal / slant
            if geom.placement is not None:
                local = points[sel] @ np.ascontiguousarray(
                    geom.object_from_env[:3, :3].T, np.float32
                )
                local += geom.object_from_env[:3, 3].astype(np.float32)
                model = geom.placement.model
                albedo[sel] = model.surface_colours(prims[sel], bary[sel], local, footprint)
                instance[sel] = gid - n_static
            elif geom.static is not None:
                albedo[sel] = geom.static.texture.colours(points[sel], footprint)
                if geom.static.name == "floor":
                    self._print_markers(sel, points, albedo, env_from_cam)
        rgb = albedo * (shade * np.float32(255.0))[:, None]
        if effects is not None:
            rgb = _apply_effects(rgb, effects, h, w)
        if self.look.noise_sigma > 0:
            rgb += rng.standard_normal(rgb.shape, np.float32) * np.float32(self.look.noise_sigma)
        image: NDArray[np.uint8] = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
        return RenderedView(
            image.reshape(h, w, 3),
            instance.reshape(h, w),
            depth.astype(np.float32).reshape(h, w),
            env_from_cam,
        )

    def _print_markers(
        self, sel: NDArray[np.int64], points: F32, albedo: F32, env_from_cam: Mat4
    ) -> None:
        """Overwrite floor pixels on marker paper with the print; pixels at a print edge are
        supersampled n×n by intersecting sub-pixel rays with the floor plane z = 0."""
        grey, on_paper = self.markers.albedo(points[sel])
        if not on_paper.any():
            return
        pix = sel[on_paper]
        h, w = self.camera.height, self.camera.width
        value = np.full(h * w, -1.0, np.float32)
        value[pix] = grey[on_paper]
        img = value.reshape(h, w)
        edge = np.zeros((h, w), bool)
        for axis in (0, 1):
            step = np.diff(img, axis=axis) != 0
            if axis == 0:
                edge[1:] |= step
                edge[:-1] |= step
            else:
                edge[:, 1:] |= step
                edge[:, :-1] |= step
        flat_edge = edge.reshape(-1)[pix]
        albedo[pix[~flat_edge]] = grey[on_paper][~flat_edge, None]
        pix = pix[flat_edge]
        n = max(1, self.look.marker_supersample)
        cam_to_env, origin = np.ascontiguousarray(env_from_cam[:3, :3].T), env_from_cam[:3, 3]
        acc = np.zeros((len(pix), 3), np.float32)
        for i in range(n):
            for j in range(n):
                du, dv = ((i + 0.5) / n - 0.5) / self.k[0, 0], ((j + 0.5) / n - 0.5) / self.k[1, 1]
                cam = self._rays_cam.reshape(-1, 3)[pix] + np.asarray([du, dv, 0.0], np.float32)
                d = cam @ cam_to_env
                t = -origin[2] / np.where(np.abs(d[:, 2]) > 1e-9, d[:, 2], -1e-9)
                sub = (origin + d * t[:, None]).astype(np.float32)
                sub_grey, sub_on = self.markers.albedo(sub)
                acc += np.where(sub_on[:, None], sub_grey[:, None], albedo[pix])
        albedo[pix] = acc / np.float32(n * n)


def _apply_effects(rgb: F32, effects: ViewEffects, h: int, w: int) -> F32:
    """(H·W, 3) linear RGB times the view's gain, then blurred by its kernel."""
    out: F32 = rgb * effects.gain_rgb.astype(np.float32)[None, :]
    if effects.blur_kernel is None:
        return out
    image = cv2.filter2D(out.reshape(h, w, 3), -1, effects.blur_kernel)
    result: F32 = np.asarray(image, np.float32).reshape(-1, 3)
    return result
