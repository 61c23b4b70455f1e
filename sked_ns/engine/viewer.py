"""What an edit shows in nerfstudio's viewer besides the scene: the sketch views as frustums and the edit box."""

from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

from sked_ns.sketches.cameras import PinholeCamera

AXES_CONDITION = 1e6
"""Above this condition number the cameras' optical axes are near parallel (a forward-facing capture): no one point
they all look at."""
STEP_BACK = 1.6
"""After a view is added the browser's camera, still where the view was taken (its frustum filling the view), moves
back to this many times its distance from what it looks at."""


def training_poses(pipeline) -> np.ndarray:
    """The training cameras' (N, 3, 4) poses in the model frame (what the viewer shows)."""
    return pipeline.datamanager.train_dataset.cameras.camera_to_worlds.detach().cpu().numpy()


def scene_framing(cameras_to_world: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(position, look-at point, up), model frame, that show the scene as its photos do: the training camera nearest
    the cameras' mean position, looking at the point nearest every camera's optical axis (the origin, where
    nerfstudio's dataparsers centre a scene, when the axes are near parallel), up as the cameras' mean up."""
    poses = np.asarray(cameras_to_world, dtype=np.float64).reshape(-1, 3, 4)
    positions, forwards = poses[:, :, 3], -poses[:, :, 2]  # OpenGL axes: a camera looks down its -z
    position = positions[np.argmin(np.linalg.norm(positions - positions.mean(axis=0), axis=1))]
    projectors = np.eye(3)[None] - forwards[:, :, None] * forwards[:, None, :]  # onto each axis' normal plane
    system, target = projectors.sum(axis=0), np.einsum("nij,nj->i", projectors, positions)
    look_at = np.linalg.solve(system, target) if np.linalg.cond(system) < AXES_CONDITION else np.zeros(3)
    up = poses[:, :, 1].mean(axis=0)
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-6 else np.array([0.0, 0.0, 1.0])
    return position, look_at, up


def frame_on_connect(server, cameras_to_world: np.ndarray, look_at: Optional[np.ndarray] = None) -> None:
    """Each browser that connects starts at `scene_framing`'s view (looking at `look_at` when given, e.g. the edit
    box's centre), not at viser's default pose, which can sit inside the scene or show it at the view's edge."""
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

    position, centre, up = scene_framing(cameras_to_world)
    centre = centre if look_at is None else np.asarray(look_at, dtype=np.float64)

    def frame(client) -> None:
        with client.atomic():
            client.camera.up_direction = tuple(up)
            client.camera.position = tuple(position * VISER_NERFSTUDIO_SCALE_RATIO)
            client.camera.look_at = tuple(centre * VISER_NERFSTUDIO_SCALE_RATIO)

    server.on_client_connect(frame)


def step_back(server, factor: float = STEP_BACK) -> None:
    """Every browser's camera moves back from what it looks at, in the direction it looks from."""
    for client in server.get_clients().values():
        look_at, position = np.array(client.camera.look_at), np.array(client.camera.position)
        with client.atomic():
            client.camera.position = tuple(look_at + (position - look_at) * factor)
            client.camera.look_at = tuple(look_at)  # viser moves it with the position: put it back


def add_frustum(server, name: str, camera: PinholeCamera, image: np.ndarray, colour):
    """A camera frustum showing `image` in the viewer's scene (model frame, viser's scale)."""
    import viser.transforms as vtf
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

    rotation = vtf.SO3.from_matrix(camera.camera_to_world[:, :3]) @ vtf.SO3.from_x_radians(np.pi)
    return server.scene.add_camera_frustum(
        name, fov=float(2 * np.arctan(camera.height / 2 / camera.fl_y)), aspect=camera.width / camera.height,
        scale=0.15, image=(np.clip(image, 0, 1) * 255).astype(np.uint8), color=colour, wxyz=rotation.wxyz,
        position=camera.camera_to_world[:, 3] * VISER_NERFSTUDIO_SCALE_RATIO,
    )


def show_sketch_views(server, views, edit_box=None, prefix: str = "/sked", images=None) -> list:
    """Each sketch view as a frustum showing its image (default: its mask), and the edit box as a
    wireframe; returns the nodes."""
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

    handles = []
    for index, view in enumerate(views):
        image = images[index] if images is not None else np.repeat(view.mask[..., None], 3, axis=-1).astype(np.float64)
        camera = PinholeCamera.from_view(view)
        handles.append(add_frustum(server, f"{prefix}/view_{index:02d}", camera, image, (220, 30, 30)))
    if edit_box is not None:
        corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=np.float64)
        vertices = (edit_box.min + corners * edit_box.size) * VISER_NERFSTUDIO_SCALE_RATIO
        # The 12 triangles of the box's 6 faces, drawn as a wireframe so it never hides the scene.
        faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                          [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
        handles.append(server.scene.add_mesh_simple(f"{prefix}/edit_box", vertices=vertices.astype(np.float32),
                                                    faces=faces, color=(255, 80, 80), wireframe=True))
    return handles
