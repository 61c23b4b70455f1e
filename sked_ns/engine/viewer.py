"""What an edit shows in nerfstudio's viewer besides the scene: the sketch views as frustums and the edit box."""

from __future__ import annotations

import numpy as np

from sked_ns.sketches.cameras import PinholeCamera


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
