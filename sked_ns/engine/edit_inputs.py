"""Every input of an edit, read and checked before `ns-train sked` writes anything.

nerfstudio makes the run folder and config.yml first; only then does it read the data, build the
model (which loads the sketch set) and, at the first step, the guidance's weights. A mistake in any
of them would surface there, as a traceback, after the run folder is made and the images are cached.
`check_edit_inputs` reads each of them as the edit will, once the edit's config is resolved
(trainer.resolve_edit), so that every mistake is refused first, in one line naming its flag or file.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import torch

from sked_ns.engine.drawn_sketches import sketches_pending
from sked_ns.engine.memory_plan import check_memory
from sked_ns.engine.pipeline import refuse_multi_device
from sked_ns.errors import (
    SkedFileNotFoundError,
    SkedUserError,
    check_name_lengths,
    existing_folder,
    reading,
    warn,
)
from sked_ns.guidance import check_guidance
from sked_ns.method.options import is_carving
from sked_ns.method.validation import check_optimizers, check_sketch_pixels
from sked_ns.sketches.sketch_set import load_sketch_set

MISSING_IMAGES_SHOWN = 3
"""Missing photos named in the message; the count says how many more."""


def check_edit_inputs(config) -> None:
    """The devices, the guidance (prompt and weights), the sketch set and the data with it, as the edit reads them."""
    model = config.pipeline.model
    check_devices(config.machine)
    warn_idle_mixed_precision(config)
    check_optimizers(config.optimizers)  # the edit's own (a splat edit's set at its start)
    check_guidance(model.guidance, model.prompt)
    if not is_carving(model):
        model.guidance.check_available()  # weights are loaded only at the first step
    if model.sketches is None:
        raise SkedUserError("ns-train sked needs the sketches: --sketches <folder with sketches.json>.")
    check_name_lengths(Path(model.sketches), "--sketches")
    if sketches_pending(config):  # drawn in the viewer: checked, with what follows from them, when saved
        check_sketches_in_data(config, with_sketches=False)
        return
    sketch_set = load_sketch_set(model.sketches)
    check_sketch_pixels(sketch_set, model.silhouette_resolution)
    check_sketches_in_data(config)
    check_memory(config)  # the plan printed; an edit that cannot fit on its GPU is refused with the options that do
    check_disk_space(config)
    if model.base_kept is None:  # a new edit (a resumed one has its own copy of the base)
        warn_live_base(Path(model.base_checkpoint))


def warn_live_base(checkpoint: Path) -> None:
    """A base still training changes after the edit starts: the edit is of its checkpoint as saved now (copied into
    the edit's folder, engine/kept_base.py), not of what the base becomes; almost surely not what was meant."""
    from sked_ns.run_lock import describe, holder, is_this_process

    run = checkpoint.parent.parent
    writer = holder(run)
    if writer is not None and not is_this_process(writer):
        warn(f"--load-dir {run}: that run is still training ({describe(writer)}); this edit changes its "
             f"{checkpoint.name} as saved now, not the scene it is training towards. Wait for it to end to edit that.")


CHECKPOINT_MARGIN = 1.25
"""An edit's checkpoint against its base's: the same modules and optimiser state, plus what the edit adds."""


def check_run_folder_names(config) -> None:
    """Every name of the run's path within what its file system allows: one too long fails every file operation
    under it (ENAMETOOLONG), so it is refused naming the flag that gave it, before anything is looked for there."""
    output = Path(config.output_dir)
    check_name_lengths(output, "--output-dir")
    check_name_lengths(output / str(config.experiment_name), "--experiment-name")
    run = output / str(config.experiment_name) / str(config.method_name) / str(config.timestamp)
    check_name_lengths(run, "--timestamp")
    check_name_lengths(Path(config.get_checkpoint_dir()) / f"step-{0:09d}.ckpt", "--output-dir")


def check_disk_space(config) -> None:
    """The checkpoints must fit where they go, found now and not after the first hour of training: refused when the
    first save cannot fit (a save writes the new checkpoint beside the last), warned when all that are kept cannot;
    and their folder's names must be ones its file system can hold."""
    import shutil

    from sked_ns.engine.kept_base import KEPT
    from sked_ns.method.frozen_base import base_weights

    check_run_folder_names(config)
    model = config.pipeline.model
    base = base_weights(model).stat().st_size if model.base_checkpoint else 0  # the edit's own copy once it has one
    sizes = [base] if base else []
    if config.load_dir is not None:  # a resumed edit: its own checkpoints say it
        sizes += [path.stat().st_size for path in Path(config.load_dir).glob("step-*.ckpt")]
    if not sizes:
        return
    size = CHECKPOINT_MARGIN * max(sizes)
    folder = config.get_checkpoint_dir()
    own = model.base_kept is not None and Path(model.base_kept).parent == folder.parent.absolute() / KEPT
    copy = 0 if own or not base else base  # a new run folder gets its own copy of the base (at most this size)
    free = shutil.disk_usage(existing_folder(folder)).free
    gb = 2**30
    if free < 2 * size + copy:
        kept = f", and its copy of the base about {copy / gb:.2f} GB" if copy else ""
        raise SkedUserError(f"--output-dir {config.output_dir}: {free / gb:.2f} GB free where the checkpoints go "
                            f"({folder}), and the edit needs about {(2 * size + copy) / gb:.2f} GB (each checkpoint "
                            f"about {size / gb:.2f} GB, the new one written beside the last{kept}). Free space there, "
                            "or pass another --output-dir.")
    saves = config.max_num_iterations // max(config.steps_per_save, 1) + 1
    if not config.save_only_latest_checkpoint and free < saves * size:
        warn(f"--save-only-latest-checkpoint False: the edit's {saves} checkpoints need about {saves * size / gb:.1f} "
             f"GB, and {folder} has {free / gb:.1f} GB free; the later saves will fail.")


def warn_idle_mixed_precision(config, argv=None) -> None:
    """--mixed-precision True typed for a CPU edit: nerfstudio trains in fp32 there without a word (the presets'
    own True is for the GPU and is not warned)."""
    from sked_ns.engine.resume import command_line_paths

    if config.mixed_precision and config.machine.device_type == "cpu" and \
            "mixed_precision" in command_line_paths(config, argv):
        warn("--mixed-precision True: has no effect on the CPU, where nerfstudio trains in fp32 (it halves the "
             "guidance's memory and time on a GPU only).")


def check_devices(machine) -> None:
    refuse_multi_device(machine.num_devices * machine.num_machines)
    if machine.device_type == "cuda" and not torch.cuda.is_available():
        raise SkedUserError("--machine.device-type cuda: torch sees no CUDA device here. Pass --machine.device-type "
                            "cpu (slow), or run where a GPU is.")
    if machine.device_type == "mps" and not torch.backends.mps.is_available():
        raise SkedUserError("--machine.device-type mps: this machine has no Apple GPU. Pass --machine.device-type cpu.")


def check_sketches_in_data(config, with_sketches: bool = True) -> None:
    """The data as its dataparser reads it, and the sketch set in the frame it gives: placed as the model places it
    (model_frame_sketches) and boxed in the space the base holds (compute_edit_box, content_bounds), and the base
    trained in that frame."""
    from sked_ns.engine.base_scene import check_same_frame, dataparser_name, edited_base
    from sked_ns.engine.datamanager import outputs_transform, sketch_frame_metadata
    from sked_ns.method.edit_box import compute_edit_box, content_bounds
    from sked_ns.method.frozen_base import check_photo_count, read_model_state
    from sked_ns.sketches.data_frame import model_frame_sketches

    datamanager, model = config.pipeline.datamanager, config.pipeline.model
    dataparser = copy.deepcopy(datamanager.dataparser)
    data = datamanager.data or config.data or dataparser.data  # as VanillaDataManager sets it
    if data is None:
        raise SkedUserError("no --data: an edit reads the base's photos through the base's dataparser, typed after "
                            "every other flag (e.g. `nerfstudio-data --data <folder>`).")
    dataparser.data = Path(data)
    check_finite_camera_file(dataparser.data)
    name = dataparser_name(dataparser)
    with reading(f"--data {dataparser.data}", f"Is it a dataset {name} reads? (give the dataparser after every "
                 "other flag, e.g. `nerfstudio-data --data <folder>`, as the base was trained)"):
        outputs = dataparser.setup().get_dataparser_outputs(split="train")
        metadata = sketch_frame_metadata(dataparser, outputs)
    check_photos_exist(outputs.image_filenames, f"--data {dataparser.data}")
    if model.base_checkpoint is not None:
        base = edited_base(model)
        checkpoint = base.checkpoint
        check_same_frame(base, outputs_transform(outputs))
        # Refused here, before the run folder exists, as the model's set-up would refuse it after.
        check_photo_count(read_model_state(checkpoint), len(outputs.image_filenames), checkpoint)
    if not with_sketches:
        return
    sketch_set = model_frame_sketches(model.sketches, metadata)
    compute_edit_box(sketch_set.views, *content_bounds(model, outputs.scene_box.aabb.numpy()))


def _first_non_finite(value, path: str):
    """The JSON path of the first NaN or infinity in a parsed JSON value (Python's json reads them), or None."""
    if isinstance(value, float) and not math.isfinite(value):
        return path
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        found = _first_non_finite(item, f"{path}.{key}" if isinstance(key, str) else f"{path}[{key}]")
        if found:
            return found
    return None


def check_finite_camera_file(data: Path) -> None:
    """NaN or infinity in the data's transforms.json would turn into a scene scale of nan, reported as a frame
    mismatch far from its cause: name the frame and field that hold it."""
    path = data / "transforms.json" if data.is_dir() else data
    if path.suffix != ".json" or not path.is_file():
        return
    try:
        parsed = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return  # unreadable: the dataparser says so, as it reads it
    found = _first_non_finite(parsed, "")
    if found:
        field = found.lstrip(".")
        frame = ""
        if field.startswith("frames["):
            index = int(field[len("frames["):].split("]")[0])
            name = parsed["frames"][index].get("file_path") if isinstance(parsed["frames"][index], dict) else None
            frame = f" (the frame of {name})" if name else ""
        raise SkedUserError(f"{path}: {field}{frame} is not a finite number (NaN or infinity); fix that value, or "
                            "pass the data the base was trained on.")


def check_photos_exist(filenames, where: str) -> None:
    missing = [Path(name) for name in filenames if not Path(name).is_file()]
    if missing:
        more = f" and {len(missing) - MISSING_IMAGES_SHOWN} more" if len(missing) > MISSING_IMAGES_SHOWN else ""
        raise SkedFileNotFoundError(f"{where}: {len(missing)} of its {len(filenames)} training photos are missing: "
                                    f"{', '.join(map(str, missing[:MISSING_IMAGES_SHOWN]))}{more}. Restore them, or "
                                    "pass the dataset the base was trained on.")

