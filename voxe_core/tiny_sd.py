"""A tiny, randomly initialised Stable Diffusion in the real diffusers layout.

SMOKE-TEST MODEL. Its weights are random: it proves the plumbing only (loading
through :meth:`voxe_core.guidance.sds.StableDiffusionGuidance.from_pretrained`,
shapes, dtypes, gradients flowing from the SDS loss into a render, attention
capture, tokenisation) and says nothing, ever, about edit quality. Never use
it to judge or demonstrate an edit.

The folder written by :func:`build_tiny_stable_diffusion` has exactly the
layout of a Stable Diffusion checkpoint on the hub (``model_index.json`` plus
``unet/ vae/ text_encoder/ tokenizer/ scheduler/``), so it loads through the
same code path as real weights, with no network access:

* UNet: ``UNet2DConditionModel``, block_out_channels (32, 64), one cross-
  attention level at the 16x16 latent resolution, a cross-attention mid block
  at 8x8, cross_attention_dim 32.
* VAE: ``AutoencoderKL`` with 3 blocks (downsampling factor 4): 64 px images
  give 16x16x4 latents, so the guidance ``resolution`` derived from the configs
  (``unet.sample_size * 2**(len(vae.block_out_channels) - 1)``) is 64.
* Text encoder: ``CLIPTextModel`` with hidden size 32, 2 layers, 77 positions.
* Tokenizer: a genuine byte-level CLIP BPE (``vocab.json`` + ``merges.txt``,
  ``</w>`` end-of-word suffixes, ``<|startoftext|>``/``<|endoftext|>``) whose
  vocabulary has all 256 byte symbols (so any text tokenises) plus whole-word
  tokens for the words used by the project's prompts and tests.
* Scheduler: ``DDIMScheduler`` with Stable Diffusion's beta schedule
  (scaled_linear, 0.00085 -> 0.012, 1000 training steps).

Deterministic for a seed; about 3.5 MB on disk.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import shutil
import stat
from pathlib import Path

import torch

from voxe_core.constants import TINY_MODEL_NAME
from voxe_core.files import locked, partial_path
from voxe_core.guidance.loading import smoke_test_model

# Whole-word tokens of the tiny vocabulary. Anything else still tokenises
# through the byte-level fallback (several sub-tokens per word).
TINY_VOCAB_WORDS: tuple[str, ...] = (
    "a", "an", "the", "render", "of", "with", "and", "wearing", "big", "small",
    "dog", "cat", "horse", "chair", "lego", "ficus", "hotdog", "ship", "drums",
    "mic", "materials", "bulldozer", "plant", "object",
    "sunglasses", "party", "hat", "birthday", "christmas", "sweater",
    "yarn", "doll", "wood", "carving", "claymation",
    "front", "side", "back", "overhead", "view",
    "red", "blue", "green", "white", "black", "gold",
)

_BOS = "<|startoftext|>"
_EOS = "<|endoftext|>"
_MAX_LENGTH = 77


def _bytes_to_unicode() -> dict[int, str]:
    """GPT-2/CLIP's reversible map from the 256 byte values to printable characters."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, (chr(c) for c in cs)))


def _bpe(symbols: list[str], ranks: dict[tuple[str, str], int]) -> list[str]:
    """Reference byte-pair encoding: repeatedly merge the best-ranked adjacent pair."""
    symbols = list(symbols)
    while len(symbols) > 1:
        pairs = {(symbols[i], symbols[i + 1]) for i in range(len(symbols) - 1)}
        best = min(pairs, key=lambda p: ranks.get(p, float("inf")))
        if best not in ranks:
            break
        merged: list[str] = []
        i = 0
        while i < len(symbols):
            if i < len(symbols) - 1 and (symbols[i], symbols[i + 1]) == best:
                merged.append(symbols[i] + symbols[i + 1])
                i += 2
            else:
                merged.append(symbols[i])
                i += 1
        symbols = merged
    return symbols


def _word_symbols(word: str, byte_map: dict[int, str]) -> list[str]:
    chars = [byte_map[b] for b in word.encode("utf-8")]
    chars[-1] = chars[-1] + "</w>"
    return chars


def build_clip_bpe(words=TINY_VOCAB_WORDS) -> tuple[dict[str, int], list[tuple[str, str]]]:
    """A CLIP-format byte-level BPE vocabulary and merge list in which every ``word`` is one token.

    Layout as CLIP's: 256 byte symbols, the same 256 with ``</w>``, the merged
    symbols in merge order, then ``<|startoftext|>`` and ``<|endoftext|>``.
    Merges are added greedily and each word is re-encoded with the reference
    BPE after every addition, so words never interfere with one another.
    """
    byte_map = _bytes_to_unicode()
    base = list(byte_map.values())
    vocab_list = base + [b + "</w>" for b in base]
    known = set(vocab_list)
    merges: list[tuple[str, str]] = []
    ranks: dict[tuple[str, str], int] = {}
    for word in words:
        if not re.fullmatch(r"[a-z]+", word):
            raise ValueError(f"tiny vocabulary words must be lower-case letters only, got {word!r}")
        symbols = _bpe(_word_symbols(word, byte_map), ranks)
        while len(symbols) > 1:
            pair = (symbols[0], symbols[1])
            ranks[pair] = len(merges)
            merges.append(pair)
            token = pair[0] + pair[1]
            if token not in known:
                known.add(token)
                vocab_list.append(token)
            symbols = _bpe(_word_symbols(word, byte_map), ranks)
    vocab_list += [_BOS, _EOS]
    return {tok: i for i, tok in enumerate(vocab_list)}, merges


def _write_tokenizer(folder: Path, words) -> dict[str, int]:
    """Write a tokenizer folder as real SD checkpoints ship it: vocab.json, merges.txt and configs."""
    from transformers import CLIPTokenizer

    folder.mkdir(parents=True, exist_ok=True)
    vocab, merges = build_clip_bpe(words)
    (folder / "vocab.json").write_text(json.dumps(vocab, ensure_ascii=False), encoding="utf-8")
    (folder / "merges.txt").write_text(
        "#version: 0.2\n" + "".join(f"{a} {b}\n" for a, b in merges), encoding="utf-8"
    )
    specials = {"bos_token": _BOS, "eos_token": _EOS, "unk_token": _EOS, "pad_token": _EOS}
    (folder / "special_tokens_map.json").write_text(json.dumps(specials, indent=2) + "\n", encoding="utf-8")
    config = {
        "tokenizer_class": "CLIPTokenizer",
        "model_max_length": _MAX_LENGTH,
        "do_lower_case": True,
        "add_prefix_space": False,
        "errors": "replace",
        **specials,
    }
    (folder / "tokenizer_config.json").write_text(json.dumps(config, indent=2) + "\n", encoding="utf-8")

    reloaded = CLIPTokenizer.from_pretrained(str(folder))
    for word in words:
        pieces = reloaded.tokenize(word)
        if len(pieces) != 1:
            raise RuntimeError(f"tiny tokenizer split {word!r} into {pieces}; vocabulary construction is broken")
    if len(reloaded) != len(vocab):
        raise RuntimeError(f"tiny tokenizer reloads with {len(reloaded)} tokens, expected {len(vocab)}")
    return vocab


def build_tiny_stable_diffusion(path, seed: int = 0) -> Path:
    """Write a tiny random-weight Stable Diffusion (SMOKE-TEST MODEL) to ``path``; return the path.

    Random weights: it proves the plumbing only, never edit quality. The same
    ``seed`` always gives byte-identical weights. The folder is in the
    diffusers layout (``model_index.json``, ``unet/``, ``vae/``,
    ``text_encoder/``, ``tokenizer/``, ``scheduler/``) and loads with
    ``StableDiffusionGuidance.from_pretrained(path)`` exactly like real
    weights. Images are 64x64 (16x16x4 latents).

    A ``path`` holding anything but a tiny model (an earlier build, rebuilt) or a file manager's
    :data:`FOLDER_METADATA_FILES` is refused, FileExistsError: the build had written its files among another model's
    (a stale sharded index beside the new weights, which loading then read). Refused, not emptied: the folder may be
    the user's real weights. The model is built in a hidden folder beside ``path`` and then takes its place
    (:func:`_put_in_place`): a build killed or failing part way had left a half-rewritten model, earlier weights
    beside new ones, that loaded as a whole one (or, on a first build, a folder the next build refused). A ``path``
    no rename can replace (a mount point: a container's volume; a folder in one not writable) is built in a hidden
    folder inside it, whose parts then replace the earlier ones (:func:`_move_in`): written in place, a build failing
    there had left the same mix, or a half model the next build refused.
    """
    root = Path(path)
    root.mkdir(parents=True, exist_ok=True)
    if not _tiny_model(root) and (held := sorted(entry.name for entry in root.iterdir()
                                                 if entry.name not in FOLDER_METADATA_FILES
                                                 and not INNER_BUILD.fullmatch(entry.name))):
        raise FileExistsError(f"{root} already holds {', '.join(held[:5])}{', ...' if len(held) > 5 else ''}, not a "
                              "tiny model: the tiny model's files would be mixed with those; give an empty or new "
                              "folder")
    # (a mount point, as a container's volume, is renamed by none, nor a folder in one this process cannot write)
    inside = os.path.ismount(root) or not os.access(Path(os.path.abspath(root)).parent, os.W_OK)
    staging = partial_path(root / "build" if inside else Path(os.path.abspath(root)), secrets.token_hex(4))
    staging.mkdir()
    held = os.open(staging, os.O_RDONLY)
    try:
        if locked(held):  # (held while it builds: a build killed since is told from a live one)
            _remove_dead_builds(staging)
        _write_tiny_stable_diffusion(staging, seed)
        _move_in(staging, root) if inside else _put_in_place(staging, root)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        os.close(held)
    return root


def _remove_dead_builds(staging: Path) -> None:
    """Remove the staging folders beside ``staging`` that builds of the same folder killed mid-way (SIGKILL, out of
    memory) left, each a whole model's size: those no process holds locked. Best effort, as
    :func:`voxe_core.files.remove_dead_partials` for files."""
    token = staging.name.rsplit(".partial", 1)[0][-8:]
    head, tail = staging.name.split(f".{token}.partial", 1)
    pattern = re.compile(re.escape(head) + r"\.[0-9a-f]{8}\.partial" + re.escape(tail))
    with contextlib.suppress(OSError):
        for found in staging.parent.iterdir():
            if found != staging and pattern.fullmatch(found.name) and found.is_dir() and not found.is_symlink():
                with contextlib.suppress(OSError):
                    fd = os.open(found, os.O_RDONLY | os.O_DIRECTORY)
                    try:
                        if locked(fd):
                            shutil.rmtree(found)
                    finally:
                        os.close(fd)


INNER_BUILD = re.compile(r"\.build\.[0-9a-f]{8}\.partial")
"""The name of the hidden folder a build into a mount point writes inside it (one a killed build left is no file of
the user's: the folder stays buildable into)."""
FOLDER_METADATA_FILES = frozenset({".DS_Store", "Thumbs.db", "desktop.ini"})
"""Files a file manager writes into a folder it shows (macOS Finder, Windows Explorer): a folder holding only these
is empty to the user, and is built into (they had had it refused as holding another model's files)."""


def _put_in_place(staging: Path, root: Path) -> None:
    """The folder ``staging`` renamed to ``root`` (empty, a file manager's files aside, or an earlier tiny model),
    keeping ``root``'s permissions: over an empty one in one rename; else ``root`` is first renamed aside, then
    removed once the new one is in place (put back where that rename fails), so that no moment leaves a mix of two
    builds under ``root``."""
    os.chmod(staging, stat.S_IMODE(root.stat().st_mode))
    for name in FOLDER_METADATA_FILES:
        (root / name).unlink(missing_ok=True)
    if not any(root.iterdir()):
        os.replace(staging, root)
        return
    aside = partial_path(Path(os.path.abspath(root)), secrets.token_hex(4))
    held = os.open(root, os.O_RDONLY)
    try:
        locked(held)  # (aside, it is named as a staging folder: held, no other build takes it for a dead one's)
        os.rename(root, aside)
        try:
            os.rename(staging, root)
        except OSError:
            os.rename(aside, root)
            raise
        shutil.rmtree(aside, ignore_errors=True)
    finally:
        os.close(held)


def _move_in(staging: Path, root: Path) -> None:
    """The parts of the model built in ``staging`` (a folder inside ``root``) moved into ``root`` over an earlier tiny
    model's, model_index.json last: the moves take a moment, where the build before them takes seconds."""
    for name in sorted(os.listdir(staging), key=lambda name: name == "model_index.json"):
        target = root / name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        else:
            target.unlink(missing_ok=True)
        os.rename(staging / name, target)


def _write_tiny_stable_diffusion(root: Path, seed: int) -> None:
    """The tiny model's files, written into the empty folder ``root``."""
    import diffusers
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    vocab = _write_tokenizer(root / "tokenizer", TINY_VOCAB_WORDS)

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        unet = UNet2DConditionModel(
            sample_size=16,
            in_channels=4,
            out_channels=4,
            down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
            up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
            block_out_channels=(32, 64),
            layers_per_block=1,
            cross_attention_dim=32,
            attention_head_dim=4,
            norm_num_groups=8,
        )
        torch.manual_seed(seed + 1)
        vae = AutoencoderKL(
            in_channels=3,
            out_channels=3,
            down_block_types=("DownEncoderBlock2D",) * 3,
            up_block_types=("UpDecoderBlock2D",) * 3,
            block_out_channels=(8, 16, 16),
            latent_channels=4,
            layers_per_block=1,
            norm_num_groups=8,
            sample_size=64,
        )
        torch.manual_seed(seed + 2)
        text_config = CLIPTextConfig(
            vocab_size=len(vocab),
            hidden_size=32,
            intermediate_size=64,
            projection_dim=32,
            num_hidden_layers=2,
            num_attention_heads=4,
            max_position_embeddings=_MAX_LENGTH,
            hidden_act="quick_gelu",
            bos_token_id=vocab[_BOS],
            eos_token_id=vocab[_EOS],
            pad_token_id=vocab[_EOS],
        )
        text_encoder = CLIPTextModel(text_config)

    scheduler = DDIMScheduler(
        num_train_timesteps=1000,
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="scaled_linear",
        clip_sample=False,
        set_alpha_to_one=False,
        steps_offset=1,
    )

    unet.save_pretrained(str(root / "unet"))
    vae.save_pretrained(str(root / "vae"))
    text_encoder.save_pretrained(str(root / "text_encoder"))
    scheduler.save_pretrained(str(root / "scheduler"))

    # What StableDiffusionPipeline.save_pretrained writes, without importing the
    # pipeline (and its image-processor dependencies).
    model_index = {
        "_class_name": "StableDiffusionPipeline",
        "_diffusers_version": diffusers.__version__,
        "_name_or_path": TINY_MODEL_NAME,
        "feature_extractor": [None, None],
        "image_encoder": [None, None],
        "requires_safety_checker": False,
        "safety_checker": [None, None],
        "scheduler": ["diffusers", "DDIMScheduler"],
        "text_encoder": ["transformers", "CLIPTextModel"],
        "tokenizer": ["transformers", "CLIPTokenizer"],
        "unet": ["diffusers", "UNet2DConditionModel"],
        "vae": ["diffusers", "AutoencoderKL"],
    }
    (root / "model_index.json").write_text(json.dumps(model_index, indent=2) + "\n", encoding="utf-8")
    (root / "README.md").write_text(
        "# SMOKE-TEST MODEL\n\nRandomly initialised tiny Stable Diffusion written by "
        "`voxe_core.tiny_sd.build_tiny_stable_diffusion(path, seed=%d)`.\n"
        "It proves the plumbing only; it never says anything about edit quality.\n" % seed,
        encoding="utf-8",
    )
    mode = stat.S_IMODE((root / "README.md").stat().st_mode)  # what a new file gets here (the umask's)
    for weights in root.rglob("*.safetensors"):  # safetensors renames its own 0600 files into place
        weights.chmod(mode)


def _tiny_model(root: Path) -> bool:
    """Whether the folder ``root`` holds a tiny model :func:`build_tiny_stable_diffusion` wrote (rebuilt in place)."""
    return smoke_test_model(str(root))
