"""Do the sketches pin the part down? The hull check, and where sked-sketch and its viewer panel report it."""

from __future__ import annotations

import socket

import numpy as np
import pytest
import torch
from scipy.ndimage import binary_closing, binary_fill_holes

from sked_ns.demo.scenes.sphere import orbit_pose
from sked_ns.drawing.hull_check import HULL_RATIO_WARN, check_hull, silhouette_area
from sked_ns.errors import SkedUserError
from sked_ns.sketches.cameras import project
from sked_ns.sketches.placement import sketch_direction
from sked_ns.sketches.sketch_set import SketchSet, SketchView, save_sketch_set

SIZE, FOCAL, RADIUS = 64, 75.0, 3.0
UP = np.array([0.0, 0.0, 1.0])
SIDE_VIEWS = ((0.0, 10.0), (90.0, 10.0))  # (azimuth, elevation) in degrees
FROM_ABOVE = (20.0, 89.9)


def box_points(half_size, yaw_deg=0.0, samples=48):
    """Dense points of a box, turned about z."""
    axes = [np.linspace(-h, h, max(2, int(samples * h / max(half_size)))) for h in half_size]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    yaw = np.radians(yaw_deg)
    turn = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    return points @ turn.T


# A thin stick lying diagonally on the ground: from two side views its hull is a whole square slab.
STICK = box_points((0.5, 0.03, 0.03), yaw_deg=45.0)


def view_of(points, azimuth, elevation, name=""):
    """The part's true silhouette as a sketch view (the pixels its points project to, holes filled)."""
    pose = orbit_pose(azimuth, elevation, RADIUS)
    pixels, _ = project(torch.tensor(points, dtype=torch.float32), torch.tensor(pose[None], dtype=torch.float32),
                        torch.tensor([[FOCAL, FOCAL, SIZE / 2, SIZE / 2]]))
    pixels = pixels[0].numpy().astype(int)
    mask = np.zeros((SIZE, SIZE), dtype=bool)
    mask[pixels[:, 1], pixels[:, 0]] = True
    mask = binary_fill_holes(binary_closing(mask, np.ones((3, 3))))
    return SketchView(mask=mask, camera_to_world=pose, fl_x=FOCAL, fl_y=FOCAL, cx=SIZE / 2, cy=SIZE / 2, name=name)


def views_of(points, sights):
    return [view_of(points, azimuth, elevation, f"view {index}") for index, (azimuth, elevation) in enumerate(sights)]


def test_silhouette_area_of_a_box_along_each_axis():
    pixel = 1.0 / 40  # cell centres of a 40 x 20 x 10 grid over a 1 x 0.5 x 0.25 box, as hull_samples places them
    axes = [pixel * (np.arange(count) + 0.5) for count in (40, 20, 10)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    for axis, area in ((0, 0.5 * 0.25), (1, 1.0 * 0.25), (2, 1.0 * 0.5)):
        assert silhouette_area(points, np.eye(3)[axis], pixel) == pytest.approx(area, rel=0.05)


def test_two_side_views_of_a_thin_part_are_reported_and_a_view_from_above_suggested():
    check = check_hull(views_of(STICK, SIDE_VIEWS), up=UP)
    assert check.underdetermined and check.ratio > 1.5 * HULL_RATIO_WARN
    assert all(ratio > 1.5 * HULL_RATIO_WARN for ratio in check.view_ratios)
    assert abs(check.widest_direction @ UP) > 0.99, "the hull's bulk shows from above"
    assert check.suggestion == "from above" and check.suggestion_direction @ UP < -0.99
    message = check.message()
    assert "underdetermine the part" in message and "Add a sketch from above" in message
    assert "view 0" in message and "view 1" in message


def test_a_third_view_from_above_pins_the_part_down():
    check = check_hull(views_of(STICK, SIDE_VIEWS + (FROM_ABOVE,)), up=UP)
    assert not check.underdetermined and check.ratio < HULL_RATIO_WARN / 1.5
    assert "Add a sketch" not in check.message() and "at most" in check.message()


def test_a_solid_part_from_two_sides_is_not_flagged():
    check = check_hull(views_of(box_points((0.3, 0.3, 0.3)), SIDE_VIEWS), up=UP)
    assert not check.underdetermined and check.ratio < 2.0


def test_the_suggestion_is_the_direction_least_covered():
    """A side view and one from above: the missing one is from the side, square to the first."""
    views = views_of(box_points((0.4, 0.03, 0.4)), ((0.0, 10.0), FROM_ABOVE))
    check = check_hull(views, up=UP)
    assert check.suggestion == "from the side, turned 90 degrees from view 0"
    assert abs(check.suggestion_direction @ UP) < 1e-9
    assert abs(check.suggestion_direction @ sketch_direction(views[0])) < 1e-9


def test_up_defaults_to_the_cameras_mean_up():
    """A sketch set in a data frame whose up is -y (COLMAP-like): still 'from above' along that up."""
    turn = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # z -> -y
    views = [SketchView(mask=v.mask, camera_to_world=turn @ v.camera_to_world, fl_x=v.fl_x, fl_y=v.fl_y, cx=v.cx,
                        cy=v.cy, name=v.name) for v in views_of(STICK, SIDE_VIEWS)]
    check = check_hull(views)
    assert check.underdetermined and check.suggestion == "from above"
    assert check.suggestion_direction @ np.array([0.0, -1.0, 0.0]) < -0.95


def test_sked_sketch_check_prints_the_warning(tmp_path, capsys):
    from sked_ns.drawing.sketch_viewer import entrypoint

    save_sketch_set(SketchSet(views=views_of(STICK, SIDE_VIEWS), frame="model"), tmp_path / "two")
    save_sketch_set(SketchSet(views=views_of(STICK, SIDE_VIEWS + (FROM_ABOVE,)), frame="model"), tmp_path / "three")
    entrypoint(["check", str(tmp_path / "two")])
    out = capsys.readouterr().out
    assert "underdetermine the part" in out and "Add a sketch from above" in out
    assert "view_00.png " in out and str(tmp_path) not in out, "views named by their mask's file name"
    entrypoint(["check", str(tmp_path / "three")])
    assert "Add a sketch" not in capsys.readouterr().out
    with pytest.raises(SkedUserError, match="no sketch set here"):
        entrypoint(["check", str(tmp_path)])


def test_viewer_panel_shows_the_coverage(tmp_path):
    """The panel's coverage text, on a real viser server with the views of the stick added one by one."""
    import viser

    import sked_ns.drawing.sketch_viewer as sketch_viewer
    from sked_ns.drawing.sketching import SketchSession
    from sked_ns.sketches.cameras import PinholeCamera
    from sked_ns.sketches.sketch_set import DataparserTransform

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    server = viser.ViserServer(port=port, verbose=False)
    try:
        session = SketchSession(lambda camera: np.full((camera.height, camera.width, 3), 0.5), DataparserTransform())
        panel = sketch_viewer.SketchPanel(server, session, tmp_path / "sketches")
        contents = []
        for view in views_of(STICK, SIDE_VIEWS + (FROM_ABOVE,)):
            session.capture(PinholeCamera.from_view(view))
            session.pending.mask = view.mask.copy()
            panel.add_view()
            contents.append(panel.coverage.content)
        assert contents[0] == ""  # one view: nothing to say yet
        assert contents[1].startswith("**Warning:**") and "Add a sketch from above" in contents[1]
        assert "Warning" not in contents[2] and "at most" in contents[2]
        panel.remove_last()
        assert "Add a sketch from above" in panel.coverage.content
    finally:
        server.stop()


def test_masks_that_do_not_overlap_in_3d_are_said_to_barely_agree():
    """Mask bounding boxes that meet in 3D, masks that do not: no ratio, no suggestion, a clear word instead."""
    views = views_of(box_points((0.3, 0.3, 0.3)), SIDE_VIEWS)
    top_and_bottom, middle = views[0].mask.copy(), np.zeros_like(views[1].mask)
    rows = np.nonzero(top_and_bottom.any(axis=1))[0]
    top_and_bottom[rows[0] + 3 : rows[-1] - 2] = False  # view 0: only the top and bottom edges of the cube
    middle[SIZE // 2 - 2 : SIZE // 2 + 2] = views[1].mask[SIZE // 2 - 2 : SIZE // 2 + 2]  # view 1: a band at mid-height
    views = [SketchView(mask=mask, camera_to_world=v.camera_to_world, fl_x=v.fl_x, fl_y=v.fl_y, cx=v.cx, cy=v.cy,
                        name=v.name) for v, mask in zip(views, (top_and_bottom, middle))]
    check = check_hull(views, up=UP)
    assert check.empty and not check.underdetermined
    assert "barely overlap in 3D" in check.message()
