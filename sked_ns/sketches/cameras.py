"""Pinhole cameras in nerfstudio's convention: the one place that knows it.

Camera-to-world poses are OpenGL-style (x right, y up, the camera looks along -z), as in
nerfstudio's `Cameras` and a nerfstudio `transforms.json`. Pixel (row i, column j)
covers [j, j+1) x [i, i+1), so its centre is (j + 0.5, i + 0.5), as nerfstudio's ray
generation places it; a projected point lands in pixel (floor(v), floor(u)). The paper's
rounding floor(x + 1/2) is the same rule for pixel centres at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Tuple

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from sked_ns.errors import SkedUserError

if TYPE_CHECKING:  # nerfstudio only where a nerfstudio camera is made: the maths above needs none
    from nerfstudio.cameras.cameras import Cameras

# Points closer to the camera plane than this (scene units) count as behind it.
MIN_DEPTH = 1e-6
NORM_EPS = float(np.finfo(float).eps * 4.0)
"""nerfstudio's floor for a ray direction's norm (camera_utils._EPS)."""


def project(
    points: Float[Tensor, "num_points 3"],
    camera_to_worlds: Float[Tensor, "num_views 3 4"],
    intrinsics: Float[Tensor, "num_views 4"],
) -> tuple[Float[Tensor, "num_views num_points 2"], Float[Tensor, "num_views num_points"]]:
    """Project world points into every view.

    Returns continuous pixel coordinates (u right, v down) and the depth along the
    viewing direction (positive in front of the camera).
    """
    rotation = camera_to_worlds[:, :, :3]
    origin = camera_to_worlds[:, :, 3]
    # x_cam = R^T (p - o), for all views at once.
    local = torch.einsum("vji,vmj->vmi", rotation, points[None] - origin[:, None])
    depth = -local[..., 2]
    safe_depth = torch.where(depth > MIN_DEPTH, depth, torch.ones_like(depth))
    fx, fy, cx, cy = (intrinsics[:, k, None] for k in range(4))
    u = cx + fx * local[..., 0] / safe_depth
    v = cy - fy * local[..., 1] / safe_depth
    return torch.stack([u, v], dim=-1), depth


def projection_rows(
    camera_to_worlds: Float[Tensor, "num_views 3 4"], intrinsics: Float[Tensor, "num_views 4"]
) -> Float[Tensor, "3 num_views 4"]:
    """Affine rows giving (u * depth, v * depth, depth) of a world point, for every view.

    One matrix product then projects all points into all views; `project` is the plain form.
    """
    rotation_t = camera_to_worlds[:, :, :3].transpose(1, 2)  # world -> camera
    translation = -(rotation_t @ camera_to_worlds[:, :, 3:])  # (V, 3, 1)
    world_to_camera = torch.cat([rotation_t, translation], dim=2)  # (V, 3, 4)
    fx, fy, cx, cy = (intrinsics[:, k, None] for k in range(4))
    depth = -world_to_camera[:, 2]
    u = fx * world_to_camera[:, 0] + cx * depth
    v = -fy * world_to_camera[:, 1] + cy * depth
    return torch.stack([u, v, depth])


MAX_PIXEL = 1e7
"""Projections are clamped to this many pixels: NaN/inf points and far-off ones stay finite and index-safe."""


def pixel_lookup(points: Tensor, rows: Tensor, sizes: Tensor, offsets: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Project points (M, 3) into every view with `projection_rows` (3, V, 4) and find their pixel in the views'
    images concatenated row-major (sizes: (2, V, 1) widths and heights; offsets: (V, 1) each image's start).
    Returns the pixel (2, V, M), floored; the same clamped onto the image; the flat index of that clamped pixel
    (V, M); and whether the point lies in front of the camera (V, M)."""
    projected = torch.einsum("cvk,mk->cvm", rows[..., :3], points) + rows[..., 3:]
    depth = projected[2]
    in_front = depth > MIN_DEPTH
    inverse_depth = torch.where(in_front, depth, torch.ones_like(depth)).reciprocal()
    pixel = (projected[:2] * inverse_depth).nan_to_num(0.0).clamp(-MAX_PIXEL, MAX_PIXEL).floor()
    pixel_in = torch.minimum(pixel.clamp_min(0.0), sizes - 1)
    index = torch.addcmul(pixel_in[0], pixel_in[1], sizes[0]).long() + offsets
    return pixel, pixel_in, index, in_front


def pixel_directions(
    pixels: Float[Tensor, "num_pixels 2"],
    camera_to_world: Float[Tensor, "3 4"],
    intrinsics: Float[Tensor, "4"],
) -> Float[Tensor, "num_pixels 3"]:
    """World-space directions (not normalised, unit depth) through image positions (u, v)."""
    fx, fy, cx, cy = intrinsics
    local = torch.stack(
        [(pixels[:, 0] - cx) / fx, -(pixels[:, 1] - cy) / fy, -torch.ones_like(pixels[:, 0])], dim=-1
    )
    return local @ camera_to_world[:, :3].T


def distort(
    points: Float[np.ndarray, "*batch 2"], coefficients: Float[np.ndarray, "6"]
) -> Float[np.ndarray, "*batch 2"]:
    """Lens distortion of normalised image points ((u - cx) / fx, (v - cy) / fy), v down.

    nerfstudio's perspective model (`camera_utils`, OpenCV's with an r^8 term): coefficients
    [k1, k2, k3, k4, p1, p2], radial 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8 plus tangential p1, p2.
    """
    k1, k2, k3, k4, p1, p2 = coefficients
    x, y = points[..., 0], points[..., 1]
    r = x * x + y * y
    radial = 1.0 + r * (k1 + r * (k2 + r * (k3 + r * k4)))
    return np.stack(
        [radial * x + 2 * p1 * x * y + p2 * (r + 2 * x * x), radial * y + 2 * p2 * x * y + p1 * (r + 2 * y * y)], axis=-1
    )


def check_camera_to_world(matrix: np.ndarray, where: str, atol: float = 1e-3) -> np.ndarray:
    """Validate a 3x4 or 4x4 rigid camera-to-world matrix and return it as 3x4 float64.

    `where` names the file and field in the error so the user knows what to fix.
    """
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape not in ((3, 4), (4, 4)):
        raise SkedUserError(f"{where}: expected a 4x4 (or 3x4) camera-to-world matrix, got shape {matrix.shape}.")
    if not np.all(np.isfinite(matrix)):
        raise SkedUserError(f"{where}: the camera-to-world matrix holds NaN or inf values.")
    if matrix.shape == (4, 4) and not np.allclose(matrix[3], [0, 0, 0, 1], atol=atol):
        raise SkedUserError(f"{where}: the last row of a 4x4 camera-to-world matrix must be [0, 0, 0, 1], got {matrix[3]}.")
    rotation = matrix[:3, :3]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=atol) or np.linalg.det(rotation) < 0:
        raise SkedUserError(
            f"{where}: the rotation part is not a proper rotation (orthonormal, determinant +1); "
            "scale, shear or a mirrored axis is not a rigid camera pose. Check the matrix convention "
            "(camera-to-world, OpenGL axes)."
        )
    return matrix[:3].copy()


def cameras_of(poses: torch.Tensor, fx, fy, cx, cy, width: int, height: int) -> Cameras:
    """nerfstudio pinhole `Cameras` for (n, 3, 4) camera-to-world poses sharing one set of intrinsics."""
    from nerfstudio.cameras.cameras import Cameras, CameraType

    return Cameras(
        camera_to_worlds=poses,
        fx=torch.as_tensor(fx, dtype=torch.float32).reshape(-1, 1),
        fy=torch.as_tensor(fy, dtype=torch.float32).reshape(-1, 1),
        cx=torch.as_tensor(cx, dtype=torch.float32).reshape(-1, 1),
        cy=torch.as_tensor(cy, dtype=torch.float32).reshape(-1, 1),
        width=torch.full((poses.shape[0], 1), width, dtype=torch.long),
        height=torch.full((poses.shape[0], 1), height, dtype=torch.long),
        camera_type=CameraType.PERSPECTIVE,
    )


def viewmat(camera_to_world: Tensor) -> Tensor:
    """nerfstudio's OpenGL camera-to-world (C, 3, 4) -> gsplat's world-to-camera (C, 4, 4), as splatfacto's
    `get_viewmat` (uncompiled): the y and z axes flip."""
    rotation = camera_to_world[:, :3, :3] * camera_to_world.new_tensor([[[1, -1, -1]]])
    translation = camera_to_world[:, :3, 3:4]
    inverse = torch.zeros(camera_to_world.shape[0], 4, 4, dtype=camera_to_world.dtype, device=camera_to_world.device)
    inverse[:, 3, 3] = 1.0
    inverse[:, :3, :3] = rotation.transpose(1, 2)
    inverse[:, :3, 3:4] = -torch.bmm(rotation.transpose(1, 2), translation)
    return inverse


@dataclass
class PinholeCamera:
    """What a sketch view needs of a camera: model-frame pose and intrinsics in pixels."""

    camera_to_world: np.ndarray
    fl_x: float
    fl_y: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def from_view(cls, view) -> "PinholeCamera":
        """The camera of a sketch view (in whatever frame the view is)."""
        return cls(view.camera_to_world, view.fl_x, view.fl_y, view.cx, view.cy, view.width, view.height)

    @classmethod
    def from_nerfstudio(cls, cameras) -> "PinholeCamera":
        """The first camera of a nerfstudio `Cameras`."""
        camera = cameras[0] if cameras.shape else cameras
        return cls(
            camera_to_world=camera.camera_to_worlds.detach().cpu().numpy().astype(np.float64).reshape(3, 4),
            fl_x=float(camera.fx), fl_y=float(camera.fy), cx=float(camera.cx), cy=float(camera.cy),
            width=int(camera.width), height=int(camera.height),
        )


def ray_aabb(rays_o: Tensor, rays_d: Tensor, aabb: Tensor) -> Tuple[Tensor, Tensor]:
    """Entry and exit distances of rays through a box (slab method); exit < entry when missed."""
    inverse = 1.0 / torch.where(rays_d.abs() < 1e-12, torch.full_like(rays_d, 1e-12), rays_d)
    t_a, t_b = (aabb[:3] - rays_o) * inverse, (aabb[3:] - rays_o) * inverse
    return torch.minimum(t_a, t_b).amax(-1), torch.maximum(t_a, t_b).amin(-1)


def pinhole_rays(camera_to_world: torch.Tensor, focal: float, size: int):
    """nerfstudio's `Cameras.generate_rays(camera_indices=0, keep_shape=True)` for one square, undistorted pinhole
    camera (fx = fy = focal, cx = cy = size / 2, OpenGL axes), made on the pose's device with the same operations:
    no host-built tensor and no scalar read on the way (nerfstudio's path has a dozen of each). `camera_to_world`:
    (3, 4). Returns a RayBundle shaped (size, size)."""
    from nerfstudio.cameras.rays import RayBundle

    device, dtype = camera_to_world.device, camera_to_world.dtype
    pixels = torch.arange(size, device=device, dtype=dtype) + 0.5
    y, x = torch.meshgrid(pixels, pixels, indexing="ij")
    centre = size / 2.0
    coord = torch.stack([(x - centre) / focal, (y - centre) / focal], -1)
    coord_x_offset = torch.stack([(x - centre + 1) / focal, (y - centre) / focal], -1)
    coord_y_offset = torch.stack([(x - centre) / focal, (y - centre + 1) / focal], -1)
    coord_stack = torch.stack([coord, coord_x_offset, coord_y_offset], dim=0)  # (3, H, W, 2)
    coord_stack[..., 1] *= -1  # OpenCV -> OpenGL
    directions_stack = torch.cat([coord_stack, -torch.ones_like(coord_stack[..., :1])], dim=-1)
    rotation = camera_to_world[:3, :3]
    directions_stack = torch.sum(directions_stack[..., None, :] * rotation, dim=-1)
    norm = torch.linalg.vector_norm(directions_stack, dim=-1, keepdim=True).clamp_min(NORM_EPS)
    directions_stack = directions_stack / norm
    directions = directions_stack[0]
    dx = torch.sqrt(torch.sum((directions - directions_stack[1]) ** 2, dim=-1))
    dy = torch.sqrt(torch.sum((directions - directions_stack[2]) ** 2, dim=-1))
    return RayBundle(
        origins=camera_to_world[:3, 3].expand(size, size, 3).clone(),  # its own memory, as nerfstudio's
        directions=directions,
        pixel_area=(dx * dy)[..., None],
        camera_indices=torch.zeros(size, size, 1, dtype=torch.long, device=device),
        metadata={"directions_norm": norm[0].detach()},
    )
