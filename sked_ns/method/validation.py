"""Range checks for SKED's settings: refused before anything is written, named as the user types them.

A setting outside its legal range (a negative loss weight, a resolution of 0) would run and silently
wreck the edit, or fail deep inside with a shape error; one that is legal but almost surely a mistake
(a guidance render far larger than the paper's 128, a loss weight or learning rate orders of magnitude off:
USUAL_RANGES) gets a warning. The usual ranges are checked by one function (errors.unusual_settings) for SKED's
options (OPTION_RANGES) and each guidance's (its config's `usual_ranges`, guidance/base.py). `check_options` runs when `ns-train sked` resolves its config
(trainer.resolve_edit), `check_optimizers` with the edit's other inputs once its optimisers are known
(engine/edit_inputs.py), `check_sketch_pixels` once the sketch set is known (there too, once: not again when the
model is built).
"""

from __future__ import annotations

import math
from typing import Dict, List

from sked_ns.errors import (
    DATAMANAGER_FLAGS,
    UsualRange,
    flag,
    is_number,
    refuse,
    unusual,
    unusual_settings,
    warn_option,
)

LOSS_WEIGHTS = ("lambda_pres", "lambda_colour", "lambda_sil", "lambda_sp", "lambda_new_mass", "lambda_carve",
                "lambda_photo")
"""Every weight of SKED's objective (paper Eq. 6 and ours): a negative one rewards what its loss penalises."""
MIN_SKETCH_PIXELS = 16
"""A sketch covering fewer pixels than this in its L_sil render barely pulls (a 4x4 patch)."""
LARGE_GUIDANCE_RESOLUTION = 512
"""Stable Diffusion's own input size; the paper renders 128 and upsamples."""
SMALL_GUIDANCE_RESOLUTION = 32
SMALL_FIELD_CHUNK = 1024
"""Fewer field samples per checkpointed chunk than this cost calls, not memory."""
SMALL_PROPOSAL_GRID = 32
"""Base proposal grids coarser than this (cells a side) are warned: they blur the base's surfaces."""
LARGE_HULL_PROPOSAL_GRID = 128
"""Hull proposal grids finer than this (cells a side) are warned: 128^3 log scales outweigh the local field itself."""
MAX_SEEDS = 10_000_000
"""New Gaussians a splat edit may start with: more than most whole scenes hold (each is 708 bytes with Adam's)."""


USUAL_RANGES: Dict[str, UsualRange] = {
    # The objective sums means of order 1 (per pixel, per sample) with the guidance's, weighted 1 (method/edit.py).
    "loss_weight": UsualRange(
        1e-6, 100.0, "a term weighing under a millionth of the guidance changes nothing; 0 turns it off",
        "each term is a mean of order 1 summed with the guidance's, weighted 1, so this one drowns every other"),
    # Adam moves a weight by about its rate each step; an edit's weights (features, MLPs, Gaussians) are of order 1.
    "learning_rate": UsualRange(
        1e-7, 1.0, "Adam moves a weight by about its rate a step, so even 10,000 steps move it by under 1e-3",
        "Adam moves a weight by about its rate a step, so each step jumps past the whole range of the weights"),
    # A length in the scene box's units, which spans about 2.
    "preservation_delta": UsualRange(
        1e-4, 1.0, "so short a step turns no base density into occupancy: L_pres holds nothing as occupied",
        "a step over half the scene's width makes any faint density fully occupied"),
    # Times the seeds' mean spacing.
    "seed_size": UsualRange(
        0.1, 10.0, "seeds this far apart for their size start as separate dots the guidance sees through",
        "each seed spans many of its neighbours: the hull starts as one blur far larger than itself"),
}
"""The usual range of each kind of SKED knob whose extremes are legal: the one table of them."""
OPTION_RANGES: Dict[str, UsualRange] = {
    **{name: USUAL_RANGES["loss_weight"] for name in LOSS_WEIGHTS},
    "preservation_delta": USUAL_RANGES["preservation_delta"],
    "seed_size": USUAL_RANGES["seed_size"],
}
"""Each SkedOptions field warned outside its usual range (a guidance declares its own: GuidanceConfig.usual_ranges)."""


def _is_whole(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def option_problems(options) -> List[str]:
    """What is out of range in a SkedOptions (the model config), each naming its flag."""
    problems = []
    for name in LOSS_WEIGHTS:
        value = getattr(options, name)
        if not (is_number(value) and value >= 0):
            problems.append(f"{flag(name)} {value!r}: a loss weight must be a finite number >= 0 (a negative weight "
                            f"rewards what the loss penalises); 0 turns the loss off.")
    positive = {
        "beta": "image widths over which preservation fades (paper 0.005-1, default 0.025)",
        "preservation_delta": "the step length turning density into occupancy (default 0.07)",
        "samples_per_ray_scale": "samples per ray relative to the base's (1 = the base's)",
    }
    for name, meaning in positive.items():
        value = getattr(options, name)
        if not (is_number(value) and value > 0):
            problems.append(f"{flag(name)} {value!r}: must be a finite number > 0 ({meaning}).")
    if not (is_number(options.occupancy_threshold) and options.occupancy_threshold >= 0):
        problems.append(f"{flag('occupancy_threshold')} {options.occupancy_threshold!r}: a density, must be a "
                        "finite number >= 0 (default 5).")
    if not (is_number(options.photo_threshold) and 0 <= options.photo_threshold <= 1):
        problems.append(f"{flag('photo_threshold')} {options.photo_threshold!r}: a preservation weight, must be in "
                        "[0, 1] (default 0.99).")
    for name in ("guidance_resolution", "silhouette_resolution"):
        value = getattr(options, name)
        if not (_is_whole(value) and value > 0):
            problems.append(f"{flag(name)} {value!r}: must be a whole number of pixels > 0 (the paper's 128).")
    if not (_is_whole(options.field_chunk) and options.field_chunk >= -1):
        problems.append(f"{flag('field_chunk')} {options.field_chunk!r}: must be a whole number of samples >= 0 "
                        "(0: no gradient checkpointing), or -1 to let the memory plan choose.")
    grid = getattr(options, "base_proposal_grid", 0)  # nerfacto bases
    if not (_is_whole(grid) and grid >= 0):
        problems.append(f"{flag('base_proposal_grid')} {grid!r}: must be a whole number of cells a side >= 0 "
                        "(0: the base's proposal networks themselves).")
    hull = getattr(options, "hull_proposal_grid", 0)  # nerfacto bases
    if not (_is_whole(hull) and hull >= 0):
        problems.append(f"{flag('hull_proposal_grid')} {hull!r}: must be a whole number of cells a side >= 0 "
                        "(0: the hull sampled evenly; default 32).")
    if not (_is_whole(options.edit_box_warmup) and options.edit_box_warmup >= 0):
        problems.append(f"{flag('edit_box_warmup')} {options.edit_box_warmup!r}: must be a whole number of "
                        "iterations >= 0.")
    if not (is_number(options.keep_threshold) and 0 < options.keep_threshold <= 1):
        problems.append(f"{flag('keep_threshold')} {options.keep_threshold!r}: a preservation weight, must be in (0, 1] "
                        "(default 0.99; 1 holds nothing exactly, the paper's soft L_pres alone).")
    # Gaussian-splat bases' settings.
    if not (_is_whole(options.num_seeds) and 0 <= options.num_seeds <= MAX_SEEDS):
        problems.append(f"{flag('num_seeds')} {options.num_seeds!r}: must be a whole number of Gaussians from 0 to "
                        f"{MAX_SEEDS:,} (default 3,000).")
    if not (is_number(options.seed_opacity) and 0 < options.seed_opacity < 1):
        problems.append(f"{flag('seed_opacity')} {options.seed_opacity!r}: an opacity, must be in (0, 1) "
                        "(default 0.005; under 1/255 a seed gets no gradient).")
    if not (is_number(options.seed_size) and options.seed_size > 0):
        problems.append(f"{flag('seed_size')} {options.seed_size!r}: must be a finite number > 0 (times the seeds' "
                        "spacing).")
    if not (_is_whole(options.splat_supersampling) and options.splat_supersampling >= 1):
        problems.append(f"{flag('splat_supersampling')} {options.splat_supersampling!r}: renders per pixel side, "
                        "must be a whole number >= 1 (1: one sample a pixel).")
    return problems


def datamanager_problems(datamanager) -> List[str]:
    """What is out of range in the SKED datamanager's random-view and photo-batch settings."""
    problems = []

    def check_range(name: str, low: float, high: float, meaning: str) -> None:
        values = tuple(getattr(datamanager, name))
        if not (len(values) == 2 and all(is_number(v) for v in values) and low <= values[0] <= values[1] <= high):
            problems.append(f"{flag(name, DATAMANAGER_FLAGS)} {' '.join(map(str, values))}: must be two numbers, "
                            f"smallest first, within {meaning}.")

    check_range("elevation_range", -90.0, 90.0, "[-90, 90] degrees")
    check_range("azimuth_range", -360.0, 360.0, "[-360, 360] degrees")
    check_range("fov_range", 1e-3, 179.0, "(0, 179] degrees")
    check_range("radius_scale_range", 1e-3, math.inf, "(0, inf) (times the sketch cameras' distance)")
    fill = getattr(datamanager, "edit_fill", 0.0)
    if not (is_number(fill) and 0.0 <= fill <= 1.0):
        problems.append(f"{flag('edit_fill', DATAMANAGER_FLAGS)} {fill!r}: must be a share of the view in [0, 1] "
                        "(0 keeps --pipeline.datamanager.fov-range as given).")
    rays = datamanager.train_num_rays_per_batch
    if not (_is_whole(rays) and rays > 0):
        problems.append(f"{flag('train_num_rays_per_batch', DATAMANAGER_FLAGS)} {rays!r}: must be a whole number "
                        "of rays > 0 (the photo anchor's batch; --pipeline.model.lambda-photo 0 turns it off).")
    return problems


def warn_unusual_options(options) -> List[str]:
    """Legal settings that are almost surely a mistake, warned. (Whether an edit fits its device is the memory
    plan's to say: engine/memory_plan.py, once the base is known.)"""
    messages, resolution = [], options.guidance_resolution
    if resolution > LARGE_GUIDANCE_RESOLUTION:
        messages.append(f"{flag('guidance_resolution')} {resolution}: larger than Stable Diffusion's "
                        f"{LARGE_GUIDANCE_RESOLUTION}-pixel input and {(resolution / 128) ** 2:.0f}x the paper's 128 "
                        "in rays per step; nothing is gained past 512.")
    elif resolution < SMALL_GUIDANCE_RESOLUTION:
        messages.append(f"{flag('guidance_resolution')} {resolution}: a {resolution}x{resolution} view shows the "
                        "guidance almost no shape (the paper uses 128).")
    if not 0.25 <= options.samples_per_ray_scale <= 8:
        messages.append(f"{flag('samples_per_ray_scale')} {options.samples_per_ray_scale:g}: "
                        + ("under a quarter of the samples the base was trained with: thin parts and the new content "
                           "fall between samples." if options.samples_per_ray_scale < 0.25 else
                           "over 8x the base's samples per ray: each step costs as much more, for little gain."))
    if 0 < getattr(options, "base_proposal_grid", 0) < SMALL_PROPOSAL_GRID:
        messages.append(f"{flag('base_proposal_grid')} {options.base_proposal_grid}: a grid this coarse blurs the "
                        "base's proposal densities, so kept space is sampled off its surfaces while training; "
                        "the default 128 follows the networks' own detail, 0 evaluates them.")
    if getattr(options, "hull_proposal_grid", 0) > LARGE_HULL_PROPOSAL_GRID:
        messages.append(f"{flag('hull_proposal_grid')} {options.hull_proposal_grid}: "
                        f"{options.hull_proposal_grid ** 3:,} log scales, more than the local field itself holds, to "
                        "place samples the proposal sampler needs only a cell of the box to find (default 32).")
    if 0 < options.field_chunk < SMALL_FIELD_CHUNK:
        messages.append(f"{flag('field_chunk')} {options.field_chunk}: chunks this small make a step many times slower "
                        "(one call per chunk) for no memory that matters; 0 turns checkpointing off, 65536 keeps a "
                        "chunk's activations to a few hundred MB, and the default -1 lets the memory plan choose.")
    if options.lambda_photo > 0 and options.photo_threshold >= 1:
        messages.append(f"{flag('photo_threshold')} 1: no photo ray has every weight above 1, so the photo anchor "
                        "never acts; use --pipeline.model.lambda-photo 0 to turn it off, or 0.99.")
    elif options.lambda_photo > 0 and options.photo_threshold < 0.5:
        messages.append(f"{flag('photo_threshold')} {options.photo_threshold:g}: photo rays through the editable "
                        "region would hold it to the base's photos, undoing the edit (default 0.99).")
    if options.keep_threshold < 0.5:
        messages.append(f"{flag('keep_threshold')} {options.keep_threshold:g}: everything with a preservation weight "
                        "above it is held exactly as the base, so the edit can act only at the sketches' core and the "
                        "new part is cut off at its edges (default 0.99; 1 holds nothing exactly).")
    if options.num_seeds > 100_000:
        messages.append(f"{flag('num_seeds')} {options.num_seeds} (splat bases): more new Gaussians than most whole "
                        "scenes' edited parts need; each costs every render (default 3,000, densification adds more).")
    if options.splat_supersampling > 4:
        messages.append(f"{flag('splat_supersampling')} {options.splat_supersampling} (splat bases): each training "
                        f"render costs {options.splat_supersampling ** 2}x the pixels for little more than 2-4 give.")
    messages = [message for message in messages if message] + unusual_settings(options, OPTION_RANGES)
    for message in messages:
        warn_option(message)
    return messages


def optimizer_problems(optimizers) -> List[str]:
    """Learning rates out of range: torch's Adam would refuse a negative one only once the run folder is written."""
    return [f"{name} {value!r}: a learning rate must be a finite number >= 0 (0 freezes the group)."
            for name, value in _learning_rates(optimizers) if not (is_number(value) and value >= 0)]


def _learning_rates(optimizers):
    """(flag, value) of each optimiser group's learning rate and its schedule's final rate, as nerfstudio's flags."""
    for group, settings in (optimizers or {}).items():
        prefix = f"--optimizers.{group.replace('_', '-')}."
        optimizer, scheduler = settings.get("optimizer"), settings.get("scheduler")
        if optimizer is not None and hasattr(optimizer, "lr"):
            yield prefix + "optimizer.lr", optimizer.lr
        if getattr(scheduler, "lr_final", None) is not None:
            yield prefix + "scheduler.lr-final", scheduler.lr_final


def check_optimizers(optimizers) -> List[str]:
    """Refuse a negative or non-finite learning rate; warn on one far outside USUAL_RANGES (the edit's
    optimisers: the presets' NeRF groups, or a splat edit's)."""
    refuse(optimizer_problems(optimizers))
    messages = [unusual(name, value, USUAL_RANGES["learning_rate"]) for name, value in _learning_rates(optimizers)]
    messages = [message for message in messages if message]
    for message in messages:
        warn_option(message)
    return messages


def check_options(options, datamanager=None) -> None:
    """Refuse out-of-range SKED settings (model config, and the SKED datamanager's if given); warn on odd ones."""
    sked_datamanager = hasattr(datamanager, "fov_range")  # nerfstudio's own datamanagers have no random views
    refuse(option_problems(options) + (datamanager_problems(datamanager) if sked_datamanager else []))
    warn_unusual_options(options)
    if sked_datamanager and getattr(datamanager, "edit_fill", 0.0) > 0.9:
        warn_option(f"{flag('edit_fill', DATAMANAGER_FLAGS)} {datamanager.edit_fill:g}: the edit box fills nearly every random "
             "view, so the guidance sees little of the scene around the part (0.7 frames it with context).")


def check_sketch_pixels(sketch_set, silhouette_resolution: int) -> List[int]:
    """Each sketch's pixel count in its L_sil render (longer side `silhouette_resolution`): a sketch under one
    pixel there makes L_sil exactly 0 for the whole edit (refused), one under a few pixels barely pulls (warned)."""
    from sked_ns.sketches.sketch_set import sketch_view_at

    counts = [int(sketch_view_at(view, silhouette_resolution)[1].sum()) for view in sketch_set.views]
    empty = [view.name or f"view {i}" for i, (view, count) in enumerate(zip(sketch_set.views, counts)) if count == 0]
    if empty:
        refuse([f"{flag('silhouette_resolution')} {silhouette_resolution}: the sketch of {', '.join(empty)} covers "
                "no pixel of its silhouette render, so L_sil would be 0 for the whole edit. Raise it (the paper uses "
                "128) or sketch a larger region."])
    small = [f"{view.name or f'view {i}'} ({count} px)" for i, (view, count) in enumerate(zip(sketch_set.views, counts))
             if count < MIN_SKETCH_PIXELS]
    if small:
        warn_option(f"{flag('silhouette_resolution')} {silhouette_resolution}: sketches cover fewer than {MIN_SKETCH_PIXELS} "
             f"pixels of their silhouette render: {', '.join(small)}; L_sil can hardly shape the edit (paper: 128).")
    return counts
