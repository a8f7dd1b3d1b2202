"""Tiny, randomly initialised evaluation models: a CLIP and an Inception-style FID feature net.

SMOKE-TEST MODELS. Their weights are random: they prove the evaluation's
plumbing (loading through :meth:`voxe_core.evaluate.ClipScorer.from_pretrained`
and :meth:`voxe_core.evaluate.InceptionFeatures.load`, shapes, batching, the
metric arithmetic) and say nothing, ever, about an edit's quality. Scores made
with them are not CLIP or FID scores.

* :func:`build_tiny_clip` writes a folder in the hub layout of
  ``openai/clip-vit-base-patch32`` (``config.json`` + weights of a
  ``CLIPModel``, a CLIP BPE tokenizer, ``preprocessor_config.json``): ViT
  with 32 px images, 8 px patches, hidden size 32, 2 layers, projection 32; the
  tokenizer is the one of :mod:`voxe_core.tiny_sd` (whole-word tokens for the
  project's prompts, byte fallback for anything else).
* Both are marked (:data:`SMOKE_TEST_MARK`), so an evaluation scoring with them says so in its table.
* :func:`build_tiny_inception` writes a TorchScript file with the calling
  convention of ``inception-2015-12-05.pt``:
  ``model(uint8 images (N, 3, H, W), return_features=True)`` -> (N, 64) pool
  features (logits otherwise), resizing to 64 px inside.

Deterministic for a seed.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
import torch.nn.functional as F

from voxe_core.constants import SMOKE_TEST_MARK
from voxe_core.tiny_sd import _BOS, _EOS, _MAX_LENGTH, TINY_VOCAB_WORDS, _write_tokenizer

TINY_CLIP_IMAGE_SIZE = 32
TINY_INCEPTION_FEATURES = 64


def build_tiny_clip(path, seed: int = 0) -> Path:
    """Write a tiny random-weight CLIPModel (SMOKE-TEST MODEL) with tokenizer and image processor to ``path``."""
    from transformers import CLIPConfig, CLIPModel

    root = Path(path)
    vocab = _write_tokenizer(root, TINY_VOCAB_WORDS)
    config = CLIPConfig(
        text_config={
            "vocab_size": len(vocab), "hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 2,
            "num_attention_heads": 4, "max_position_embeddings": _MAX_LENGTH, "hidden_act": "quick_gelu",
            "bos_token_id": vocab[_BOS], "eos_token_id": vocab[_EOS], "pad_token_id": vocab[_EOS],
        },
        vision_config={
            "image_size": TINY_CLIP_IMAGE_SIZE, "patch_size": 8, "hidden_size": 32, "intermediate_size": 64,
            "num_hidden_layers": 2, "num_attention_heads": 4, "hidden_act": "quick_gelu",
        },
        projection_dim=32, **{SMOKE_TEST_MARK: True},
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = CLIPModel(config)
    model.save_pretrained(str(root))
    # CLIP's own preprocessing constants, at the tiny image size (as openai/clip-vit-base-patch32 ships them).
    preprocessing = {
        "image_processor_type": "CLIPImageProcessor", "do_resize": True, "resample": 3, "do_center_crop": True,
        "size": {"shortest_edge": TINY_CLIP_IMAGE_SIZE},
        "crop_size": {"height": TINY_CLIP_IMAGE_SIZE, "width": TINY_CLIP_IMAGE_SIZE},
        "do_rescale": True, "rescale_factor": 1 / 255, "do_normalize": True,
        "image_mean": [0.48145466, 0.4578275, 0.40821073], "image_std": [0.26862954, 0.26130258, 0.27577711],
    }
    (root / "preprocessor_config.json").write_text(json.dumps(preprocessing, indent=2) + "\n", encoding="utf-8")
    _smoke_test_readme(root, f"`voxe_core.tiny_eval.build_tiny_clip(path, seed={seed})`")
    return root


class _TinyInception(torch.nn.Module):
    """Three strided convolutions and a global average pool; the pool is the 'feature' layer."""

    def __init__(self):
        super().__init__()
        setattr(self, SMOKE_TEST_MARK, True)  # kept in the TorchScript file
        self.conv1 = torch.nn.Conv2d(3, 16, 3, stride=2, padding=1)
        self.conv2 = torch.nn.Conv2d(16, 32, 3, stride=2, padding=1)
        self.conv3 = torch.nn.Conv2d(32, TINY_INCEPTION_FEATURES, 3, stride=2, padding=1)
        self.fc = torch.nn.Linear(TINY_INCEPTION_FEATURES, 10)

    def forward(self, img: torch.Tensor, return_features: bool = False) -> torch.Tensor:
        x = (img.to(torch.float32) - 128.0) / 128.0  # the real network's input scaling of uint8 pixels
        x = F.interpolate(x, size=(64, 64), mode="bilinear", align_corners=False)
        x = F.relu(self.conv1(x))
        x = F.relu(self.conv2(x))
        x = F.relu(self.conv3(x))
        features = x.mean(dim=(2, 3))
        if return_features:
            return features
        return self.fc(features)


def build_tiny_inception(path, seed: int = 0) -> Path:
    """Write a tiny random-weight TorchScript FID feature net (SMOKE-TEST MODEL) to the file ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        module = torch.jit.script(_TinyInception().eval())
    module.save(str(path))
    return path


def _smoke_test_readme(root: Path, builder: str) -> None:
    (root / "README.md").write_text(
        f"# SMOKE-TEST MODEL\n\nRandomly initialised tiny model written by {builder}.\n"
        "It proves the plumbing only; its scores say nothing about edit quality.\n",
        encoding="utf-8",
    )
