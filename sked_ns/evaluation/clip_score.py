"""CLIP similarity of an edit to its prompt over views around the edited object (paper Sec. 4.2).

Weights come only from local files (a hub id already in the cache, or a folder saved with
`save_pretrained`): evaluation never downloads. Missing weights are reported, not faked.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from sked_ns.evaluation.eval_args import DEFAULT_CLIP
from sked_ns.guidance.hub import download_command
from sked_ns.sketches.random_views import look_at, orbit_position

# OpenAI CLIP's input normalisation (the constants of every CLIP image processor config).
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


class ClipScorer:
    """Cosine similarity between CLIP image and text embeddings."""

    def __init__(self, model, tokenizer) -> None:
        self.model = model.eval().requires_grad_(False)
        self.tokenizer = tokenizer
        self.image_size = int(model.config.vision_config.image_size)

    @classmethod
    def load(cls, source: str = DEFAULT_CLIP) -> Tuple[Optional["ClipScorer"], Optional[str]]:
        """(scorer, None), or (None, why it is unavailable)."""
        from transformers import AutoTokenizer, CLIPModel

        try:
            model = CLIPModel.from_pretrained(source, local_files_only=True)
            tokenizer = AutoTokenizer.from_pretrained(source, local_files_only=True)
        except Exception as error:  # missing files surface as several exception types
            where = source if Path(source).exists() else f"'{source}' in the Hugging Face cache"
            return None, (f"unavailable: no CLIP weights at {where} ({type(error).__name__}). Download them once "
                          f"(`{download_command(DEFAULT_CLIP)}`) or pass --clip-model <folder>.")
        return cls(model, tokenizer), None

    @torch.no_grad()
    def similarity(self, images: Sequence[Tensor], prompt: str) -> List[float]:
        """One cosine similarity per image (h, w, 3) in [0, 1]."""
        batch = torch.stack([image.permute(2, 0, 1).float() for image in images])
        batch = torch.nn.functional.interpolate(batch, size=(self.image_size, self.image_size), mode="bicubic",
                                                align_corners=False).clamp(0, 1)
        mean = torch.tensor(CLIP_MEAN).view(1, 3, 1, 1)
        std = torch.tensor(CLIP_STD).view(1, 3, 1, 1)
        image_embeddings = self.model.get_image_features(pixel_values=(batch - mean) / std)
        tokens = self.tokenizer([prompt], padding="max_length", truncation=True, return_tensors="pt")
        text_embedding = self.model.get_text_features(input_ids=tokens["input_ids"],
                                                      attention_mask=tokens["attention_mask"])
        image_embeddings = _features(image_embeddings)
        text_embedding = _features(text_embedding)
        cosine = torch.nn.functional.cosine_similarity(image_embeddings, text_embedding, dim=-1)
        return cosine.tolist()


def _features(output) -> Tensor:
    # transformers 5 may wrap the projected features in an output object.
    return output if isinstance(output, Tensor) else output.pooler_output


def orbit_cameras(centre: np.ndarray, radius: float, count: int = 40, elevations=(15.0, 35.0)) -> List[np.ndarray]:
    """`count` camera-to-world poses on rings around `centre` (model frame), alternating elevations."""
    poses = []
    for index in range(count):
        azimuth = 360.0 * index / count
        position = np.asarray(centre) + orbit_position(azimuth, elevations[index % len(elevations)], radius)
        poses.append(look_at(position, np.asarray(centre)))
    return poses
