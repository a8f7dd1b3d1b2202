"""The method's fixed numbers and default model ids, importable without torch.

The service's settings and the API's job schema read them from here, so the API process never
imports torch or diffusers to learn a model id or a default; the library's stage configs
(``EditConfig``, ``RefineConfig``) take their defaults from here too, so each value is written once.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

SDS_MODEL_ID = "stabilityai/stable-diffusion-2-base"
"""The model the authors' code uses for SDS (the paper cites SD 2.1)."""

ATTENTION_MODEL_ID = "CompVis/stable-diffusion-v1-4"
"""The model the authors use for cross-attention maps."""

CLIP_MODEL_ID = "openai/clip-vit-base-patch32"
"""CLIP ViT-B/32 of the paper's evaluation (SPEC §4)."""

INCEPTION_FILE = "inception-2015-12-05.pt"
"""The TorchScript Inception network of FID (StyleGAN2-ADA's metrics)."""


def inception_path(path: str | os.PathLike) -> Path:
    """The Inception file ``path`` names: the path itself, or ``INCEPTION_FILE`` in it when it is a folder (the
    loader and the workers' model check read it alike)."""
    path = Path(path).expanduser()
    return path / INCEPTION_FILE if path.is_dir() else path

NERF_SYNTHETIC_RADIUS = 4.0311
"""Distance of the NeRF-synthetic cameras from the origin."""

NERF_SYNTHETIC_FOV_X = 0.6911112070083618
"""camera_angle_x of the NeRF-synthetic scenes (radians)."""

# ------------------------------------------------------------------ editing (SPEC §2)
EDIT_ITERATIONS = 8000
"""Edit iterations of the paper (objects; real scenes: ``voxe_core.presets.EDIT_SCHEDULES``)."""

EDIT_LR = 0.03
"""Adam's learning rate on G_e."""

RENDER_SIZE = 266
"""Pixels of the edit's and the refinement's renders: the paper's 800 px inputs downsampled 3×."""

MIN_RENDER_SIZE = 8
"""The fewest pixels a side of the edit's and the refinement's renders may have (the service's bound too). A 1 px
render's min-max normalised attention maps are 0 everywhere, and the 2–3 px ones of a test sphere missed it from
every pose: both ran every attention pass and fit before the cut found no seeds."""

MAX_RENDER_SIZE = 1024
"""The most pixels a side of the edit's, the refinement's and the evaluation ring's renders may have (the service's
bound, and the CLI's)."""

FLOAT32_MAX = 3.4028234663852886e38
"""The largest float32: a setting used in float32 past it is inf there (a finite float64 one had passed the
"finite" checks and overflowed as an inf would)."""

RENDER_CHUNK_RAYS = 32768
"""Rays per chunk of a whole-image render (and of the refinement's back-projection)."""

DEFAULT_GUIDANCE_SCALE = 100.0
"""Classifier-free guidance scale of SDS."""

DEFAULT_REGULARISER = "reg3d"
"""L_reg3D: 1 − Pearson correlation of G_i's and G_e's raw densities."""

DEFAULT_REGULARISER_WEIGHT = 200.0
"""Weight of the volumetric regulariser."""

# ------------------------------------------------------------------ refinement (SPEC §3)
DEFAULT_ATTENTION_TIMESTEP = 200
"""The fixed diffusion time step (of 1000) of the cross-attention maps."""

DIFFUSION_TIMESTEPS = 1000
"""Length of Stable Diffusion's training noise schedule: its time steps are 0 to 999."""

REFINE_ITERATIONS = 1500
"""Fitting iterations of the 3D attention grids."""

SERVICE_SMOOTHING_SIGMA = 0.5
"""Gaussian std, in attention cells, of the 2D maps' smoothing: the authors' code's 0.5 (the paper names none);
1.0 before issue 18 lost the clean-map IoU on bench/localisation.py (0.82 against 0.99)."""

SERVICE_REFINE_ITERATIONS = 0
"""The service's fitting steps instead: the back-projection start alone cuts as well as the 1,500-step fit
(bench/localisation.py), and further steps did not buy IoU there."""

REFINE_LR = 0.035
"""Adam's learning rate on the attention grids."""

REFINE_TV_WEIGHT = 0.01
"""Weight of the attention grids' total variation."""

REFINE_VIEWS = 32
"""Random upper-hemisphere poses whose 2D maps are lifted (ours; the authors use the training views)."""

MAX_REFINE_VIEWS = 1000
"""The most views a refinement lifts maps from (the service's bound, and the CLI's)."""

MAX_BATCH_SIZE = 16
"""The most poses an edit renders per iteration (``batch_size``; the service's bound, and the CLI's through
``EditConfig``): each is rendered with its autograd graph held until the step's backward."""

MAX_IMAGE_REGULARISER_RAYS = MAX_BATCH_SIZE * MAX_RENDER_SIZE**2
"""The most rays an edit's image regulariser (``image_l1`` / ``image_l2``) renders per iteration: as many as the
largest step's renders hold (``MAX_BATCH_SIZE`` of ``MAX_RENDER_SIZE``² pixels), each with its autograd graph."""

REFINE_RAYS_PER_STEP = 8192
"""Rays per attention-grid fitting step."""

MAX_RAYS_PER_STEP = 1 << 20
"""The most rays a reconstruction's or an attention-grid fit's step may take (the service's bound, and the CLI's
``--rays``): ``voxe reconstruct --rays 2000000000`` had been taken, and the fit's first step killed by the system's
out-of-memory killer (exit 137, nothing said)."""

MAX_GRID_RESOLUTION = 512
"""The finest grid a reconstruction's final stage, or a mesh's voxelization, may be (the service's bound, and the
CLI's ``--resolution``): ``voxe reconstruct --resolution 5000`` had been taken, its grid past the machine's memory."""

MIN_GRID_RESOLUTION = 4
"""The coarsest final grid a reconstruction, or a mesh's voxelization, may be (the service's bound, and the CLI's
``--resolution``, whose per-stage list may start coarser, to 2, as the service's scaled stages do): the CLI had taken
a final 2 or 3 that a job's reconstruction.resolution refuses."""

MAX_MESH_RESOLUTION = 1024
"""The most lattice points per axis an exported mesh is resampled to (the service's ``mesh_resolution`` bound, and
``voxe export-mesh --resolution``'s)."""

REFINE_BACKPROJECTION_STRIDE = 2
"""The back-projection start reads every n-th pixel row and column of each view (maps are a coarse lattice
upsampled)."""

EDIT_SEEDS = 300
"""Voxels of highest P_edit tied to the graph cut's edit terminal."""

OBJECT_SEEDS = 200
"""Voxels of highest P_object tied to the object terminal."""

SERVICE_OBJECT_SEEDS = 5000
"""The service's object seeds instead (the authors' code's count): measured better on bench/localisation.py."""

SERVICE_OBJECT_SEED_MARGIN = 0.02
"""Random object seeds are drawn among P_obj > P_e + this (the authors' code: 0). Chosen on bench/localisation_seeds.py
(spot and horse voxelised and reconstructed, the fox with a hat; clean and moderate maps) by the best worst draw
over seeds 0–4 among 0 / 0.01 / 0.02 / 0.05 (IoU 0.336 / 0.531 / 0.539 / 0.432). On the 25 other draws (seeds
5–29): the fox's worst clean-map cut 0.294 → 0.715, the ten cases' worst draws 0.837 → 0.879 on average, the
mean IoU 0.894 → 0.897; the reconstructed spot's moderate-map mean fell 0.923 → 0.874."""

CUT_SIGMA = 0.1
"""Colour scale of the graph cut's pairwise weights."""

CUT_SMOOTHNESS = 5.0
"""The graph cut's smoothness weight λ."""

MAX_SEED = 2**32 - 1
"""The largest seed a job, the CLI or a RefineConfig takes (numpy's seed range; ``voxe_core.presets`` names it too)."""

TINY_MODEL = "tiny"
"""The name the service's model settings (``VOXE_SDS_MODEL``, ``VOXE_CLIP_MODEL``, ...) give the random-weight
smoke-test models it builds in code: no hub id, and no folder the CLI reads (it had advised ``hf download tiny``)."""

TINY_MODEL_NAME = "voxe-tiny-stable-diffusion (SMOKE-TEST MODEL, random weights)"
"""The ``_name_or_path`` of the model_index.json of a folder ``voxe_core.tiny_sd`` wrote (every build has written it):
what tells a folder holding its random-weight Stable Diffusion (``voxe_core.guidance.loading.smoke_test_model``)."""

SMOKE_TEST_MARK = "voxe_smoke_test"
"""True in the config of ``voxe_core.tiny_eval``'s CLIP and on its Inception module: what tells an evaluation scoring
with them, whatever their folder or file is called, that its numbers are a smoke test's
(``voxe_core.evaluate.smoke_test_roles``)."""

# ------------------------------------------------------------------ evaluation (SPEC §4)
EVALUATION_RING_VIEWS = 100
"""Poses evenly on the 360° ring the edits are scored on (the paper's 100)."""

EVALUATION_RING_ELEVATION = 30.0
"""The evaluation ring's elevation above the horizon, in degrees."""

EVALUATION_RING_SIZE = RENDER_SIZE
"""Pixels of the evaluation ring's renders: the edit's render size."""

MAX_EVALUATION_RING_VIEWS = 360
"""The most poses an evaluation ring may have (the service's bound, and the CLI's through ``EvaluateConfig``); its
renders may be ``MAX_RENDER_SIZE`` px at most."""

# ------------------------------------------------------------------ meshes as input
TEXTURE_SUFFIXES = (".png", ".jpg", ".jpeg")
"""Texture images the mesh loader reads (``voxe_core.mesh_input``), here so the client (``voxe_client``) checks one
without torch."""

# ------------------------------------------------------------------ outputs
VIDEO_SUFFIXES = (".mp4", ".gif")
"""The videos ``voxe_core.export.write_video`` writes, here so ``voxe turntable`` checks its --out before torch."""

MESH_SUFFIXES = (".ply", ".glb", ".obj")
"""The meshes ``voxe_core.export.save_mesh`` writes, here so ``voxe export-mesh`` checks its --out before torch."""

# ------------------------------------------------------------------ how numbers are written
INTEGER_AS_WRITTEN = re.compile(r"-?[0-9]+")
"""An integer as the API's query parameters (``api.paging.DIGITS_ONLY``) and the CLI's options read it: the digits
0-9, an optional minus; ``int()`` had taken ``1_0`` as 10, ``+5`` and `` 5`` as 5, a full-width ``５`` as 5."""
