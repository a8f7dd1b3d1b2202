"""Request and response bodies of the /v1 API (pydantic 2).

Job parameters are typed with the paper's defaults (SPEC §1-§3), read from ``voxe_core.presets`` and
``voxe_core.constants`` (torch-free) so the CLI and the service share one set, and forbid unknown
fields, so a misspelt parameter is a 422 naming it instead of a silently ignored value.
"""

from __future__ import annotations

import unicodedata
from datetime import datetime
from typing import Annotated, Generic, Literal, TypeVar

from pydantic import (
    AfterValidator, BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_serializer, model_validator,
)

from voxe_core import constants as paper
from voxe_core import presets
from voxe_core.guidance.prompts import (CLIP_SPECIAL_TOKENS, TEXT_ENCODER_TOKENS, check_edit_words_name_an_edit,
                                        check_edit_words_read, check_no_special_tokens, check_prompt_length,
                                        names_something)
from voxe_service.webhooks import DEFAULT_WEBHOOK_EVENTS, WEBHOOK_EVENTS

T = TypeVar("T")

Regulariser = Literal["reg3d", "reg3d_plus", "volumetric_l1", "volumetric_l2", "image_l1", "image_l2"]
JobState = Literal["queued", "running", "succeeded", "failed", "canceled"]
SceneState = Literal["processing", "ready", "failed"]
Stage = Literal["reconstruct", "edit", "refine", "export", "evaluate"]
WebhookEvent = Literal[WEBHOOK_EVENTS]


StageIterations = Annotated[int, Field(ge=0, le=1_000_000)]
# What str.split() splits at, spelt out: a JSON Schema pattern is ECMA-262's, whose \s lacks \x1c-\x1f and \x85 and
# has \ufeff.
_WHITESPACE = r"\t-\r\x1c-\x20\x85\xa0\u1680\u2000-\u200a\u2028\u2029\u202f\u205f\u3000"
# What clean_text accepts, for the document: no control character but whitespace, and a character naming something
# (names_something: a letter, digit or symbol) somewhere: for a single ASCII character exactly so (0-9 A-Z a-z $);
# beyond it, any character but whitespace. So it never refuses what the server takes, but takes some texts the server
# refuses: a contraction's ending alone ("'s", "'ll-") is no word to the model, and neither is a character beyond
# ASCII that names nothing. ECMA-262 has no class of Unicode's letters, digits and symbols that every JSON Schema
# validator reads alike (its \w is ASCII's: "猫" had been no word to the document; \p{L} needs the u flag), so the
# descriptions say the rule, and the server applies it.
_ALLOWED = r"[^\x00-\x08\x0e-\x1b\x7f-\x84\x86-\x9f]"
_NAMING_CHARACTER = rf"[^{_WHITESPACE}\x00-\x23\x25-\x2f\x3a-\x40\x5b-\x60\x7b-\x9f]"
TEXT_PATTERN = rf"^{_ALLOWED}*{_NAMING_CHARACTER}{_ALLOWED}*$"
# An edit word's: something but whitespace (whether it names anything, a symbol as "🎩" does, is the core's rule).
EDIT_WORD_PATTERN = rf"^{_ALLOWED}*[^{_WHITESPACE}\x00-\x08\x0e-\x1b\x7f-\x84\x86-\x9f]{_ALLOWED}*$"
# A scene's name sent in the upload form: no control character (it is one line of display text), something but
# whitespace (scene_name).
_NOT_IN_NAME = r"\x00-\x1f\x7f-\x9f"
SCENE_NAME_PATTERN = rf"^[^{_NOT_IN_NAME}]*[^{_WHITESPACE}{_NOT_IN_NAME}][^{_NOT_IN_NAME}]*$"
# A webhook URL's: no whitespace, spelt out as str.split()'s and ECMA-262's \s (\ufeff): its \s had been read apart by
# the document's readers (no \x85, \ufeff) and the server's check (\x85, no \ufeff). (NUL and a lone surrogate are
# every string's rule: Strict.) The scheme in any case (RFC 3986 §3.1), as the checks and the sender read it: "HTTP://"
# had been refused by this pattern alone.
_NOT_IN_URL = rf"{_WHITESPACE}\ufeff"
WEBHOOK_URL_PATTERN = rf"^[Hh][Tt][Tt][Pp][Ss]?://[^{_NOT_IN_URL}/?#]+[^{_NOT_IN_URL}]*$"
_NO_SPECIAL_TOKENS = (f"nor CLIP's special tokens {' or '.join(CLIP_SPECIAL_TOKENS)} written out (the model reads "
                      "each as its text's start or end)")
_TEXT_RULE = (" (something that names: a word or number of any script, or a symbol such as an emoji or a currency "
              "sign, not punctuation, marks such as ^ + | or a contraction's ending such as 's alone; no control "
              f"characters but whitespace, which is collapsed, {_NO_SPECIAL_TOKENS})")


class Strict(BaseModel):
    """Unknown fields, non-finite numbers (JSON's NaN / Infinity extensions), coercions (1 for true, "5" for 5,
    5.0 for an integer), NUL characters in strings (PostgreSQL text cannot hold one) and lone surrogates (JSON may
    escape one; no UTF-8 holds it: pydantic's string_unicode) are 422s naming the field: what the OpenAPI document
    says is all that is accepted."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)

    @field_validator("*", mode="after")
    @classmethod
    def _no_nul(cls, value):
        if _holds_nul(value):
            raise ValueError("contains a NUL character")
        return value


def _holds_nul(value) -> bool:
    if isinstance(value, str):
        return "\x00" in value
    if isinstance(value, (list, tuple)):
        return any(map(_holds_nul, value))
    return isinstance(value, dict) and any(_holds_nul(k) or _holds_nul(v) for k, v in value.items())


# ------------------------------------------------------------------ job parameters
class ReconstructionParams(Strict):
    """How G_i is fitted (SPEC §1). Jobs with equal values (and downsample / resample / max_images) share one fit."""

    preset: Literal["fast", "paper", "scene"] | None = Field(
        None, description="fast: 40→80→128 (the CPU budget); paper: the authors' 20→40→80→160 × 500 iterations; "
        "scene: 48→96 (the CPU budget of a scene-backbone fit); none: scene for a scene-backbone fit, fast otherwise"
    )
    resolution: int | None = Field(
        None, ge=paper.MIN_GRID_RESOLUTION, le=paper.MAX_GRID_RESOLUTION,
        description="final grid resolution; earlier stages are scaled in proportion"
    )
    iterations: Annotated[list[StageIterations], Field(min_length=1, max_length=8)] | StageIterations | None = Field(
        None, description="iterations of the final stage, or one value per stage of the preset (fast: 3, paper: 4, scene: 2; "
        "another count is a 422, under backbone auto counted for the scene's backbone; a job created while its "
        "scene is processing fails, naming the count, when the processing decides a backbone that does not take "
        "it); the preset's otherwise"
    )
    rays_per_step: int | None = Field(None, ge=1, le=paper.MAX_RAYS_PER_STEP)
    seed: int = Field(presets.SEED, ge=0, le=presets.MAX_SEED)
    backbone: Literal[presets.BACKBONE_CHOICES] = Field(
        presets.BACKBONE, description="relu_field: objects on a transparent background; scene: captured photos with a "
        "background (DVGO-style, SPEC §5); auto: the scene's backbone (decided from its images' alpha)"
    )
    route: Literal["auto", "fit", "voxelize"] = Field(
        "auto", description="fit: optimise G_i on the images; voxelize: write an uploaded mesh straight into G_i "
        "at the final resolution (mesh scenes only); auto: voxelize for mesh scenes, fit otherwise"
    )

    @model_validator(mode="after")
    def _route(self):
        if self.route == "voxelize" and self.backbone == "scene":
            raise ValueError("route 'voxelize' writes an object grid: it cannot give backbone 'scene'")
        return self


class RefineParams(Strict):
    """Spatial refinement of local edits (SPEC §3)."""

    iterations: int = Field(paper.SERVICE_REFINE_ITERATIONS, ge=0, le=100_000,
                            description="fitting steps of the 3D attention grids after their back-projection start (the paper: 1500)")
    lift_start: Literal[presets.LIFT_STARTS] = Field(
        presets.LIFT_START, description="start of the attention grids: the maps' weighted back-projection, or 0 (the paper's; "
        "it needs iterations > 0)")
    smoothing_sigma: float = Field(paper.SERVICE_SMOOTHING_SIGMA, ge=0, le=16,
                                   description="std in attention cells of the 2D maps' 3x3 Gaussian, applied on the 16x16 map and again "
                                               "after upsampling (the authors' code)")
    lr: float = Field(paper.REFINE_LR, gt=0, le=10)
    tv_weight: float = Field(paper.REFINE_TV_WEIGHT, ge=0, le=1e6)
    render_size: int | None = Field(None, ge=paper.MIN_RENDER_SIZE, le=paper.MAX_RENDER_SIZE, description="attention render size (default: the edit's)")
    views: int = Field(paper.REFINE_VIEWS, ge=1, le=paper.MAX_REFINE_VIEWS,
                       description="random upper-hemisphere poses whose 2D attention maps are lifted")
    rays_per_step: int = Field(paper.REFINE_RAYS_PER_STEP, ge=1, le=paper.MAX_RAYS_PER_STEP)
    edit_seeds: int = Field(paper.EDIT_SEEDS, ge=0, le=10_000_000,
                            description="voxels tied to the 'edit' terminal: every voxel with P_edit >= 0.992 max "
                                        "P_edit, topped up to this many by the highest P_edit, then only those more "
                                        "likely edit than object (the authors' code)")
    # At least 1: the service's cut has no unary term, so with no object seed nothing pulls a voxel to the object and
    # every voxel joined to an edit seed stayed edited (0 had run the whole refinement to an edit not localised).
    object_seeds: int = Field(paper.SERVICE_OBJECT_SEEDS, ge=1, le=10_000_000,
                              description="up to this many voxels tied to the 'object' terminal, drawn at random (the "
                                          f"job's seed) among P_object > P_edit + {paper.SERVICE_OBJECT_SEED_MARGIN} "
                                          "(the authors' code: among P_object > P_edit); at least 1, as the cut has "
                                          "no unary term: without object seeds it keeps every voxel joined to an edit "
                                          "seed")
    sigma: float = Field(paper.CUT_SIGMA, gt=0, le=1e6, description="colour scale of the pairwise weights")
    smoothness: float = Field(paper.CUT_SMOOTHNESS, ge=0, le=1e6, description="graph-cut smoothness weight λ")


class ExportParams(Strict):
    """What the export stage writes (``voxe_core.presets.ExportConfig``)."""

    views: int = Field(presets.ExportConfig.views, ge=0, le=360, description="PNG renders on a ring around the object")
    view_size: int = Field(presets.ExportConfig.view_size, ge=8, le=2048)
    turntable_frames: int = Field(presets.ExportConfig.turntable_frames, ge=1, le=1000)
    turntable_size: int = Field(presets.ExportConfig.turntable_size, ge=8, le=2048)
    elevation: float = Field(presets.ExportConfig.elevation, ge=-89, le=89)
    fps: float = Field(presets.ExportConfig.fps, ge=presets.VIDEO_MIN_FPS, le=120,
                       description="turntable frames per second; a GIF frame lasts at most 655.35 s")
    gif: bool = presets.ExportConfig.gif
    mesh: bool = presets.ExportConfig.mesh
    mesh_resolution: int | None = Field(presets.ExportConfig.mesh_resolution, ge=2, le=paper.MAX_MESH_RESOLUTION)


class JobParams(Strict):
    # input images
    downsample: int = Field(presets.DOWNSAMPLE, ge=1, le=64,
                            description="integer image downsampling on load (paper: 800 px / 3)")
    resample: Literal["bilinear", "box"] = Field(
        presets.RESAMPLE, description="the downsampling's antialiasing filter (bilinear: as the authors' loader)"
    )
    max_images: int | None = Field(None, ge=1, le=100_000, description=(
        "use only the first N training images. A scene-backbone fit of one image (1 here, or a one-image scene; one "
        "camera orbits no centre) is a 422 where the backbone is known: named 'scene', or 'auto' on a ready scene of "
        "photos; a job on a scene still processing fails when its ingest decides 'auto' is the scene backbone. 1 is "
        "a 422 too for a sweep's evaluation with fid_input (FID compares at least 2)"))
    # editing (SPEC §2)
    iterations: int = Field(
        paper.EDIT_ITERATIONS, ge=0, le=200_000,
        description=f"edit iterations; on a scene-backbone G_i the default {paper.EDIT_ITERATIONS} means SPEC §5's "
        f"{presets.EDIT_SCHEDULES['scene'].iterations} (any other count runs as given)",
    )
    render_size: int = Field(paper.RENDER_SIZE, ge=paper.MIN_RENDER_SIZE, le=paper.MAX_RENDER_SIZE, description="edit render size in pixels")
    guidance_scale: float = Field(paper.DEFAULT_GUIDANCE_SCALE, gt=0, le=1000)
    lr: float = Field(paper.EDIT_LR, gt=0, le=10)
    regulariser: Regulariser = paper.DEFAULT_REGULARISER
    regulariser_weight: float = Field(paper.DEFAULT_REGULARISER_WEIGHT, ge=0, le=1e6)
    timestep_schedule: Literal["paper", "authors"] = Field(
        presets.TIMESTEP_SCHEDULES[0],
        description="annealing floor 0.35 (paper) or 0.22 (authors' code); a scene-backbone G_i anneals from "
        f"iteration {presets.EDIT_SCHEDULES['scene'].i_start} every {presets.EDIT_SCHEDULES['scene'].every} (SPEC §5)",
    )
    view_words: bool = Field(presets.VIEW_WORDS, description="append ', front view' etc. to the prompt from the pose (the authors' code)")
    batch_size: int = Field(presets.BATCH_SIZE, ge=1, le=paper.MAX_BATCH_SIZE)
    autocast: Literal["bf16", "fp16"] | None = None
    seed: int = Field(presets.SEED, ge=0, le=presets.MAX_SEED)
    preview_every: int = Field(presets.PREVIEW_EVERY, ge=0, le=200_000,
                               description="iterations between preview renders (0: none)")
    reconstruction: ReconstructionParams = Field(default_factory=ReconstructionParams)
    refine: RefineParams = Field(default_factory=RefineParams, validate_default=True)
    export: ExportParams = Field(default_factory=ExportParams, validate_default=True)

    # Each stage's config built as the worker will (a rule the bounds above miss had failed the job after its fit),
    # a refusal located at the stage's section; the reconstruction's is checked against the scene
    # (api.services.jobs.usable_scene).
    @field_validator("refine")
    @classmethod
    def _refinement_takes_it(cls, refine: RefineParams, info: ValidationInfo) -> RefineParams:
        # with the edit's fields above it (its render size is the refinement's default; view words, seed)
        presets.check_stage("refine", {**info.data, "refine": refine.model_dump(mode="json")})
        return refine

    @field_validator("export")
    @classmethod
    def _export_takes_it(cls, export: ExportParams) -> ExportParams:
        presets.check_stage("export", {"export": export.model_dump(mode="json")})
        return export

    @model_validator(mode="after")
    def _edit_takes_them(self):
        presets.check_stage("edit", self.model_dump(mode="json"))
        return self


def clean_text(value: str, what: str, need_words: bool = True) -> str:
    """Free text with whitespace collapsed; control characters, CLIP's special tokens written out (its tokenizer
    reads each as the text's start or end, and no word starts after it) or nothing the model reads as naming anything
    (a word, number or symbol; without ``need_words``: nothing at all) are errors naming ``what``. A prompt of an
    emoji alone ("🐶") had been refused as having no words, one of punctuation alone ("---") accepted: the other
    way round from what names an edit or the object (check_edit_words_name_an_edit)."""
    if any(unicodedata.category(c) == "Cc" and not c.isspace() for c in value):
        raise ValueError(f"{what} contains control characters")
    check_no_special_tokens(value, what)
    value = " ".join(value.split())
    if need_words and not names_something(value):
        raise ValueError(f"{what} has no words: nothing in it names anything (a word, number or symbol such as an "
                         "emoji does; punctuation, marks such as ^ + | or a contraction's ending such as 's alone do "
                         "not)")
    if not value:
        raise ValueError(f"{what} is blank")
    return value


def scene_name(value: str | None) -> str | None:
    """The upload form's ``name`` as sent, or an error saying what it holds that a name cannot: a control character
    (a newline or ESC had been stored and listed as sent, where a name taken from the file's has them stripped) or
    nothing but whitespace (a name of spaces had been stored, so the scene listed as nameless). Refused, not cleaned:
    the user chose this text, and a scene stored under other words would not be found by the name they sent."""
    if value is None:
        return None
    if any(unicodedata.category(c) == "Cc" for c in value):
        raise ValueError("the name contains control characters (a newline, tab or escape, say): send one line of text")
    if not value.strip():
        raise ValueError("the name is blank: send one with something but spaces, or leave it out for the default "
                         "(the file's name)")
    return value


# A symbol the model reads names an edit ("🎩"): check_edit_words_name_an_edit refuses what names nothing.
EditWord = Annotated[str, Field(min_length=1, max_length=100, json_schema_extra={"pattern": EDIT_WORD_PATTERN}),
                     AfterValidator(lambda value: clean_text(value, "an edit word", need_words=False))]


class JobCreate(Strict):
    scene_id: str = Field(min_length=1, max_length=64)
    prompt: str = Field(min_length=1, max_length=500, json_schema_extra={"pattern": TEXT_PATTERN},
                        description='e.g. "a microphone wearing big sunglasses"' + _TEXT_RULE
                        + f"; at most {TEXT_ENCODER_TOKENS} text-encoder tokens as the model sees it (with the "
                          "view_words suffix, start and end tokens included): a prompt surely longer is a 422, "
                          "one the model's tokenizer splits further fails the job before its fit")
    mode: Literal[presets.EDIT_MODES] = Field(presets.EDIT_MODE, description="local: refined to the edit_words' region")
    edit_words: list[EditWord] = Field(
        default_factory=list, max_length=16,
        description="local edits: the word(s) of the prompt naming the edit (e.g. ['sunglasses']); required "
        "(non-empty) with mode 'local', empty otherwise. Rules beyond the schema (422 naming them): each names "
        "something (a word, number or symbol such as an emoji or a currency sign; punctuation, marks such as "
        "^ + | and a contraction's ending such as 's name nothing), occurs in the prompt as whole words, also as "
        "the model reads the prompt (punctuation at a word's edge is read with the punctuation beside it: 'hat.' "
        "is not found in '..., a hat.'), and some other word of the prompt names the object; no control characters "
        f"but whitespace, {_NO_SPECIAL_TOKENS}",
    )
    params: JobParams = Field(default_factory=JobParams)
    webhook_url: str | None = Field(
        None, max_length=2000, pattern=WEBHOOK_URL_PATTERN,
        description="POST each event of `webhook_events` here, signed (Standard Webhooks; the secret is at "
        "GET /v1/webhooks/secret); a public address unless the operator allows more (VOXE_WEBHOOK_ALLOW_NETWORKS). "
        "Beyond the pattern, as in every string: no NUL character and no lone surrogate (U+D800-U+DFFF)",
    )
    webhook_events: list[WebhookEvent] | None = Field(
        None, min_length=1, max_length=len(WEBHOOK_EVENTS), json_schema_extra={"uniqueItems": True},
        description=f"which job events to send (default: {', '.join(DEFAULT_WEBHOOK_EVENTS)}); needs webhook_url",
    )

    @field_validator("webhook_events")
    @classmethod
    def _distinct_events(cls, value):
        if value is not None and len(set(value)) != len(value):
            raise ValueError("webhook_events lists an event twice")
        return value

    @field_validator("prompt")
    @classmethod
    def _prompt(cls, value: str) -> str:
        return clean_text(value, "the prompt")

    @model_validator(mode="after")
    def _edit_words(self):
        check_prompt_length(self.prompt, self.params.view_words)  # a longer one was cut off at the text encoder
        if broken := presets.broken_job_option_rule(self.mode, self.edit_words, self.webhook_url, self.webhook_events):
            raise ValueError(JOB_OPTION_RULES[broken])
        if self.mode == "local":
            # Words as the model splits them, in NFC: "dog" in "a dog's hat", "sunglasses" in "sunglasses-wearing"
            # and a decomposed "café" in a composed one had been refused as "not in the prompt".
            check_edit_words_name_an_edit(self.prompt, self.edit_words)
            # As the refinement's attention model will look for them, after the edit: "hat." or "hat!" had passed
            # the whole-word match above and failed the job there.
            check_edit_words_read(self.prompt, self.edit_words, self.params.view_words)
        return self


JOB_OPTION_RULES = {
    "edit_words_required": "edit_words is required for a local edit: the word(s) of the prompt naming the edit",
    "edit_words_local_only": "edit_words apply to local edits only (mode 'local')",
    "webhook_events_need_url": "webhook_events needs a webhook_url to send them to",
}
"""``presets.JOB_OPTION_RULES`` as ``POST /v1/jobs`` says them (its fields')."""


# ------------------------------------------------------------------ evaluation (SPEC §4)
class EvaluationParams(Strict):
    """The ring the edits are scored on, and what they are compared with."""

    views: int = Field(paper.EVALUATION_RING_VIEWS, ge=2, le=paper.MAX_EVALUATION_RING_VIEWS,
                       description="poses evenly on a 360° ring (default: the paper's)")
    elevation: float = Field(paper.EVALUATION_RING_ELEVATION, gt=-90, lt=90,
                             description="ring elevation above the horizon, degrees")
    size: int = Field(paper.EVALUATION_RING_SIZE, ge=11, le=paper.MAX_RENDER_SIZE, description="ring render size in pixels")
    fid_input: bool = Field(True, description="also FID against the scene's input images (FID_input): a 422 where "
                            "the edits were fitted from fewer than 2 (params.max_images, or the scene's images)")
    save_renders: bool = Field(True, description="publish the ring renders as PNG artifacts")


ObjectName = Annotated[str, Field(min_length=1, max_length=100, json_schema_extra={"pattern": TEXT_PATTERN}),
                      AfterValidator(lambda value: clean_text(value, "the object name"))]


class EvaluationCreate(Strict):
    job_ids: list[Annotated[str, Field(min_length=1, max_length=64)]] = Field(
        min_length=1, max_length=60, json_schema_extra={"uniqueItems": True},
        description="succeeded edit jobs of one scene and reconstruction")
    object: ObjectName = Field(description='what the object is: the source text is "a render of a <object>"'
                               + _TEXT_RULE + f"; a source text surely longer than the {TEXT_ENCODER_TOKENS} "
                               "tokens CLIP's text model reads is a 422")
    params: EvaluationParams = Field(default_factory=EvaluationParams)

    @field_validator("job_ids")
    @classmethod
    def _unique(cls, value: list[str]) -> list[str]:
        if len(set(value)) != len(value):
            raise ValueError("job_ids lists a job twice")
        return value


class SweepScene(Strict):
    scene_id: str = Field(min_length=1, max_length=64)
    object: ObjectName = Field(description='the object\'s name in the prompts, e.g. "microphone"' + _TEXT_RULE)


class SweepCreate(Strict):
    """The paper's protocol: every scene × the six prompts of SPEC §4 (local ones refined), each edit then evaluated."""

    scenes: list[SweepScene] = Field(min_length=1, max_length=20, description="each scene_id once")
    params: JobParams = Field(default_factory=JobParams)
    evaluation: EvaluationParams = Field(default_factory=EvaluationParams)

    @field_validator("scenes")
    @classmethod
    def _unique(cls, value: list[SweepScene]) -> list[SweepScene]:
        if len({s.scene_id for s in value}) != len(value):
            raise ValueError("scenes lists a scene twice")
        return value


class SweepEntry(BaseModel):
    scene_id: str
    object: str
    prompt: str
    mode: str
    edit_job_id: str
    edit_state: JobState
    evaluation_job_id: str
    evaluation_state: JobState


class SweepOut(BaseModel):
    id: str
    state: JobState = Field(description="succeeded / failed / canceled once every job is finished, else running or queued")
    counts: dict[str, int] = Field(description="jobs of the sweep (edits and evaluations) per state")
    entries: list[SweepEntry]
    rows: list[dict] = Field(description="one per evaluated edit: scene, object, prompt, mode and the metrics")
    means: dict = Field(description="metric means over the local edits, the global ones and all")
    table: str = Field(description="the rows and means as a Markdown table, below a line \"**SMOKE TEST**: ...\" "
                                   "where the evaluations scored with the random-weight smoke-test models")


# ------------------------------------------------------------------ responses
class Page(BaseModel, Generic[T]):
    items: list[T]
    total: int
    limit: int
    offset: int = Field(description="how many rows come before this page (with a cursor: as the list is now)")
    next_cursor: str | None = Field(description="send as `cursor` for the page after this one's last row (stable "
                                                "while rows are added); null on the last page")


class SceneOut(BaseModel):
    id: str
    name: str
    format: str
    state: SceneState = Field(description="processing: stored, its images being decoded (a mesh rendered) by a "
                                          "worker; ready: jobs run on it; failed: see error")
    error: str | None = Field(description="why the scene failed (the file and frame, as a 422 would say); while "
                                          "processing, what stopped its ingest's last run (an outage, the worker's "
                                          "disk full: it is tried again)")
    image_count: int
    width: int
    height: int
    splits: list[str] = Field(description="a NeRF-synthetic dataset's splits that load: train, and val or test where "
                                          "its transforms_val.json or transforms_test.json loads with its first image "
                                          "(one that does not is stored unlisted: jobs fit train); all for the other "
                                          "formats; train and test for a mesh's rendered views")
    backbone: Literal[presets.BACKBONE_KINDS] | None = Field(
        description="what reconstruction backbone auto means for this scene, decided by its processing from all its "
        "training images (relu_field: an object on a transparent background; scene: opaque photos); null while "
        "processing, and for scenes processed before it was recorded")
    warnings: list[str] | None = Field(
        description="what its processing loaded the upload without (a mesh's .mtl its OBJ names not sent, its PLY's "
        "TextureFile unread: the mesh loads grey), each also a warning event (stage ingest) of every edit job on the "
        "scene, whether created before or after it was ready; [] for none; null while processing, and for scenes "
        "processed before it was recorded (not known: an edit job created on such a mesh scene is told so, a warning "
        "event of stage ingest). A failed scene keeps those said before it failed (null where "
        "it failed before its upload was loaded)")
    size_bytes: int = Field(description="bytes stored (0 once failed: a failed upload is not kept)")
    sha256: str
    created_at: datetime


class ReconstructionOut(BaseModel):
    id: str
    state: str
    run_count: int = Field(description="how many times a fit was started (1 for a fit that ran once)")
    iteration: int
    total: int
    params: dict
    error: str | None = Field(description="why its last fit stopped: failed, or pending after a fit whose worker ran "
                              "out of memory, could not store its grid, or met a storage or database outage or a full "
                              "disk (handed back to a job of it not yet ended)")
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class JobReconstruction(BaseModel):
    id: str | None
    state: str | None
    error: str | None = Field(description="why its last fit stopped, as the scene's reconstructions list it: "
                              "failed, or pending after a fit whose worker ran out of memory, could not store its grid, "
                              "or met a storage or database outage or a full disk")
    run_count: int | None
    reused: bool | None = Field(description="true when this job used a reconstruction another job had fitted")


class Models(BaseModel):
    sds: str | None
    attention: str | None
    clip: str | None = Field(None, description="evaluation jobs only")
    fid: str | None = Field(None, description="evaluation jobs only")

    @model_serializer(mode="wrap")
    def _evaluation_models_only_when_set(self, handler):
        """An edit job's models read {sds, attention} as they always did."""
        return {k: v for k, v in handler(self).items() if k in ("sds", "attention") or v is not None}


class JobOut(BaseModel):
    id: str
    scene_id: str
    prompt: str
    mode: str
    edit_words: list[str]
    params: dict
    models: Models
    device: str
    state: JobState
    stage: Stage | None
    iteration: int
    total: int
    progress: float = Field(description="fraction of the current stage done")
    completed_stages: list[str]
    elapsed_seconds: float | None
    eta_seconds: float | None = Field(description="estimated seconds left in the current stage")
    overall_progress: float = Field(ge=0, le=1, description="fraction of the whole job done: its stages weighed "
                                    "by their measured costs on the job's device (voxe_service/progress.py)")
    overall_eta_seconds: float | None = Field(description="estimated seconds left for the whole job (running jobs)")
    losses: dict
    message: str | None
    error: str | None
    cancel_requested: bool
    reconstruction: JobReconstruction
    preview_url: str | None
    artifacts_url: str
    events_url: str = Field(description="the job's timeline: stages, checkpoints, resumes, its end")
    worker_hostname: str | None
    source_job_ids: list[str] | None = Field(None, description="evaluation jobs: the edit jobs scored")
    result: dict | None = Field(None, description=(
        "peak_memory_gb: each stage's peak memory in GiB (peak_memory_kind: cuda_allocated on a GPU worker, "
        "process_rss on a CPU one); edit_schedule: the edit the worker runs, recorded when the job's fit starts or its reconstruct stage ends (backbone of G_i, iterations, i_start, "
        "every, floor: SPEC §5's 5000 / 3000 / 400 for a capture's scene grid); fit: what the job's own fit runs, "
        "recorded as it starts (backbone, steps, rays_per_step: what overall_progress weighs it by); graph_cut: a local "
        "edit's refinement cut, as voxe refine's refine.json (nodes: the occupied voxels, edit_voxels: those taking "
        "the edit, seeds, flow, notes; none or all of them taken: a warning event too); orbit_centre: the point the "
        "renders and the turntable look at, in G_i's frame (the origin for objects, the fitted object's matter "
        "centre for captures); evaluation jobs: the metrics too (also the evaluation.json artifact)"))
    batch_id: str | None = Field(None, description="the sweep this job belongs to")
    webhook_url: str | None = None
    webhook_events: list[str] | None = None
    webhooks_url: str = Field(description="the job's webhook deliveries and their attempts")
    created_at: datetime
    started_at: datetime | None
    stage_started_at: datetime | None = Field(None, description="when its current (or last) stage's run began")
    finished_at: datetime | None
    updated_at: datetime


class JobEventOut(BaseModel):
    id: int
    kind: str = Field(description="stage_started, stage_completed, checkpoint, resumed, requeued, warning (a "
                                  "stage's result to look at, an edit's regulariser a constant reconstruction switches "
                                  "off, a start over from a checkpoint it could not go on from, or a mesh scene's "
                                  "ingest loading the mesh without the .mtl or texture its file names: detail says "
                                  "what), artifact, preview, succeeded, failed or canceled")
    stage: str | None
    iteration: int | None = Field(description="checkpoint: the iteration it holds; resumed: where the stage went on")
    worker_hostname: str | None
    detail: str | None
    at: datetime


class WebhookDeliveryOut(BaseModel):
    id: str = Field(description="the webhook-id header: the same on every attempt (dedupe on it)")
    event_id: int = Field(description="the timeline event delivered")
    event_type: str = Field(description='"job." + the event kind, as the body\'s "type"')
    url: str
    state: Literal["pending", "delivered", "failed"] = Field(
        description="pending: due at next_attempt_at; delivered: the receiver answered 2xx; failed: gave up")
    attempts: int
    last_status: int | None = Field(description="the receiver's last HTTP status (null: no answer)")
    last_error: str | None
    next_attempt_at: datetime | None
    created_at: datetime
    delivered_at: datetime | None


class WebhookSecretOut(BaseModel):
    secret: str = Field(description="whsec_<base64>: the HMAC-SHA256 key of this API key's webhook signatures")


class ArtifactOut(BaseModel):
    name: str
    kind: str
    size: int
    content_type: str
    sha256: str
    url: str
    created_at: datetime


class Problem(BaseModel):
    detail: str | dict | list
