"""The method's fixed numbers and default model ids, importable without torch.

The service's settings read the model ids from here, so the API process never imports
torch or diffusers to learn three strings; the library modules import them from here too,
so each value is written once.
"""

SDS_MODEL_ID = "stabilityai/stable-diffusion-2-base"
"""The model the authors' code uses for SDS (the paper cites SD 2.1)."""

ATTENTION_MODEL_ID = "CompVis/stable-diffusion-v1-4"
"""The model the authors use for cross-attention maps."""

CLIP_MODEL_ID = "openai/clip-vit-base-patch32"
"""CLIP ViT-B/32 of the paper's evaluation (SPEC §4)."""

INCEPTION_FILE = "inception-2015-12-05.pt"
"""The TorchScript Inception network of FID (StyleGAN2-ADA's metrics)."""

NERF_SYNTHETIC_RADIUS = 4.0311
"""Distance of the NeRF-synthetic cameras from the origin."""

NERF_SYNTHETIC_FOV_X = 0.6911112070083618
"""camera_angle_x of the NeRF-synthetic scenes (radians)."""
