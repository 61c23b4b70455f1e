"""Every input of an edit, read and checked before `ns-train sked` writes anything.

nerfstudio makes the run folder and config.yml first; only then does it read the data, build the
model (which loads the sketch set) and, at the first step, the guidance's weights. A mistake in any
of them would surface there, as a traceback, after the run folder is made and the images are cached.
`check_edit_inputs` reads each of them as the edit will, once the edit's config is resolved
(trainer.resolve_edit), so that every mistake is refused first, in one line naming its flag or file.
"""

from __future__ import annotations

import copy
from pathlib import Path

import torch

from sked_ns.engine.memory_plan import check_memory
from sked_ns.engine.drawn_sketches import sketches_pending
from sked_ns.errors import SkedFileNotFoundError, SkedUserError, reading
from sked_ns.guidance import check_guidance
from sked_ns.method.options import is_carving
from sked_ns.engine.pipeline import refuse_multi_device
from sked_ns.sketches.sketch_set import load_sketch_set
from sked_ns.method.validation import check_sketch_pixels

MISSING_IMAGES_SHOWN = 3
"""Missing photos named in the message; the count says how many more."""


def check_edit_inputs(config) -> None:
    """The devices, the guidance (prompt and weights), the sketch set and the data with it, as the edit reads them."""
    model = config.pipeline.model
    check_devices(config.machine)
    check_guidance(model.guidance, model.prompt)
    if not is_carving(model):
        model.guidance.check_available()  # weights are loaded only at the first step
    if model.sketches is None:
        raise SkedUserError("ns-train sked needs the sketches: --sketches <folder with sketches.json>.")
    if sketches_pending(config):  # drawn in the viewer: checked, with what follows from them, when saved
        check_sketches_in_data(config, with_sketches=False)
        return
    sketch_set = load_sketch_set(model.sketches)
    check_sketch_pixels(sketch_set, model.silhouette_resolution)
    check_sketches_in_data(config)
    check_memory(config)  # the plan printed; an edit that cannot fit on its GPU is refused with the options that do


def check_devices(machine) -> None:
    refuse_multi_device(machine.num_devices * machine.num_machines)
    if machine.device_type == "cuda" and not torch.cuda.is_available():
        raise SkedUserError("--machine.device-type cuda: torch sees no CUDA device here. Pass --machine.device-type "
                            "cpu (slow), or run where a GPU is.")
    if machine.device_type == "mps" and not torch.backends.mps.is_available():
        raise SkedUserError("--machine.device-type mps: this machine has no Apple GPU. Pass --machine.device-type cpu.")


def check_sketches_in_data(config, with_sketches: bool = True) -> None:
    """The data as its dataparser reads it, and the sketch set in the frame it gives: placed as the model places it
    (model_frame_sketches) and boxed inside its scene box (compute_edit_box), and the base trained in that frame."""
    from sked_ns.engine.base_scene import check_same_frame, dataparser_name, resolve_base
    from sked_ns.engine.datamanager import outputs_transform, sketch_frame_metadata
    from sked_ns.sketches.data_frame import model_frame_sketches
    from sked_ns.method.edit_box import compute_edit_box

    datamanager, model = config.pipeline.datamanager, config.pipeline.model
    dataparser = copy.deepcopy(datamanager.dataparser)
    data = datamanager.data or config.data or dataparser.data  # as VanillaDataManager sets it
    if data is None:
        raise SkedUserError("no --data: an edit reads the base's photos through the base's dataparser, typed after "
                            "every other flag (e.g. `nerfstudio-data --data <folder>`).")
    dataparser.data = Path(data)
    name = dataparser_name(dataparser)
    with reading(f"--data {dataparser.data}", f"Is it a dataset {name} reads? (give the dataparser after every "
                 "other flag, e.g. `nerfstudio-data --data <folder>`, as the base was trained)"):
        outputs = dataparser.setup().get_dataparser_outputs(split="train")
        metadata = sketch_frame_metadata(dataparser, outputs)
    check_photos_exist(outputs.image_filenames, f"--data {dataparser.data}")
    if model.base_checkpoint is not None:
        check_same_frame(resolve_base(Path(model.base_checkpoint)), outputs_transform(outputs))
    if not with_sketches:
        return
    sketch_set = model_frame_sketches(model.sketches, metadata)
    compute_edit_box(sketch_set.views, scene_box=outputs.scene_box.aabb.numpy())


def check_photos_exist(filenames, where: str) -> None:
    missing = [Path(name) for name in filenames if not Path(name).is_file()]
    if missing:
        more = f" and {len(missing) - MISSING_IMAGES_SHOWN} more" if len(missing) > MISSING_IMAGES_SHOWN else ""
        raise SkedFileNotFoundError(f"{where}: {len(missing)} of its {len(filenames)} training photos are missing: "
                                    f"{', '.join(map(str, missing[:MISSING_IMAGES_SHOWN]))}{more}. Restore them, or "
                                    "pass the dataset the base was trained on.")

