"""SKED on a nerfacto field: a frozen base, an editable copy, and the paper's losses.

Per iteration (paper Eq. 6): L = L_guidance + lambda_pres L_pres + lambda_sil L_sil
+ lambda_sp L_sp. L_pres and L_sp come from one random view aimed at the edit box, L_sil
from the fixed sketch views at reduced resolution. The base field is a frozen copy kept
out of the module tree: it is never optimised, never saved, and follows `.to()`.
"""

from __future__ import annotations

import contextlib
import copy
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Type

import torch
import torchmetrics.image.lpip as lpip_module
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.field_components.encodings import HashEncoding
from nerfstudio.field_components.field_heads import FieldHeadNames
from nerfstudio.model_components.losses import interlevel_loss
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig
from torch import Tensor
from torch.nn import Parameter

from sked_ns.base_scene import read_model_state, uses_tcnn
from sked_ns.edit_box import EditBox, compute_edit_box
from sked_ns.guidance import Guidance, ReferenceGuidanceConfig, RenderedView, StableDiffusionGuidanceConfig
from sked_ns.losses import occupancy_log_probabilities, preservation_loss, silhouette_loss, sparsity_loss
from sked_ns.preservation import SketchDistanceField, check_beta
from sked_ns.sketches import SketchSet

# Architecture of the base that the edit must share to load its weights.
ARCHITECTURE_FIELDS = (
    "hidden_dim", "hidden_dim_color", "hidden_dim_transient", "num_levels", "base_res", "max_res",
    "log2_hashmap_size", "features_per_level", "num_proposal_iterations", "num_proposal_samples_per_ray",
    "num_nerf_samples_per_ray", "proposal_net_args_list", "use_same_proposal_network", "use_appearance_embedding",
    "appearance_embed_dim", "use_average_appearance_embedding", "disable_scene_contraction", "predict_normals",
    "implementation", "background_color", "near_plane", "far_plane", "proposal_initial_sampler",
    "average_init_density", "use_single_jitter",
)


@dataclass
class SkedModelConfig(NerfactoModelConfig):
    """SKED on a nerfacto-style field. Architecture fields are copied from the base."""

    _target: Type = field(default_factory=lambda: SkedModel)
    sketches: Optional[Path] = None
    """Sketch-set folder (sketches.json + PNG masks); `ns-train sked --sketches` sets it."""
    prompt: Optional[str] = None
    """What should be in the sketched region; none with Stable Diffusion guidance = carve it away."""
    base_checkpoint: Optional[Path] = None
    """The base's step-*.ckpt; filled in from --load-dir."""
    guidance: Literal["stable-diffusion", "reference"] = "stable-diffusion"
    """Which guidance pulls the sketched region (reference: renders of a known target scene)."""
    sds: StableDiffusionGuidanceConfig = field(default_factory=StableDiffusionGuidanceConfig)
    reference: ReferenceGuidanceConfig = field(default_factory=ReferenceGuidanceConfig)
    beta: float = 0.025
    """Falloff of the preservation weight, in image widths (paper Eq. 4)."""
    lambda_pres: float = 5.0
    """Weight of L_pres (a mean over samples; the authors' 5e-6 multiplied a sum)."""
    lambda_colour: float = 5.0
    """Weight of the colour term inside L_pres."""
    lambda_sil: float = 1.0
    """Weight of L_sil."""
    lambda_sp: float = 5e-4
    """Weight of the sparsity (accumulation entropy) loss."""
    lambda_carve: float = 5.0
    """Weight of the carving loss (empty the sketched region) when there is no prompt."""
    occupancy_threshold: float = 5.0
    """Base density above which a sample counts as occupied."""
    preservation_delta: float = 0.07
    """Fixed step length turning density into occupancy in L_pres."""
    guidance_resolution: int = 128
    """Side of the random view rendered for guidance (authors: 128, upsampled for SD)."""
    silhouette_resolution: int = 128
    """Longer side of the sketch views rendered for L_sil (authors: 128)."""
    edit_box_warmup: int = 1000
    """Iterations during which the empty edit box is kept sampled."""
    edit_box_density: float = 2.0
    """Proposal density added inside the edit box during warm-up, per unit of box diagonal."""
    compile_lookup: bool = True
    """torch.compile the sketch-distance lookup on CUDA."""
    camera_optimizer: CameraOptimizerConfig = field(default_factory=lambda: CameraOptimizerConfig(mode="off"))
    """Edits keep the base's cameras."""


@contextlib.contextmanager
def _without_lpips():
    """nerfacto builds LPIPS (an AlexNet download) in populate_modules; SKED needs none."""
    original = lpip_module.LearnedPerceptualImagePatchSimilarity
    lpip_module.LearnedPerceptualImagePatchSimilarity = lambda *args, **kwargs: None
    try:
        yield
    finally:
        lpip_module.LearnedPerceptualImagePatchSimilarity = original


class SkedModel(NerfactoModel):
    """Editable nerfacto field + frozen base + sketch geometry + guidance."""

    config: SkedModelConfig

    def populate_modules(self) -> None:
        check_beta(self.config.beta)
        with _without_lpips():
            super().populate_modules()
        self.lpips = None
        sketch_set: Optional[SketchSet] = self.kwargs.get("sketch_set")
        if sketch_set is None:
            raise ValueError("SKED needs a sketch set: pass --sketches <folder with sketches.json>.")
        self.sketch_set = sketch_set
        scene = self.scene_box.aabb.numpy()
        self.edit_box: EditBox = compute_edit_box(sketch_set.views, scene_box=scene)
        self.sketch_field = SketchDistanceField(
            sketch_set.views, compile=self.config.compile_lookup and torch.cuda.is_available()
        )
        # The appearance of random views is the average embedding: keep it as trained.
        if self.field.embedding_appearance is not None:
            self.field.embedding_appearance.requires_grad_(False)
        warn_degenerate_settings(self.config, sketch_set)
        self._load_base()
        self._boost_proposals_in_edit_box()
        self._captured: Dict[str, object] = {}
        self._capture_field_samples()
        self.guidance: Optional[Guidance] = None  # plain attribute: never in a checkpoint

    # ---- base field -------------------------------------------------------------------------
    def _load_base(self) -> None:
        """Editable field <- base weights; a frozen copy of them supplies sigma_o, c_o."""
        checkpoint = self.config.base_checkpoint
        if checkpoint is None:
            raise ValueError("No base checkpoint: run `ns-train sked --load-dir <base run or its nerfstudio_models>`.")
        state = read_model_state(Path(checkpoint))
        ours = self.state_dict()
        if uses_tcnn(state) != uses_tcnn(ours):
            trained, here = ("tiny-cuda-nn", "torch") if uses_tcnn(state) else ("torch", "tiny-cuda-nn")
            raise ValueError(
                f"{checkpoint}: the base was trained with the {trained} implementation, but this edit builds "
                f"{here} modules, whose weights are laid out differently. "
                + ("Install tinycudann here, or edit on the machine that trained the base."
                   if uses_tcnn(state) else "Pass --pipeline.model.implementation torch.")
            )
        embedding = state.get("field.embedding_appearance.embedding.weight")
        if embedding is not None and embedding.shape[0] != self.num_train_data:
            raise ValueError(
                f"{checkpoint}: the base was trained on {embedding.shape[0]} images but --data has "
                f"{self.num_train_data}. Pass the base's own data and dataparser settings."
            )
        wanted = [key for key in ours if key.startswith(("field.", "proposal_networks."))]
        missing = [key for key in wanted if key not in state]
        mismatched = [key for key in wanted if key in state and state[key].shape != ours[key].shape]
        if missing or mismatched:
            raise ValueError(
                f"{checkpoint}: the base's weights do not fit this model (missing {missing[:3]}, "
                f"shape mismatch {mismatched[:3]}). Is --data the base's data, and the base a supported method?"
            )
        self.load_state_dict({key: state[key] for key in wanted}, strict=False)
        base_field = copy.deepcopy(self.field).eval().requires_grad_(False)
        base_proposals = copy.deepcopy(self.proposal_networks).eval().requires_grad_(False)
        # A list hides the frozen base from the module tree, and so from optimisers and checkpoints.
        self._base = [base_field, base_proposals]

    @property
    def base_field(self):
        return self._base[0]

    def _apply(self, fn, *args, **kwargs):
        # `.to()`, `.cuda()`, `.half()` reach the hidden base too.
        super()._apply(fn, *args, **kwargs)
        for module in getattr(self, "_base", []):
            module._apply(fn, *args, **kwargs)
        return self

    @torch.no_grad()
    def render_base(self, ray_bundle: RayBundle) -> Dict[str, Tensor]:
        """The frozen base seen along `ray_bundle` (already collided), e.g. for comparisons."""
        edit_field, edit_density_fns = self.field, self.density_fns
        captured = self._captured
        base_field, base_proposals = self._base
        try:
            object.__setattr__(self, "field", base_field)  # swap without registering a submodule
            self.density_fns = [network.density_fn for network in base_proposals]
            return super().get_outputs(ray_bundle)
        finally:
            object.__setattr__(self, "field", edit_field)
            self.density_fns = edit_density_fns
            self._captured = captured

    # ---- sampling the edit region -----------------------------------------------------------
    def _boost_proposals_in_edit_box(self) -> None:
        """Add density inside the edit box to the proposal networks during warm-up.

        A nerfacto base has no mass where the new content goes, so its proposal networks
        would never place samples there; the boost does until they learn the new mass.
        """
        low = torch.tensor(self.edit_box.min, dtype=torch.float32)
        high = torch.tensor(self.edit_box.max, dtype=torch.float32)
        diagonal = float(torch.linalg.norm(high - low).clamp_min(1e-6))

        def boosted(density_fn):
            def density(positions: Tensor, times: Optional[Tensor] = None) -> Tensor:
                value = density_fn(positions, times)
                strength = self.edit_box_boost()
                if strength > 0:
                    inside = ((positions >= low.to(positions.device)) & (positions <= high.to(positions.device))).all(-1)
                    value = value + strength / diagonal * inside[..., None].to(value.dtype)
                return value

            return density

        self.density_fns = [boosted(fn) for fn in self.density_fns]

    def edit_box_boost(self) -> float:
        """Linear fade from `edit_box_density` to 0 over the warm-up."""
        warmup = max(self.config.edit_box_warmup, 1)
        return self.config.edit_box_density * max(0.0, 1.0 - self.step / warmup)

    def _capture_field_samples(self) -> None:
        """Keep the last samples and field outputs: L_pres needs them, nerfacto returns neither.

        nerfacto calls `self.field.forward(...)` directly, which skips module hooks, so the
        bound method is wrapped instead.
        """
        forward = self.field.forward

        def capturing_forward(ray_samples, *args, **kwargs):
            outputs = forward(ray_samples, *args, **kwargs)
            self._captured = {"ray_samples": ray_samples, "field_outputs": outputs}
            return outputs

        self.field.forward = capturing_forward

    # ---- parameters -----------------------------------------------------------------------
    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        """Hash grids get their own group: method.md trains them at 10x the MLPs' rate."""
        grids = {id(p) for module in self.modules() if isinstance(module, HashEncoding) for p in module.parameters()}
        trainable = lambda module: [p for p in module.parameters() if p.requires_grad]  # noqa: E731
        groups = {
            "proposal_networks": [p for p in trainable(self.proposal_networks) if id(p) not in grids],
            "fields": [p for p in trainable(self.field) if id(p) not in grids],
            "hash_grids": [p for p in trainable(self) if id(p) in grids],
        }
        self.camera_optimizer.get_param_groups(param_groups=groups)
        return groups

    # ---- rendering ------------------------------------------------------------------------
    def get_outputs(self, ray_bundle: RayBundle):
        outputs = super().get_outputs(ray_bundle)
        samples = self._captured.get("ray_samples")
        if samples is not None and not self.training:
            weights = outputs.get("weights_list", [None])[-1]
            if weights is None:
                weights = samples.get_weights(self._captured["field_outputs"][FieldHeadNames.DENSITY])
            preservation = self.preservation_weight(samples.frustums.get_positions())
            # Background counts as preserved: the viewer shows where the edit may act.
            accumulation = weights.sum(dim=-2)
            outputs["preservation_weight"] = (weights * preservation).sum(dim=-2) + (1 - accumulation).clamp(0, 1)
        return outputs

    def preservation_weight(self, positions: Tensor) -> Tensor:
        """w for sample positions (..., 3) -> (..., 1)."""
        return self.sketch_field.preservation_weight(positions.detach(), self.config.beta)[..., None]

    @contextlib.contextmanager
    def _average_appearance(self):
        """Random and sketch views have no training image: use the average appearance."""
        was_training = self.field.training
        self.field.train(False)
        try:
            yield
        finally:
            self.field.train(was_training)

    # ---- SKED losses ---------------------------------------------------------------------
    def get_sked_loss_dict(
        self,
        random_view: RayBundle,
        random_camera: Dict,
        sketch_rays: RayBundle,
        sketch_masks: Tensor,
        step: int,
    ) -> tuple[Dict[str, Tensor], Dict[str, Tensor], Dict[str, Tensor]]:
        """All losses of one iteration; returns (outputs, losses, metrics)."""
        config = self.config
        losses: Dict[str, Tensor] = {}
        metrics: Dict[str, Tensor] = {}
        height, width = random_view.shape[:2]
        with self._average_appearance():
            # Model.forward would apply the collider; these renders bypass it, so apply it here.
            view = super().get_outputs(self.collider(random_view.flatten()))
            captured = self._captured
            sketch = super().get_outputs(self.collider(sketch_rays)) if sketch_rays is not None else None

        # L_pres on the random view's samples.
        samples = captured["ray_samples"]
        field_outputs = captured["field_outputs"]
        positions = samples.frustums.get_positions()
        weight = self.preservation_weight(positions)
        with torch.no_grad():
            base_outputs = self.base_field(samples)
        density_edit = field_outputs[FieldHeadNames.DENSITY]
        losses["preservation_loss"] = config.lambda_pres * preservation_loss(
            density_edit, field_outputs[FieldHeadNames.RGB], base_outputs[FieldHeadNames.DENSITY],
            base_outputs[FieldHeadNames.RGB], weight, config.occupancy_threshold, config.preservation_delta,
            config.lambda_colour,
        )
        losses["sparsity_loss"] = config.lambda_sp * sparsity_loss(view["accumulation"])
        losses["interlevel_loss"] = config.interlevel_loss_mult * interlevel_loss(
            view["weights_list"], view["ray_samples_list"]
        )
        carving = config.guidance == "stable-diffusion" and not (config.prompt and config.prompt.strip())
        if carving:
            # No prompt: empty the sketched region (occupancy -> 0 where w is small).
            _, log_empty = occupancy_log_probabilities(density_edit, config.preservation_delta)
            losses["carve_loss"] = config.lambda_carve * ((1 - weight) * -log_empty).mean()
        else:
            assert self.guidance is not None, "guidance is prepared by the pipeline before training"
            as_image = lambda rgb: rgb.reshape(1, height, width, 3).permute(0, 3, 1, 2)  # noqa: E731
            base_image = None
            if self.guidance.needs_base_render:
                with self._average_appearance():
                    base_image = as_image(self.render_base(self.collider(random_view.flatten()))["rgb"])
            rendered = RenderedView(image=as_image(view["rgb"]), camera_to_world=random_camera["camera_to_world"],
                                    focal=random_camera["focal"], direction=random_camera["direction"],
                                    base_image=base_image)
            losses.update(self.guidance(rendered, step))
            if sketch is not None:
                accumulation = sketch["accumulation"].reshape(sketch_masks.shape)
                losses["silhouette_loss"] = config.lambda_sil * silhouette_loss(accumulation, sketch_masks)
                metrics["sketch_coverage"] = (accumulation.detach() > 0.5).float().mul(sketch_masks).sum() / sketch_masks.sum().clamp_min(1)
        if sketch is not None:
            losses["interlevel_loss"] = losses["interlevel_loss"] + config.interlevel_loss_mult * interlevel_loss(
                sketch["weights_list"], sketch["ray_samples_list"]
            )
        metrics["mean_preservation_weight"] = weight.mean().detach()
        metrics["edit_box_boost"] = torch.tensor(self.edit_box_boost())
        bad = [name for name, value in losses.items() if not torch.isfinite(value).all()]
        if bad:
            metrics["nonfinite_losses"] = torch.tensor(float(len(bad)))
        return view, losses, metrics

    # ---- evaluation without LPIPS ----------------------------------------------------------
    def get_image_metrics_and_images(self, outputs, batch):
        gt = self.renderer_rgb.blend_background(batch["image"].to(self.device))
        predicted = outputs["rgb"]
        gt_chw, predicted_chw = gt.permute(2, 0, 1)[None], predicted.permute(2, 0, 1)[None]
        metrics = {"psnr": float(self.psnr(gt_chw, predicted_chw).item()), "ssim": float(self.ssim(gt_chw, predicted_chw))}
        images = {"img": torch.cat([gt, predicted], dim=1), "accumulation": outputs["accumulation"]}
        if "preservation_weight" in outputs:
            images["preservation_weight"] = outputs["preservation_weight"]
        return metrics, images


def warn_degenerate_settings(config: SkedModelConfig, sketch_set: SketchSet) -> List[str]:
    """Settings that run without error but cannot give a sensible edit get a clear warning."""
    messages = []
    if config.beta < 1e-3:
        messages.append(f"beta = {config.beta:g} image widths is under a pixel at usual sizes: only the exact "
                        "sketch rays may change and the edit cannot blend in (paper range 0.005-1).")
    if config.beta > 1.0:
        messages.append(f"beta = {config.beta:g} image widths: preservation weights are near 0 around the whole "
                        "object, so the edit may change everything (paper range 0.005-1).")
    if config.lambda_pres == 0:
        messages.append("lambda_pres = 0: nothing preserves the base (the paper's no-preserve ablation).")
    if config.lambda_sil == 0 and config.prompt:
        messages.append("lambda_sil = 0: nothing makes the edit fill the sketches (the paper's no-silhouette ablation).")
    for view in sketch_set.views:
        covered = float(view.mask.mean())
        if covered > 0.9:
            messages.append(f"{view.name or 'a sketch view'}: the mask covers {covered:.0%} of the image, so almost "
                            "nothing in that view is preserved.")
    for message in messages:
        warnings.warn(message, SkedSettingsWarning, stacklevel=2)
    return messages


class SkedSettingsWarning(UserWarning):
    """A setting that runs but defeats the method."""


def copy_base_architecture(target: SkedModelConfig, base_model_config) -> None:
    """Make the edit's field the base's shape (hash grids, MLPs, proposal networks)."""
    for name in ARCHITECTURE_FIELDS:
        if hasattr(base_model_config, name):
            setattr(target, name, copy.deepcopy(getattr(base_model_config, name)))
