"""`sked-sketch`: draw a sketch set over a trained base in the nerfstudio viewer, or headless.

    sked-sketch outputs/scene/nerfacto/RUN/config.yml --out my-sketches/      # viewer + SKED panel
    sked-sketch canvases outputs/.../config.yml canvases/ --images 0 7        # renders to paint on
    sked-sketch import canvases/ --out my-sketches/                           # painted canvases -> set
    sked-sketch check my-sketches/                                            # do the sketches pin the part down?

The viewer is nerfstudio's own (ViewerState); the SKED panel is a folder of viser controls
driving a `SketchSession`. The base run is only read (the viewer's log goes to a temp folder).
The panel, `import` and `check` report the set's coverage (`sked_ns.drawing.hull_check`): how much larger the
region the sketches allow looks than each sketch shows, and which view to add when that is too much.
"""

from __future__ import annotations

import argparse
import contextlib
import shlex
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, List, Optional

import numpy as np
import torch

from sked_ns.drawing.sketching import (
    PinholeCamera,
    SketchSession,
    check_new_canvas_folder,
    import_canvases,
    sketch_set_coverage,
    write_canvases,
)
from sked_ns.engine.viewer import add_frustum, frame_on_connect, show_sketch_views, step_back, training_poses
from sked_ns.errors import ArgumentParser, SkedFileExistsError, SkedUserError, reading
from sked_ns.method.edit_box import content_bounds
from sked_ns.progress import Heartbeat
from sked_ns.sketches.sketch_set import SKETCHES_JSON, DataparserTransform

VIEW_WIDTH = 512
"""Width of a captured view; the height follows the browser window's aspect."""
SKETCH_PANEL_ORDER = -1.0
"""The panel's place in the viewer's sidebar: above nerfstudio's controls (viser numbers those from 1)."""
CAPTURE_BEAT_SECONDS = 2.0
"""The panel says how long the captured view has been rendering this often."""
CPU_PREVIEW_WIDTH = 160
"""On a CPU the captured view's picture is rendered this wide and upsampled: it is only the
backdrop to click on (the mask keeps VIEW_WIDTH), and it costs about 1/10 of the rays."""
CPU_RAYS_PER_CHUNK = 4096
"""Rays a CPU renders at once: nerfacto's default chunk (32,768) holds several GB of samples per render, which a
laptop (or the viewer's render beside a captured view) runs out of."""


def load_base(run: Path, device: str, flag: str = "sked-sketch", data: Optional[Path] = None):
    """(run folder, pipeline, dataparser transform) of a base run, for sked-sketch and the edit session's viewer, with
    a clear error if it does not load; `data`: the dataset's folder when it is not where the run's config.yml says."""
    from sked_ns.evaluation.render import load_pipeline

    run = run.parent if run.name == "config.yml" else run
    with reading(f"{flag}: the base {run}", "Point at a trained run's folder or its config.yml, with the data "
                 "it was trained on where its config.yml says."):
        pipeline = load_pipeline(run, device, flag=flag, data=data)
    if device == "cpu":  # the viewer's renders and each captured view go through the model in chunks this size
        config = pipeline.model.config
        config.eval_num_rays_per_chunk = min(config.eval_num_rays_per_chunk, CPU_RAYS_PER_CHUNK)
    return run, pipeline, sketch_frame(pipeline)


def sketch_frame(pipeline) -> DataparserTransform:
    """The frame sketch sets are saved in (the data's transforms.json frame, the one sets copied from the photos'
    entries are in) -> the pipeline's model frame."""
    from sked_ns.sketches.data_frame import data_frame_transform

    recorded = getattr(pipeline.datamanager, "data_frame_transform", None)
    if recorded is not None:  # an edit as the base: the frame it edited in, as it recorded it (its data may have moved)
        return recorded
    outputs = pipeline.datamanager.train_dataparser_outputs
    transform = DataparserTransform(outputs.dataparser_transform.numpy().astype(np.float64), float(outputs.dataparser_scale))
    return data_frame_transform(pipeline.datamanager.config.dataparser, transform)


def renderer(pipeline, lock: Optional[threading.Lock] = None, max_width: Optional[int] = None):
    """PinholeCamera -> (h, w, 3) numpy render of the pipeline's model; rendered at most
    `max_width` wide (same field of view) and resized to the camera's size."""
    import cv2

    from sked_ns.evaluation.render import render_camera
    from sked_ns.sketches.cameras import cameras_of

    def render(camera: PinholeCamera) -> np.ndarray:
        scale = min(1.0, max_width / camera.width) if max_width else 1.0
        width, height = max(1, round(camera.width * scale)), max(1, round(camera.height * scale))
        sx, sy = width / camera.width, height / camera.height
        cameras = cameras_of(torch.tensor(camera.camera_to_world[None], dtype=torch.float32), camera.fl_x * sx,
                             camera.fl_y * sy, camera.cx * sx, camera.cy * sy, width, height)
        with lock or contextlib.nullcontext():
            image = render_camera(pipeline.model, cameras)["rgb"].numpy()
        if (width, height) != (camera.width, camera.height):
            image = cv2.resize(image, (camera.width, camera.height), interpolation=cv2.INTER_LINEAR)
        return image

    return render


def client_camera(server, width: int = VIEW_WIDTH) -> Optional[PinholeCamera]:
    """The first connected browser's camera (model frame), as nerfstudio's ViewerControl reads it."""
    import viser.transforms as vtf
    from nerfstudio.cameras.cameras import CameraType
    from nerfstudio.viewer.utils import CameraState, get_camera
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

    clients = server.get_clients()
    if not clients:
        return None
    client = clients[min(clients)]
    rotation = vtf.SO3(wxyz=client.camera.wxyz) @ vtf.SO3.from_x_radians(np.pi)
    position = torch.tensor(client.camera.position, dtype=torch.float64) / VISER_NERFSTUDIO_SCALE_RATIO
    c2w = torch.cat([torch.tensor(rotation.as_matrix()), position[:, None]], dim=1)
    state = CameraState(fov=client.camera.fov, aspect=client.camera.aspect, c2w=c2w, camera_type=CameraType.PERSPECTIVE)
    height = max(1, round(width / client.camera.aspect))
    return PinholeCamera.from_nerfstudio(get_camera(state, height, width))


class SketchPanel:
    """The SKED folder in the viewer's control panel."""

    def __init__(self, server, session: SketchSession, out: Optional[Path]) -> None:
        """`out`: the folder the Save button writes; None for no Save controls (an edit session saves the set
        where its round is written)."""
        self.server, self.session = server, session
        self.handles: list = []  # scene nodes of the saved views and the edit box
        self.pending_handle = None  # the frustum of the view being drawn
        self.last_message = ""
        self.out_text = self.save_button = None
        self.on_views_changed: Callable[[], None] = lambda: None
        self._capturing = threading.Lock()  # repeated presses while a view renders are ignored
        gui = server.gui
        with gui.add_folder("SKED sketch", order=SKETCH_PANEL_ORDER):
            self.status = gui.add_markdown("Move to a view of the region, then **Capture view**.")
            self.coverage = gui.add_markdown("")  # does the set pin the part down (hull_check)?
            self.capture_button = gui.add_button("Capture view")
            self.close_button = gui.add_button("Close scribble", disabled=True)
            self.upload_button = gui.add_upload_button("Upload mask", mime_type="image/png", disabled=True)
            self.clear_button = gui.add_button("Clear mask", disabled=True)
            self.add_button = gui.add_button("Add view", disabled=True)
            self.remove_button = gui.add_button("Remove last view", disabled=True)
            if out is not None:
                self.out_text = gui.add_text("Save to", initial_value=str(out))
                self.save_button = gui.add_button("Save sketch set", disabled=True)
        self.capture_button.on_click(lambda _: self._guarded(self.capture))
        self.close_button.on_click(lambda _: self._guarded(self.close_scribble))
        self.upload_button.on_upload(lambda event: self._guarded(lambda: self.upload(event.target.value)))
        self.clear_button.on_click(lambda _: self._guarded(self.clear))
        self.add_button.on_click(lambda _: self._guarded(self.add_view))
        self.remove_button.on_click(lambda _: self._guarded(self.remove_last))
        if self.save_button is not None:
            self.save_button.on_click(lambda _: self._guarded(self.save))

    # ---- actions (also called directly by tests) ---------------------------------------------
    def capture(self) -> None:
        if not self._capturing.acquire(blocking=False):
            self._say("Still rendering the captured view...")
            return
        try:
            with Heartbeat("sked-sketch", "rendering the captured view", every_seconds=CAPTURE_BEAT_SECONDS,
                           say=lambda line: self._say(line[:1].upper() + line[1:])):
                self.session.capture(client_camera(self.server))
        finally:
            self._capturing.release()
        self.server.scene.on_pointer_event("click")(self._on_click)
        self._show_pending()
        self._set_drawing(True)
        self._say("Click the points of a closed outline around the region (or upload a mask), then **Add view**.")

    def _on_click(self, event) -> None:
        self._guarded(lambda: self.click(*event.screen_pos[0]))

    def click(self, x: float, y: float) -> None:
        count = self.session.add_point(x, y)
        self._show_pending()
        self._say(f"{count} point(s); **Close scribble** when the outline is complete.")

    def close_scribble(self) -> None:
        self.session.close_scribble()
        self._show_pending()
        self._say("Outline filled. Add another outline, or **Add view**.")

    def upload(self, uploaded) -> None:
        warning = self.session.upload_mask(uploaded.content, uploaded.name)
        self._show_pending()
        self._say(warning or f"{uploaded.name}: mask loaded.")

    def clear(self) -> None:
        self.session.clear()
        self._show_pending()

    def add_view(self) -> None:
        self.session.add_view()
        self.server.scene.remove_pointer_callback()
        self._set_drawing(False)
        self._show_views()
        step_back(self.server)  # the camera is where the view was taken: its frustum would fill the screen
        box = self.session.edit_box()
        self._say(f"{len(self.session.views)} view(s)." + (
            f" Edit box {np.round(box.min, 2).tolist()} .. {np.round(box.max, 2).tolist()}." if box else
            " Sketch the same region from a second viewpoint."))
        self._show_coverage()

    def remove_last(self) -> None:
        self.session.remove_view(len(self.session.views) - 1)
        self._show_views()
        self._say(f"{len(self.session.views)} view(s).")
        self._show_coverage()

    def restart(self, session: SketchSession, message: str) -> None:
        """Draw a new set: `session` replaces the current one, and its views leave the scene."""
        self.session = session
        for handle in self.handles + ([self.pending_handle] if self.pending_handle is not None else []):
            handle.remove()
        if self.pending_handle is not None:  # a view was being drawn: its clicks stop
            self.server.scene.remove_pointer_callback()
        self.handles, self.pending_handle = [], None
        self._set_drawing(False)
        self.coverage.content = ""
        self._say(message)

    def set_enabled(self, enabled: bool) -> None:
        """Whether views can be captured now (an edit session turns sketching off while a round trains)."""
        self._set_drawing(False)
        self.capture_button.disabled = not enabled
        if not enabled:
            self.remove_button.disabled = True

    def save(self) -> Path:
        path = self.session.save(Path(self.out_text.value))
        # The folder's name only: a long unbreakable path would widen the panel past the window.
        self._say(f"Saved {len(self.session.views)} views to **{path.parent.name}/** (the folder under *Save to*).")
        return path

    # ---- display ------------------------------------------------------------------------
    def _guarded(self, action) -> None:
        guarded(action, self._say)

    def _say(self, message: str) -> None:
        self.status.content = message
        self.last_message = message

    def _show_coverage(self) -> None:
        """The hull check of the views so far, a warning when they underdetermine the part."""
        check = self.session.hull_check()
        if check is None:
            self.coverage.content = ""
        else:
            self.coverage.content = ("**Warning:** " if check.underdetermined else "") + check.message()

    def _set_drawing(self, drawing: bool) -> None:
        for button in (self.close_button, self.upload_button, self.clear_button, self.add_button):
            button.disabled = not drawing
        self.remove_button.disabled = not self.session.views
        if self.save_button is not None:
            self.save_button.disabled = len(self.session.views) < 2
        self.on_views_changed()

    def _show_pending(self) -> None:
        pending = self.session.pending
        if pending is not None:
            self.pending_handle = add_frustum(self.server, "/sked/pending", pending.camera, self.session.preview(),
                                              (255, 160, 0))

    def _show_views(self) -> None:
        for handle in self.handles:
            handle.remove()
        if self.session.pending is None and self.pending_handle is not None:  # the view was added
            self.pending_handle.remove()
            self.pending_handle = None
        images = [self.session.view_image(index) for index in range(len(self.session.views))]
        self.handles = show_sketch_views(self.server, self.session.views, self.session.edit_box(), images=images)
        self._set_drawing(False)


def guarded(action: Callable[[], object], say: Callable[[str], None]) -> None:
    """A panel button's action: a user's mistake (ValueError, FileExistsError) is said in the panel; anything else
    too, and raised (a callback thread would swallow it)."""
    try:
        action()
    except (ValueError, FileExistsError) as error:
        say(f"**Error:** {error}")
    except Exception as error:
        say(f"**Unexpected error:** {type(error).__name__}: {error}")
        raise


def start_viewer(run: Path, out: Path, port: Optional[int] = None, device: str = "cpu", flag: str = "sked-sketch"):
    """nerfstudio's viewer on the base with the SKED panel; returns (viewer state, panel)."""
    from nerfstudio.viewer.viewer import Viewer as ViewerState

    from sked_ns.engine.base_scene import resolve_base

    run, pipeline, transform = load_base(run, device, flag)
    viewer_config = resolve_base(run, flag=flag).config.viewer
    if port is not None:
        viewer_config.websocket_port = port
    lock = threading.Lock()
    log_dir = Path(tempfile.mkdtemp(prefix="sked-sketch-"))  # never write into the base's run folder
    viewer = ViewerState(viewer_config, log_filename=log_dir / "viewer_log.txt",
                         datapath=pipeline.datamanager.get_datapath(), pipeline=pipeline, train_lock=lock)
    viewer.init_scene(train_dataset=pipeline.datamanager.train_dataset, train_state="completed",
                      eval_dataset=pipeline.datamanager.eval_dataset)
    viewer.update_scene(step=0)
    frame_on_connect(viewer.viser_server, training_poses(pipeline))
    preview_width = CPU_PREVIEW_WIDTH if device == "cpu" else None
    bounds = content_bounds(pipeline.model.config, pipeline.model.scene_box.aabb.numpy())
    session = SketchSession(renderer(pipeline, lock, preview_width), transform, *bounds)
    return viewer, SketchPanel(viewer.viser_server, session, out)


def stop_viewer(viewer) -> None:
    """Stop the server and join the per-browser render threads, so none is mid-render when the
    interpreter exits (torch then aborts the process)."""
    from nerfstudio.viewer.render_state_machine import RenderStateMachine

    # A closed browser's machine has already left viewer.render_statemachines but may still render.
    machines = [thread for thread in threading.enumerate()
                if isinstance(thread, RenderStateMachine) and thread.viewer is viewer]
    viewer.viser_server.stop()
    for machine in machines:
        machine.running = False
        machine.interrupt_render_flag = True
    for machine in machines:
        machine.join(timeout=60)


def training_cameras(pipeline, indices: List[int]) -> List[PinholeCamera]:
    cameras = pipeline.datamanager.train_dataset.cameras
    for index in indices:
        if not 0 <= index < len(cameras):
            raise SkedUserError(f"sked-sketch canvases: --images {index}: the base has {len(cameras)} training images "
                                f"(0..{len(cameras) - 1}).")
    return [PinholeCamera.from_nerfstudio(cameras[index : index + 1]) for index in indices]


def port_number(text: str) -> int:
    """argparse type: a TCP port."""
    if not (text.isdigit() and 1 <= int(text) <= 65535):
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number (1-65535)")
    return int(text)


def new_sketch_folder(out: Path, command: str) -> Path:
    """--out must not hold a sketch set yet: refused before anything is loaded or painted, never replaced."""
    if (out / SKETCHES_JSON).exists():
        raise SkedFileExistsError(f"{command}: --out {out} already holds a sketch set ({out / SKETCHES_JSON}); choose a new "
                         "folder (an existing sketch set is never overwritten).")
    return out


def entrypoint(argv: Optional[List[str]] = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    device = "cuda" if torch.cuda.is_available() else "cpu"
    if argv and argv[0] == "canvases":
        parser = ArgumentParser(prog="sked-sketch canvases", description="Render canvases to paint masks on.")
        parser.add_argument("base", type=Path, help="base run folder or its config.yml")
        parser.add_argument("folder", type=Path, help="new folder for view_XX.png and canvases.json")
        parser.add_argument("--images", type=int, nargs="+", required=True, help="training image indices to render")
        args = parser.parse_args(argv[1:])
        check_new_canvas_folder(args.folder)  # before the base loads
        _, pipeline, transform = load_base(args.base, device)
        path = write_canvases(renderer(pipeline), training_cameras(pipeline, args.images), transform, args.folder,
                              names=[f"training image {i}" for i in args.images])
        print(f"wrote {path}: paint the region on a copy of each view_XX.png saved as view_XX_sketch.png "
              f"(or a white-on-black view_XX_mask.png), then run: sked-sketch import {shlex.quote(str(args.folder))} --out SKETCHES")
        return
    if argv and argv[0] == "import":
        parser = ArgumentParser(prog="sked-sketch import", description="Painted canvases -> sketch set.")
        parser.add_argument("folder", type=Path, help="the canvases folder (canvases.json and the painted views)")
        parser.add_argument("--out", type=Path, required=True, help="new folder to save the sketch set into")
        args = parser.parse_args(argv[1:])
        new_sketch_folder(args.out, "sked-sketch import")
        print(f"wrote {import_canvases(args.folder, args.out)}")
        try:
            print(sketch_set_coverage(args.out).message())
        except ValueError as error:  # the set is written; an edit would refuse it with this same message
            print(f"sked-sketch import: the set's coverage could not be checked: {error}")
        return
    if argv and argv[0] == "check":
        parser = ArgumentParser(prog="sked-sketch check", description="Do a sketch set's views pin the part "
                                "down? Prints the coverage report (exit status 0 either way).")
        parser.add_argument("folder", type=Path, help="sketch set folder (with sketches.json)")
        args = parser.parse_args(argv[1:])
        print(sketch_set_coverage(args.folder).message())
        return
    parser = ArgumentParser(
        prog="sked-sketch", description=__doc__.split("\n")[0],
        usage="sked-sketch BASE --out FOLDER [--port PORT]      draw in the viewer on the base (or --load-config)\n"
              "       sked-sketch canvases BASE FOLDER --images I [I ...]   canvases to paint over, headless\n"
              "       sked-sketch import CANVASES --out FOLDER          painted canvases -> a sketch set\n"
              "       sked-sketch check FOLDER                         do the sketches pin the part down?",
        epilog="Each subcommand has its own --help.")
    parser.add_argument("base", type=Path, nargs="?", default=None, help="base run folder or its config.yml")
    parser.add_argument("--load-config", type=Path, default=None, help="the base's config.yml, as ns-viewer takes it")
    parser.add_argument("--out", type=Path, required=True, help="folder to save the sketch set into (must be new)")
    parser.add_argument("--port", type=port_number, default=None,
                        help="the viewer's port (default: nerfstudio's, 7007, or the next free one)")
    args = parser.parse_args(argv)
    if (args.base is None) == (args.load_config is None):
        parser.error("give the base once: its run folder (or config.yml), or --load-config config.yml")
    flag = "sked-sketch" if args.base is not None else "--load-config"
    args.base = args.base if args.base is not None else args.load_config
    new_sketch_folder(args.out, "sked-sketch")
    viewer, _ = start_viewer(args.base, args.out, args.port, device, flag)
    where = viewer.viewer_info[0] if viewer.viewer_info else "The viewer is running"
    print(f"SKED sketching: {where}; open it in a browser, sketch two or more views, and Save sketch set "
          f"({args.out}).")
    try:
        while True:
            time.sleep(0.1)
    finally:
        stop_viewer(viewer)


if __name__ == "__main__":
    entrypoint()
