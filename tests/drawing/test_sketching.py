"""Drawing sketch sets: the session behind the viewer panel, and the headless canvases."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sked_ns.demo.scenes import sphere as demo_scene
from sked_ns.drawing.sketching import (
    CANVASES_JSON,
    PinholeCamera,
    SketchSession,
    import_canvases,
    write_canvases,
)
from sked_ns.sketches.sketch_set import DataparserTransform, load_sketch_set

# A dataparser-like transform: a rotation about z, a shift and a scale (data -> model frame).
ANGLE = 0.3
TRANSFORM = DataparserTransform(
    np.array([[np.cos(ANGLE), -np.sin(ANGLE), 0, 0.1], [np.sin(ANGLE), np.cos(ANGLE), 0, -0.2], [0, 0, 1, 0.05]]), 0.4
)


def _render(camera: PinholeCamera) -> np.ndarray:
    rows, cols = np.mgrid[0 : camera.height, 0 : camera.width]
    return np.stack([cols / camera.width, rows / camera.height, np.full(rows.shape, 0.5)], axis=-1)


def _hat_views(size=64):
    """The hat's sketch views, in the model frame, as cameras + their true masks."""
    for view in demo_scene.SCENES["hat"].sketch_set(size=size).in_model_frame(TRANSFORM).views:
        camera = PinholeCamera.from_view(view)
        yield camera, view.mask


def _outline(mask: np.ndarray):
    """Screen positions in [0, 1] of points around the mask's outer contour."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    contour = max(contours, key=cv2.contourArea)[:, 0, :].astype(np.float64)
    return [((x + 0.5) / mask.shape[1], (y + 0.5) / mask.shape[0]) for x, y in contour]


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_clicked_outlines_become_a_sketch_set_in_the_data_frame(tmp_path):
    session = SketchSession(_render, TRANSFORM)
    truths = []
    for camera, truth in _hat_views():
        canvas = session.capture(camera)
        assert canvas.shape == (camera.height, camera.width, 3)
        for x, y in _outline(truth):
            session.add_point(x, y)
        session.close_scribble()
        assert _iou(session.pending.mask, truth) > 0.85
        assert session.preview()[session.pending.mask].mean(axis=0)[0] > 0.5, "the mask is tinted red"
        session.add_view()
        truths.append(truth)
    box = session.edit_box()
    assert box is not None and np.all(box.max > box.min)
    session.save(tmp_path / "sketches")
    loaded = load_sketch_set(tmp_path / "sketches")
    assert loaded.frame == "data"
    for (camera, _), saved, truth, drawn in zip(_hat_views(), loaded.in_model_frame(TRANSFORM).views, truths, session.views):
        np.testing.assert_allclose(saved.camera_to_world, camera.camera_to_world, atol=1e-9)
        assert np.array_equal(saved.mask, drawn.mask)
    data_views = demo_scene.SCENES["hat"].sketch_set(size=64).views
    for saved, original in zip(loaded.views, data_views):
        np.testing.assert_allclose(saved.camera_to_world, original.camera_to_world, atol=1e-9)


def test_session_refuses_bad_input_clearly(tmp_path):
    session = SketchSession(_render, TRANSFORM)
    with pytest.raises(ValueError, match="No viewer client is connected"):
        session.capture(None)
    with pytest.raises(ValueError, match="Capture view"):
        session.add_point(0.5, 0.5)
    camera, truth = next(_hat_views())
    session.capture(camera)
    session.add_point(0.2, 0.2)
    session.add_point(0.4, 0.2)
    with pytest.raises(ValueError, match="at least 3 points"):
        session.close_scribble()
    with pytest.raises(ValueError, match="outside the view"):
        session.add_point(1.5, 0.2)
    session.clear()
    with pytest.raises(ValueError, match="mask is empty"):
        session.add_view()
    with pytest.raises(ValueError, match="notes.txt: not an image"):
        session.upload_mask(b"hello", "notes.txt")
    # Same aspect, another size: resized, with a warning that says so.
    big = cv2.imencode(".png", cv2.resize(truth.astype(np.uint8) * 255, (128, 128), interpolation=cv2.INTER_NEAREST))[1]
    with pytest.warns(UserWarning, match="resized from 128x128"):
        message = session.upload_mask(big.tobytes(), "big.png")
    assert "resized" in message and _iou(session.pending.mask, truth) > 0.9
    wide = cv2.imencode(".png", np.zeros((64, 100), np.uint8))[1]
    with pytest.raises(ValueError, match="aspect ratio"):
        session.upload_mask(wide.tobytes(), "wide.png")


def test_saving_never_overwrites_a_sketch_set(tmp_path):
    session = SketchSession(_render, TRANSFORM)
    for camera, truth in _hat_views():
        session.capture(camera)
        session.upload_mask(cv2.imencode(".png", truth.astype(np.uint8) * 255)[1].tobytes(), "mask.png")
        session.add_view()
    existing = tmp_path / "sketches"
    session.save(existing)
    before = (existing / "sketches.json").read_bytes()
    with pytest.raises(FileExistsError, match="never overwritten"):
        session.save(existing)
    assert (existing / "sketches.json").read_bytes() == before
    session.remove_view(1)
    assert session.edit_box() is None, "one view cannot place the edit"
    with pytest.raises(ValueError, match="No view 5"):
        session.remove_view(5)


def test_painted_canvases_import_as_a_sketch_set(tmp_path):
    cameras, truths = zip(*_hat_views())
    write_canvases(_render, cameras, TRANSFORM, tmp_path / "canvases")
    assert (tmp_path / "canvases" / CANVASES_JSON).exists()
    with pytest.raises(FileExistsError):
        write_canvases(_render, cameras, TRANSFORM, tmp_path / "canvases")
    # View 0: an outline painted over the canvas; view 1: a separate white-on-black mask.
    canvas = cv2.imread(str(tmp_path / "canvases" / "view_00.png"))
    contour = (np.array(_outline(truths[0])) * [truths[0].shape[1], truths[0].shape[0]] - 0.5).round().astype(np.int32)
    cv2.polylines(canvas, [contour], isClosed=True, color=(0, 0, 255), thickness=1)
    cv2.imwrite(str(tmp_path / "canvases" / "view_00_sketch.png"), canvas)
    with pytest.raises(ValueError, match=r"1 painted view\(s\) \(none for view_01\)"):
        import_canvases(tmp_path / "canvases", tmp_path / "out")
    cv2.imwrite(str(tmp_path / "canvases" / "view_01_mask.png"), truths[1].astype(np.uint8) * 255)
    import_canvases(tmp_path / "canvases", tmp_path / "sketches")
    loaded = load_sketch_set(tmp_path / "sketches")
    assert _iou(loaded.views[0].mask, truths[0]) > 0.9 and np.array_equal(loaded.views[1].mask, truths[1])
    for saved, camera in zip(loaded.in_model_frame(TRANSFORM).views, cameras):
        np.testing.assert_allclose(saved.camera_to_world, camera.camera_to_world, atol=1e-6)


@pytest.mark.parametrize("held", ["sketches.json", "view_00.png", "notes/"])
def test_canvases_go_into_a_new_folder_only_refused_before_the_base_loads(tmp_path, monkeypatch, held):
    from sked_ns.drawing import sketch_viewer

    folder = tmp_path / "set"
    folder.mkdir()
    (folder / held).mkdir() if held.endswith("/") else (folder / held).write_text("the user's")
    before = sorted(p.name for p in folder.iterdir())
    monkeypatch.setattr(sketch_viewer, "load_base", lambda *args: pytest.fail("loaded the base"))
    kind = "a sketch set" if held == "sketches.json" else "1 file"
    with pytest.raises(FileExistsError, match=rf"sked-sketch canvases: {folder} already holds {kind}.*new folder"):
        sketch_viewer.entrypoint(["canvases", str(tmp_path / "base"), str(folder), "--images", "0"])
    assert sorted(p.name for p in folder.iterdir()) == before
    if not held.endswith("/"):
        assert (folder / held).read_text() == "the user's"
    with pytest.raises(FileExistsError, match="already holds"):  # the writer itself checks too
        write_canvases(_render, [next(iter(_hat_views()))[0]], TRANSFORM, folder)
    write_canvases(_render, [next(iter(_hat_views()))[0]], TRANSFORM, tmp_path / "empty")  # a new folder is fine
