"""Guidance interface, SDS and cross-attention capture on the tiny random-weight SD.

The tiny model (voxe_core.tiny_sd) is a SMOKE-TEST MODEL: these tests check
plumbing and maths (gradients, shapes, normalisation, loading), never quality.
"""

from __future__ import annotations

import json
import re
import shutil

import pytest
import torch

from voxe_core.constants import ATTENTION_MODEL_ID, SDS_MODEL_ID
from voxe_core.guidance import Guidance
from voxe_core.guidance.attention import AttentionStore, CrossAttentionCapture
from voxe_core.guidance.loading import ModelNotAvailableError, download_command
from voxe_core.guidance.prompts import TEXT_ENCODER_TOKENS, clip_pieces, edit_prompt, tokens_at_least, view_word
from voxe_core.guidance.sds import StableDiffusionGuidance
from voxe_core.tiny_sd import build_tiny_stable_diffusion


@pytest.fixture(autouse=True)
def _single_thread():
    # The tiny model's ops are microseconds long: OpenMP thread hand-offs
    # dominate (and stall badly on a loaded 2-core box).
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def tiny_path(tmp_path_factory):
    return build_tiny_stable_diffusion(tmp_path_factory.mktemp("tiny_sd") / "model", seed=0)


@pytest.fixture(scope="session")
def guidance(tiny_path) -> StableDiffusionGuidance:
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HF_HUB_OFFLINE", "1")
        return StableDiffusionGuidance.from_pretrained(str(tiny_path))


# ----------------------------------------------------------------- tiny model


def test_tiny_model_layout_and_size(tiny_path):
    index = json.loads((tiny_path / "model_index.json").read_text())
    assert index["_class_name"] == "StableDiffusionPipeline"
    assert index["unet"] == ["diffusers", "UNet2DConditionModel"]
    assert index["tokenizer"] == ["transformers", "CLIPTokenizer"]
    for sub in ("unet", "vae", "text_encoder", "tokenizer", "scheduler"):
        assert (tiny_path / sub).is_dir()
    assert (tiny_path / "tokenizer" / "vocab.json").is_file()
    assert (tiny_path / "tokenizer" / "merges.txt").read_text().startswith("#version")
    total = sum(f.stat().st_size for f in tiny_path.rglob("*") if f.is_file())
    assert total < 5 * 1024 * 1024
    assert "SMOKE-TEST MODEL" in (tiny_path / "README.md").read_text()


def test_tiny_model_is_deterministic_per_seed(tiny_path, tmp_path):
    weights = "unet/diffusion_pytorch_model.safetensors"
    same = build_tiny_stable_diffusion(tmp_path / "same", seed=0)
    other = build_tiny_stable_diffusion(tmp_path / "other", seed=1)
    assert (same / weights).read_bytes() == (tiny_path / weights).read_bytes()
    assert (same / "text_encoder/model.safetensors").read_bytes() == (tiny_path / "text_encoder/model.safetensors").read_bytes()
    assert (other / weights).read_bytes() != (tiny_path / weights).read_bytes()


def test_loads_offline_like_real_weights(guidance, tiny_path):
    from diffusers.models.attention_processor import AttnProcessor2_0

    assert isinstance(guidance, Guidance)
    assert guidance.resolution == 64  # unet.sample_size 16 x VAE factor 4
    assert guidance.num_train_timesteps == 1000
    assert guidance.dtype == torch.float32 and guidance.device.type == "cpu"
    assert guidance.latent_scale == pytest.approx(0.18215)
    for module in (guidance.unet, guidance.vae, guidance.text_encoder):
        assert not module.training
        assert all(not p.requires_grad for p in module.parameters())
    assert all(isinstance(p, AttnProcessor2_0) for p in guidance.unet.attn_processors.values())
    # SD's noise schedule: scaled_linear betas 0.00085 -> 0.012 over 1000 steps
    betas = torch.linspace(0.00085**0.5, 0.012**0.5, 1000, dtype=torch.float64) ** 2
    expected = torch.cumprod(1 - betas, 0).float()
    torch.testing.assert_close(guidance.alphas_cumprod, expected, rtol=1e-5, atol=1e-7)


def test_encode_prompts_shape_and_cache(guidance):
    emb = guidance.encode_prompts(["a render of a dog", "a render of a dog, side view"])
    assert emb.shape == (2, 77, 32)
    assert not torch.allclose(emb[0], emb[1])
    again = guidance.encode_prompts(["a render of a dog, side view"])
    torch.testing.assert_close(again[0], emb[1])
    assert guidance.unconditional_embedding().shape == (1, 77, 32)


def test_a_full_embedding_cache_still_answers_a_call_mixing_cached_and_new_prompts(guidance):
    """When the bounded cache starts afresh in the middle of a call, the call's cached prompts are still returned
    (they were once dropped before the stack: KeyError)."""
    guidance._embedding_cache.clear()
    filler = [f"a render of thing {i}" for i in range(256)]
    guidance.encode_prompts(filler)
    mixed = guidance.encode_prompts([filler[0], "a render of a new thing", filler[0]])
    fresh = guidance.encode_prompts([filler[0], "a render of a new thing"])
    torch.testing.assert_close(mixed, fresh[[0, 1, 0]])
    assert len(guidance._embedding_cache) <= 256
    guidance._embedding_cache.clear()


def test_an_embedding_first_asked_for_under_autocast_is_cached_as_the_model_computes_it(guidance):
    """An edit under ``autocast_dtype`` asks for the empty prompt's embedding first inside its SDS step's autocast;
    the cache, keyed on the prompt alone, had kept that bfloat16-computed embedding for every later job of the
    worker's guidance, autocast or not."""
    guidance._embedding_cache.clear()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        under_autocast = guidance.encode_prompts(["", "a render of a dog"])
    guidance._embedding_cache.clear()
    torch.testing.assert_close(under_autocast, guidance.encode_prompts(["", "a render of a dog"]), rtol=0, atol=0)
    guidance._embedding_cache.clear()


# ----------------------------------------------------------------- SDS


@pytest.mark.parametrize("t", [20, 980])
def test_sds_gradient_reaches_the_image(guidance, t):
    image = torch.rand(1, 3, 48, 48, generator=torch.Generator().manual_seed(1)).requires_grad_(True)
    emb = guidance.encode_prompts([edit_prompt("a dog wearing big sunglasses", "front")])
    loss, diag = guidance.sds_loss(image, emb, torch.tensor([t]), guidance_scale=100.0,
                                   generator=torch.Generator().manual_seed(0))
    assert loss.ndim == 0
    loss.backward()
    assert image.grad is not None and image.grad.shape == image.shape
    assert torch.isfinite(image.grad).all()
    assert image.grad.abs().sum() > 0
    for key in ("vae_encode_ms", "unet_ms", "sds_ms"):  # host timings
        assert isinstance(diag[key], float)
    for key in ("grad_norm", "w_mean", "t_mean"):  # left on the device, unread: the caller reads them when it reports
        assert isinstance(diag[key], torch.Tensor) and diag[key].ndim == 0 and diag[key].device == guidance.device
    assert float(diag["t_mean"]) == t
    assert float(diag["w_mean"]) == pytest.approx(1 - float(guidance.alphas_cumprod[t]), rel=1e-6)


def test_encoded_renders_are_the_vaes_scaled_latents_of_the_renders_mapped_to_minus_one_to_one(guidance):
    """Renders in [0, 1] reach the VAE resized to the model's resolution and mapped to [-1, 1], as Stable Diffusion
    was trained; their latents are scaled by the VAE's ``scaling_factor`` (the posterior's mean, or its sample from
    the generator given)."""
    images = torch.rand(2, 3, 48, 48, generator=torch.Generator().manual_seed(4))
    x = torch.nn.functional.interpolate(images, size=(guidance.resolution,) * 2, mode="bilinear",
                                        align_corners=False) * 2 - 1
    with torch.no_grad():
        posterior = guidance.vae.encode(x).latent_dist
        sampled = posterior.sample(generator=torch.Generator().manual_seed(5))
    assert guidance.resolution != 48 and guidance.latent_shift == 0.0
    torch.testing.assert_close(guidance.encode_images(images, sample=False), posterior.mean * guidance.latent_scale,
                               rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(guidance.encode_images(images, torch.Generator().manual_seed(5)),
                               sampled * guidance.latent_scale, rtol=1e-5, atol=1e-6)


def test_sds_loss_is_reproducible_with_a_generator(guidance):
    emb = guidance.encode_prompts(["a render of a dog"])
    base = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(2))
    grads = []
    for seed in (0, 0, 1):
        image = base.clone().requires_grad_(True)
        loss, _ = guidance.sds_loss(image, emb, torch.tensor([500]), generator=torch.Generator().manual_seed(seed))
        loss.backward()
        grads.append(image.grad)
    torch.testing.assert_close(grads[0], grads[1])
    assert not torch.allclose(grads[0], grads[2])


@torch.no_grad()
def _expected_sds_grad(guidance, latents, noise, t, cond, scale):
    """(1 - alphā_t)(eps_u + s(eps_c - eps_u) - eps) from the ε-predicting UNet, and (z_t, eps_c)."""
    a = guidance.alphas_cumprod[t].reshape(-1, 1, 1, 1)
    noisy = a.sqrt() * latents + (1 - a).sqrt() * noise
    uncond = guidance.unconditional_embedding().expand(len(t), -1, -1)
    eps_u = guidance.unet(noisy, t, encoder_hidden_states=uncond).sample
    eps_c = guidance.unet(noisy, t, encoder_hidden_states=cond).sample
    return (1 - a) * (eps_u + scale * (eps_c - eps_u) - noise), (noisy, eps_c)


def test_sds_gradient_is_weighted_cfg_residual(guidance):
    """d(loss)/d(latents) == (1 - alphā_t)(eps_u + s(eps_c - eps_u) - eps) / B, computed independently: the mean
    over the batch's views, so batch_size leaves the SDS / regulariser balance alone (a sum had doubled it at 2)."""
    g = torch.Generator().manual_seed(3)
    latents = torch.randn(2, 4, 16, 16, generator=g).requires_grad_(True)
    noise = torch.randn(2, 4, 16, 16, generator=g)
    t = torch.tensor([20, 980])
    cond = guidance.encode_prompts(["a render of a dog, front view", "a render of a cat, back view"])
    scale = 7.5

    loss, _ = guidance.sds_loss_on_latents(latents, cond, t, guidance_scale=scale, noise=noise)
    loss.backward()

    expected, _ = _expected_sds_grad(guidance, latents, noise, t, cond, scale)
    assert expected.abs().max() > 1e-3
    torch.testing.assert_close(latents.grad, expected / 2, rtol=1e-4, atol=1e-5)
    direct, _ = guidance.sds_grad_on_latents(latents, cond, t, guidance_scale=scale, noise=noise)
    torch.testing.assert_close(direct, expected, rtol=1e-4, atol=1e-5)


def test_sds_reports_the_share_of_non_finite_gradient_entries_it_zeroed(guidance, monkeypatch):
    """A float16 UNet overflowing in one of the 4 latent channels: that quarter of the gradient is zeroed, and said
    so (it had been zeroed silently, an everywhere-overflowing UNet making SDS a no-op with a finite loss)."""
    eager = guidance._eager_unet

    def overflowing(sample, timestep, text):
        out = eager(sample, timestep, text).clone()
        out[:, 0] = torch.inf
        return out

    monkeypatch.setattr(guidance, "_eager_unet", overflowing)
    g = torch.Generator().manual_seed(3)
    latents, noise = torch.randn(2, 4, 16, 16, generator=g), torch.randn(2, 4, 16, 16, generator=g)
    grad, diag = guidance.sds_grad_on_latents(latents, guidance.encode_prompts(["a dog"]), [300, 600], noise=noise)
    assert float(diag["nonfinite_fraction"]) == 0.25
    assert not grad[:, 0].any() and grad[:, 1:].abs().min() > 0 and torch.isfinite(grad).all()
    monkeypatch.undo()
    _, healthy = guidance.sds_grad_on_latents(latents, guidance.encode_prompts(["a dog"]), [300, 600], noise=noise)
    assert float(healthy["nonfinite_fraction"]) == 0


def test_sds_rejects_out_of_range_timesteps(guidance):
    emb = guidance.encode_prompts(["a dog"])
    with pytest.raises(ValueError, match=r"^timesteps must lie in \[0, 999\], got \[1000\]$"):
        guidance.sds_grad_on_latents(torch.zeros(1, 4, 16, 16), emb, torch.tensor([1000]))


# ----------------------------------------------------------------- cross-attention


@pytest.mark.parametrize("resolution_filter, size", [(16, 16), (8, 8), (None, 16)])
def test_cross_attention_maps_are_token_distributions(guidance, resolution_filter, size):
    from diffusers.models.attention_processor import AttnProcessor2_0

    image = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(4))
    maps = guidance.cross_attention_maps(image, "a dog wearing a party hat", timestep=200,
                                         resolution_filter=resolution_filter,
                                         generator=torch.Generator().manual_seed(0))
    assert maps.shape == (77, size, size)
    assert (maps >= 0).all()
    torch.testing.assert_close(maps.sum(0), torch.ones(size, size), rtol=0, atol=1e-5)
    # the default SDPA processors are back afterwards
    assert all(isinstance(p, AttnProcessor2_0) for p in guidance.unet.attn_processors.values())


def test_cross_attention_maps_equal_softmax_qk(guidance):
    """Filter 8 selects the mid block's single cross-attention: compare with softmax(QKᵀ/√d) by hand."""
    attn = guidance.unet.mid_block.attentions[0].transformer_blocks[0].attn2
    seen = {}

    def hook(module, args, kwargs):
        seen["x"] = args[0] if args else kwargs["hidden_states"]
        seen["ctx"] = kwargs["encoder_hidden_states"]

    handle = attn.register_forward_pre_hook(hook, with_kwargs=True)
    try:
        image = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(5))
        maps = guidance.cross_attention_maps(image, "a dog", resolution_filter=8,
                                             generator=torch.Generator().manual_seed(0))
    finally:
        handle.remove()
    with torch.no_grad():
        q = attn.to_q(seen["x"])  # (1, 64, C)
        k = attn.to_k(seen["ctx"])  # (1, 77, C)
        heads = attn.heads
        d = q.shape[-1] // heads
        q = q.reshape(1, -1, heads, d).transpose(1, 2)
        k = k.reshape(1, -1, heads, d).transpose(1, 2)
        probs = torch.softmax(q @ k.transpose(-1, -2) / d**0.5, dim=-1).mean(1)[0]  # (64, 77)
    expected = probs.T.reshape(77, 8, 8)
    torch.testing.assert_close(maps, expected, rtol=1e-4, atol=1e-6)


def test_cross_attention_probabilities_recorded_under_a_callers_bf16_autocast_are_the_float32_ones(guidance):
    """The recorded probabilities are softmax(QKᵀ/√d) in float32 of the layer's own queries and keys, whatever autocast
    the caller runs the UNet under: a bf16 one had run the scores' bmm and the softmax in bf16 (maps stored in bf16,
    a pixel's probabilities summing to 1 only within 1e-3)."""
    attn = guidance.unet.mid_block.attentions[0].transformer_blocks[0].attn2
    g = torch.Generator().manual_seed(7)
    x = torch.randn(1, 64, attn.to_q.in_features, generator=g)
    ctx = 3 * torch.randn(1, 77, attn.to_k.in_features, generator=g)
    store = AttentionStore((8, 8), 8)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        CrossAttentionCapture(store)(attn, x, ctx)
        q, k = attn.to_q(x).float(), attn.to_k(ctx).float()  # the layer's, in bf16 under the autocast
    heads = attn.heads
    d = q.shape[-1] // heads
    q = q.reshape(1, -1, heads, d).transpose(1, 2)
    k = k.reshape(1, -1, heads, d).transpose(1, 2)
    expected = torch.softmax(q @ k.transpose(-1, -2) / d**0.5, dim=-1).mean(1).reshape(1, 8, 8, 77)
    (recorded,) = store.maps
    assert recorded.dtype == torch.float32
    torch.testing.assert_close(recorded, expected, rtol=1e-4, atol=1e-6)
    assert float((recorded.sum(-1) - 1).abs().max()) < 1e-5


def test_capture_processor_keeps_the_unet_output(guidance):
    unet = guidance.unet
    g = torch.Generator().manual_seed(6)
    x = torch.randn(1, 4, 16, 16, generator=g)
    ctx = guidance.encode_prompts(["a render of a dog wearing a party hat"])
    t = torch.tensor([200])
    with torch.no_grad():
        reference = unet(x, t, encoder_hidden_states=ctx).sample
        original = unet.attn_processors
        store = AttentionStore((16, 16), None)
        capture = CrossAttentionCapture(store)
        unet.set_attn_processor({n: capture if n.endswith("attn2.processor") else p for n, p in original.items()})
        try:
            captured = unet(x, t, encoder_hidden_states=ctx).sample
        finally:
            unet.set_attn_processor(original)
    assert len(store.maps) == 4  # down 16x16, mid 8x8, two up 16x16 cross-attentions
    torch.testing.assert_close(captured, reference, rtol=1e-4, atol=1e-5)


def test_unknown_attention_resolution_is_an_error(guidance):
    with pytest.raises(ValueError, match="4x4"):
        guidance.cross_attention_maps(torch.rand(1, 3, 64, 64), "a dog", resolution_filter=4)


# ----------------------------------------------------------------- tokens


def test_token_spans_phrase_repeats_and_subwords(guidance):
    prompt = "a dog wearing a party hat"
    # <start> a dog wearing a party hat <end> ...
    assert guidance.token_spans(prompt, ["party hat"]) == [5, 6]
    assert guidance.token_spans(prompt, ["a"]) == [1, 4]
    assert guidance.token_spans(prompt, ["dog", "hat"]) == [2, 6]
    n = len(guidance.tokenizer.tokenize("zebra"))
    assert n > 1  # not in the tiny vocabulary: byte-level sub-tokens
    assert guidance.token_spans("a zebra with a hat", ["zebra"]) == list(range(2, 2 + n))
    assert guidance.content_token_indices(prompt) == [1, 2, 3, 4, 5, 6]
    with pytest.raises(ValueError, match="sunglasses"):
        guidance.token_spans(prompt, ["sunglasses"])


def test_token_spans_match_whole_words_of_the_text_before_its_view_word(guidance):
    """Sub-words had matched ("shade" inside "lampshade", "hat" inside "partyhat"), and so had the appended view word
    ("back" in ", back view"): the edit map then took in the object or the view word's attention."""
    tokens = guidance.tokenizer.tokenize("a lampshade with a red shade")
    assert tokens[5:9] == tokens[-4:]  # both shades are the same sub-tokens: only the word start tells them apart
    last_shade = list(range(len(tokens) - 3, len(tokens) + 1))  # positions count the start token
    assert guidance.token_spans("a lampshade with a red shade", ["shade"]) == last_shade
    with pytest.raises(ValueError, match="'hat' does not occur in the prompt 'a partyhat'"):
        guidance.token_spans("a partyhat", ["hat"])
    prompt = edit_prompt("a dog with a saddle on its back", "back")
    assert guidance.tokenizer.tokenize(prompt).count("back</w>") == 2
    back = guidance.tokenizer.tokenize(prompt).index("back</w>") + 1
    assert guidance.token_spans(prompt, ["back"]) == [back]
    with pytest.raises(ValueError, match="'view' does not occur"):
        guidance.token_spans(prompt, ["view"])
    assert guidance.token_spans("a dog, back view", ["dog"]) == [2]


def test_a_prompt_longer_than_the_text_encoder_reads_is_refused_not_cut_off(guidance):
    """It was cut at 77 tokens: the edit guided by the front of it, and an edit word beyond the cut not found
    until the refinement looked for it."""
    long = "a dog wearing " + " ".join(["zebra"] * 20)  # "zebra" is byte-level sub-tokens in the tiny vocabulary
    n = len(guidance.tokenizer(long).input_ids)
    assert n > guidance.max_length == TEXT_ENCODER_TOKENS
    assert tokens_at_least(long) <= guidance.max_length  # the API's lower bound lets it through; this does not
    for refused in (lambda: guidance.encode_prompts([long]), lambda: guidance.token_spans(long, ["dog"])):
        with pytest.raises(ValueError, match=rf"the prompt .* is {n} tokens; the text encoder of .* reads 77, its "
                                             "start and end tokens included: shorten it"):
            refused()
    fits = "a dog wearing " + " ".join(["hat"] * (guidance.max_length - 5))  # 77 with its start and end
    assert len(guidance.tokenizer(fits).input_ids) == guidance.max_length
    assert guidance.encode_prompts([fits]).shape[1] == guidance.max_length


@pytest.mark.parametrize("text", ["a dog wearing a party hat", "a zebra's 3D-printed hat!!", "a_b, c.d 42 overhead view",
                                  "a render of a microphone wearing big sunglasses, overhead view",
                                  "a cafe\u0301 hat"])  # a decomposed accent: one piece once NFC, as CLIP reads it
def test_the_apis_token_count_is_a_lower_bound_of_the_clip_tokenizers(guidance, text):
    assert tokens_at_least(text) <= len(guidance.tokenizer(text).input_ids)


@pytest.mark.parametrize("text", ["\u0395\u039d\u0391\u03a3 \u03a3\u039a\u03a5\u039b\u039f\u03a3 wearing a hat",
                                  "a \U0001f3a9 on a dog's mic, front view", "a cafe\u0301 hat!! 3D", "\u0130stanbul"])
def test_the_apis_pieces_are_the_clip_tokenizers_words(guidance, text):
    """The tokenizer lowers character by character: a word-final capital sigma had been the final \u03c2 in the
    API's pieces and \u03c3 in the model's, the API accepting an edit word the refinement refused."""
    backend = guidance.tokenizer.backend_tokenizer
    normal = backend.normalizer.normalize_str(text)
    words = [normal[start:end] for _, (start, end) in backend.pre_tokenizer.pre_tokenize_str(normal)]  # not byte-level
    assert clip_pieces(text) == words


@pytest.mark.parametrize("prompt, word, said", [
    ("\u4e00\u53ea\u6234\u5e3d\u5b50\u7684\u72d7", "\u5e3d\u5b50",  # no spaces: one word to CLIP
     "the model reads '\u4e00\u53ea\u6234\u5e3d\u5b50\u7684\u72d7' as one word (text written without spaces, as "
     "Chinese is, is one word to it): name all of it, or separate the edit word from the words around it with spaces "
     "in the prompt"),
    ("a dog\u2019s hat", "dog's hat",
     "its apostrophes and quotes must be the prompt's own (\u2019 is not ', \u201d is not \")"),
    ("a dog with a hat", "zebra", ""),
    ("a mic wearing Sunglasses", "glasses", "'glasses' is part of the word 'sunglasses'"),  # no text without spaces
    ("\u307c\u3046\u3057\u3092\u304b\u3076\u3063\u305f\u3044\u306c", "\u307c\u3046\u3057",  # kana
     "the model reads '\u307c\u3046\u3057\u3092\u304b\u3076\u3063\u305f\u3044\u306c' as one word (text written without "
     "spaces, as Chinese is, is one word to it): name all of it, or separate the edit word from the words around it "
     "with spaces in the prompt"),
])
def test_an_edit_word_not_found_is_told_the_likely_cause(prompt, word, said):
    """Text without spaces (Chinese) is one word to CLIP's tokenizer, and a curly apostrophe no straight one: both
    had been refused only as "does not occur ... as whole words", which does not say what to change. An English word
    inside a longer one ("glasses" in "sunglasses") had been told about text without spaces."""
    from voxe_core.guidance.prompts import check_edit_words_name_an_edit

    with pytest.raises(ValueError) as refused:
        check_edit_words_name_an_edit(prompt, [word])
    assert str(refused.value) == f"edit word {word!r} does not occur in the prompt {prompt!r} as whole words" + (
        f": {said}" if said else "")
    check_edit_words_name_an_edit("\u4e00\u53ea \u6234 \u5e3d\u5b50 \u7684 \u72d7", ["\u5e3d\u5b50"])


# ----------------------------------------------------------------- missing weights


def test_missing_hub_model_names_id_and_local_folder():
    with pytest.raises(ModelNotAvailableError) as info:
        StableDiffusionGuidance.from_pretrained("some-org/does-not-exist", local_files_only=True)
    message = str(info.value)
    assert "some-org/does-not-exist" in message
    assert "local folder" in message
    assert isinstance(info.value, RuntimeError)


def test_a_hub_id_the_hub_does_not_have_is_told_to_be_checked_not_that_it_is_offline(monkeypatch):
    """Downloads allowed, a mistyped id had been told "not available offline: download them once with `huggingface-cli
    download <the typo>`", though the hub had been asked and had no such model. (The hub's answer as diffusers
    raises it.)"""
    from diffusers import UNet2DConditionModel

    def not_on_the_hub(model, *_args, **_kwargs):
        raise OSError(f"{model} is not a local folder and is not a valid model identifier listed on "
                      "'https://huggingface.co/models'")

    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    monkeypatch.setattr(UNet2DConditionModel, "from_pretrained", not_on_the_hub)
    with pytest.raises(ModelNotAvailableError) as info:
        StableDiffusionGuidance.from_pretrained("CompVis/stable-diffusion-v1-5", local_files_only=False)
    message = str(info.value)
    assert message.startswith("Stable Diffusion weights 'CompVis/stable-diffusion-v1-5' could not be fetched from the "
                              "Hugging Face hub: check the model id")
    assert "offline" not in message and "not a valid model identifier" in message
    with pytest.raises(ModelNotAvailableError, match="'CompVis/stable-diffusion-v1-5' are not available offline"):
        StableDiffusionGuidance.from_pretrained("CompVis/stable-diffusion-v1-5", local_files_only=True)


def test_offline_env_makes_local_files_only_the_default(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(ModelNotAvailableError, match="some-org/also-missing"):
        StableDiffusionGuidance.from_pretrained("some-org/also-missing")


def test_incomplete_local_folders_are_reported(tiny_path, tmp_path):
    with pytest.raises(ModelNotAvailableError, match="local folder"):
        StableDiffusionGuidance.from_pretrained(str(tmp_path / "nowhere"), local_files_only=True)
    no_unet = tmp_path / "no_unet"
    shutil.copytree(tiny_path, no_unet)
    shutil.rmtree(no_unet / "unet")
    with pytest.raises(ModelNotAvailableError, match="no_unet"):
        StableDiffusionGuidance.from_pretrained(str(no_unet), local_files_only=True)
    # transformers 5 silently builds an empty tokenizer for a missing folder
    no_tok = tmp_path / "no_tokenizer"
    shutil.copytree(tiny_path, no_tok)
    shutil.rmtree(no_tok / "tokenizer")
    with pytest.raises(ModelNotAvailableError, match="tokenizer"):
        StableDiffusionGuidance.from_pretrained(str(no_tok), local_files_only=True)


@pytest.mark.parametrize("removed, lacks", [
    ("vae", "vae/config.json, weights in vae/"),
    ("unet/diffusion_pytorch_model.safetensors", "weights in unet/"),
    ("text_encoder/config.json", "text_encoder/config.json"),
    ("scheduler", "scheduler/scheduler_config.json"),
    ("tokenizer/merges.txt", "tokenizer/merges.txt"),
])
def test_a_local_folder_missing_a_part_is_reported_naming_that_part(tiny_path, tmp_path, capfd, removed, lacks):
    """The libraries had named no part: "no file named config.json found in directory <the model's folder>" for a
    missing vae/, "no file named diffusion_pytorch_model.bin" for the UNet's missing safetensors, and without
    text_encoder/config.json a default 512-wide encoder was built and failed on the weights' shapes after a table of
    every layer on stderr ("You set `ignore_mismatched_sizes` to `False`")."""
    folder = tmp_path / "partial"
    shutil.copytree(tiny_path, folder)
    path = folder / removed
    shutil.rmtree(path) if path.is_dir() else path.unlink()
    capfd.readouterr()
    with pytest.raises(ModelNotAvailableError, match=rf"'.*partial' are not available.*the folder lacks {re.escape(lacks)}$"):
        StableDiffusionGuidance.from_pretrained(str(folder), local_files_only=True)
    assert "MISMATCH" not in capfd.readouterr().err


def test_a_folder_holding_only_a_variants_weights_is_neither_whole_nor_loaded_unnamed(tiny_path, tmp_path):
    """What a download of the fp16 files alone leaves: diffusers_model_present had counted it whole (a worker offered
    it) and loading failed with "no file named diffusion_pytorch_model.bin found in directory <the model's folder>"."""
    from voxe_core.guidance.loading import diffusers_model_present

    folder = tmp_path / "fp16_only"
    shutil.copytree(tiny_path, folder)
    weights = folder / "unet" / "diffusion_pytorch_model.safetensors"
    weights.rename(weights.with_suffix(".fp16.safetensors"))
    assert not diffusers_model_present(str(folder))
    with pytest.raises(ModelNotAvailableError, match=re.escape(
            "the folder lacks weights in unet/ (only diffusion_pytorch_model.fp16.safetensors: a variant's, which "
            "loading does not read)")):
        StableDiffusionGuidance.from_pretrained(str(folder), local_files_only=True)
    assert diffusers_model_present(str(tiny_path))


def test_a_folder_without_model_index_is_present_as_it_is_loaded(tiny_path, tmp_path, monkeypatch):
    """Loading reads the components alone, but diffusers_model_present required model_index.json: the workers
    reported missing (and refused jobs for) a folder, or a cached snapshot, the CLI loaded. One rule now."""
    import huggingface_hub.constants

    from voxe_core.guidance.loading import diffusers_model_present, load_stable_diffusion

    folder = tmp_path / "no_index"
    shutil.copytree(tiny_path, folder)
    (folder / "model_index.json").unlink()
    assert diffusers_model_present(str(folder))
    assert load_stable_diffusion(str(folder), torch.float32, local_files_only=True)[0] is not None
    hub = tmp_path / "hub"
    snapshot = hub / "models--owner--no-index" / "snapshots" / ("0" * 40)
    shutil.copytree(folder, snapshot)
    (hub / "models--owner--no-index" / "refs").mkdir()
    (hub / "models--owner--no-index" / "refs" / "main").write_text("0" * 40)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(hub))
    assert diffusers_model_present("owner/no-index")
    shutil.rmtree(folder / "vae")  # a part loading reads is still needed
    assert not diffusers_model_present(str(folder))


@pytest.mark.parametrize("revision", [None, "v2"])
def test_a_cached_snapshot_missing_a_part_is_told_which_before_loading_as_a_folder_is(tiny_path, tmp_path,
                                                                                      monkeypatch, revision):
    """A hub id whose cached snapshot lacks unet/ (a download cut short), loaded offline, had been told by diffusers
    "owner/sd does not appear to have a file named config.json", naming no part, where a local folder's are named
    before loading: the snapshot gets the same check, its download advised at the revision loaded."""
    from huggingface_hub import constants

    from diffusers import UNet2DConditionModel

    from voxe_core.guidance.loading import diffusers_model_present, load_stable_diffusion

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "cache"))
    repo = tmp_path / "cache" / "models--owner--sd"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / (revision or "main")).write_text("abc123")
    snapshot = repo / "snapshots" / "abc123"
    shutil.copytree(tiny_path, snapshot)
    shutil.rmtree(snapshot / "unet")
    (snapshot / "vae" / "diffusion_pytorch_model.safetensors").unlink()
    monkeypatch.setattr(UNet2DConditionModel, "from_pretrained", lambda *a, **k: pytest.fail("loading was tried"))
    with pytest.raises(ModelNotAvailableError) as missing:
        load_stable_diffusion("owner/sd", torch.float32, local_files_only=True, revision=revision)
    download = download_command("owner/sd", revision=revision)
    assert f"not available offline: download them once with `{download}` on a machine" in str(missing.value)
    assert str(missing.value).endswith(f"Underlying error: FileNotFoundError: its snapshot in the cache ({snapshot}) "
                                       "lacks unet/config.json, weights in unet/, weights in vae/")
    assert not diffusers_model_present("owner/sd", revision)


def test_a_cached_model_whose_weights_cannot_be_read_is_told_to_be_fetched_again(tiny_path, tmp_path, monkeypatch):
    """A hub id whose files are all in the cache, one of them damaged (the UNet's weights cut short: diffusers'
    "Unable to load weights from checkpoint file"), had been told "could not be fetched from the Hugging Face hub:
    check the model id" (downloads allowed) or "not available offline: download them once" (offline), though the model
    is cached and nothing was to be fetched."""
    from huggingface_hub import constants

    from diffusers import UNet2DConditionModel

    from voxe_core.guidance.loading import diffusers_model_present, load_stable_diffusion

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "cache"))
    repo = tmp_path / "cache" / "models--owner--sd"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text("abc123")
    snapshot = repo / "snapshots" / "abc123"
    shutil.copytree(tiny_path, snapshot)
    weights = next((snapshot / "unet").glob("*.safetensors"))
    weights.write_bytes(weights.read_bytes()[:100])
    assert diffusers_model_present("owner/sd")
    told = ("Stable Diffusion weights 'owner/sd' are in the Hugging Face cache (HF_HOME) but could not be read: a file "
            "of them is damaged (a download cut short, a disk error) or not this model's; download them again with "
            f"`{download_command('owner/sd')} --force-download`. Underlying error: ")

    def damaged(*args, **kwargs):  # (diffusers' answer for that file, loading it from the cache)
        raise OSError(f"Unable to load weights from checkpoint file for '{weights}'")

    monkeypatch.setattr(UNet2DConditionModel, "from_pretrained", damaged)
    with pytest.raises(ModelNotAvailableError) as offline:
        load_stable_diffusion("owner/sd", torch.float32, local_files_only=True)
    assert str(offline.value).startswith(told) and str(weights) in str(offline.value)
    with pytest.raises(ModelNotAvailableError) as online:
        load_stable_diffusion("owner/sd", torch.float32, local_files_only=False)
    assert str(online.value).startswith(told) and "check the model id" not in str(online.value)
    (repo / "refs" / "v2").write_text("abc123")  # a revision loaded: its download is told, not main's again
    with pytest.raises(ModelNotAvailableError) as revision:
        load_stable_diffusion("owner/sd", torch.float32, local_files_only=True, revision="v2")
    assert str(revision.value).startswith(told.replace(download_command("owner/sd"),
                                                       download_command("owner/sd", revision="v2")))
    assert "hf download owner/sd --revision v2 --include " in str(revision.value)


def test_a_single_file_checkpoint_is_told_to_be_converted_not_missing(tmp_path):
    """A single-file Stable Diffusion checkpoint (what many tools save) had been told "no folder <the file>"."""
    checkpoint = tmp_path / "v1-5-pruned.safetensors"
    checkpoint.write_bytes(b"weights")
    with pytest.raises(ModelNotAvailableError, match=rf"NotADirectoryError: {re.escape(str(checkpoint))} is a file, not "
                                                     r"a folder: a single-file checkpoint .* convert it to the diffusers"
                                                     r" layout first") as raised:
        StableDiffusionGuidance.from_pretrained(str(checkpoint), local_files_only=True)
    assert "no folder" not in str(raised.value)


def test_a_prompt_is_counted_against_what_the_text_encoder_reads_whatever_its_tokenizer_says(guidance):
    """A tokenizer config without model_max_length says 1e30: the worker's check before a fit had then passed an
    82-token prompt the guidance refuses at 77, after the fit. Both read the encoder's positions."""
    from voxe_core.guidance.prompts import check_prompt_tokens, tokens_read

    tokenizer, positions = guidance.tokenizer, guidance.text_encoder.config.max_position_embeddings
    assert tokens_read(tokenizer, positions) == guidance.max_length == 77
    long = "a mic wearing " + "zyxwv " * 14 + "sunglasses"
    original = tokenizer.model_max_length
    try:
        tokenizer.model_max_length = int(1e30)
        assert tokens_read(tokenizer, positions) == 77
        with pytest.raises(ValueError, match="is 82 tokens as the model's tokenizer reads it; its text encoder reads 77"):
            check_prompt_tokens(long, tokenizer, tokens_read(tokenizer, positions))
    finally:
        tokenizer.model_max_length = original
    check_prompt_tokens("a mic wearing big sunglasses", tokenizer, tokens_read(tokenizer, positions))


def test_a_home_relative_folder_is_a_folder_not_a_hub_id(tiny_path, tmp_path, monkeypatch):
    """VOXE_SDS_MODEL=~/models/sd had been read as a hub id: reported missing, with `hf download ~/models/sd`."""
    from voxe_core.guidance.loading import load_stable_diffusion, model_file

    monkeypatch.setenv("HOME", str(tmp_path))
    shutil.copytree(tiny_path, tmp_path / "models" / "sd")
    assert model_file("~/models/sd", "model_index.json") is not None
    assert load_stable_diffusion("~/models/sd", torch.float32, local_files_only=True)[0] is not None
    with pytest.raises(ModelNotAvailableError, match=f"no folder {tmp_path / 'models' / 'gone'}"):
        load_stable_diffusion("~/models/gone", torch.float32, local_files_only=True)


def test_damaged_weights_are_reported_naming_the_model(tiny_path, tmp_path):
    damaged = tmp_path / "damaged_text_encoder"
    shutil.copytree(tiny_path, damaged)
    (damaged / "text_encoder" / "model.safetensors").write_bytes(b"trunc")  # a SafetensorError underneath
    with pytest.raises(ModelNotAvailableError, match="'.*damaged_text_encoder' are not available.*SafetensorError"):
        StableDiffusionGuidance.from_pretrained(str(damaged), local_files_only=True)


@pytest.mark.parametrize("config, damage, fault", [
    ("vae/config.json", lambda config: None, r"vae/config.json is not a JSON object: it holds null"),
    ("text_encoder/config.json", lambda config: [], r"text_encoder/config.json is not a JSON object: it holds \[\]"),
    ("text_encoder/config.json", lambda config: {**config, "hidden_act": "nope"},
     r"text_encoder/config.json names hidden_act 'nope', an activation this transformers \(.*\) does not have"),
])
def test_a_component_config_the_libraries_cannot_build_from_is_reported_naming_the_model(tiny_path, tmp_path, config,
                                                                                        damage, fault):
    """These had escaped loading as a TypeError or KeyError naming neither the model nor the file."""
    folder = tmp_path / "damaged_config"
    shutil.copytree(tiny_path, folder)
    (folder / config).write_text(json.dumps(damage(json.loads((folder / config).read_text()))))
    with pytest.raises(ModelNotAvailableError, match=f"'.*damaged_config' are not available.*{fault}"):
        StableDiffusionGuidance.from_pretrained(str(folder), local_files_only=True)


@pytest.mark.parametrize("damaged, content", [("vocab.json", b"{bad"), ("merges.txt", b"garbage"),
                                               ("vocab.json", b'{"a": 0}')])
def test_unreadable_tokenizer_files_are_reported_naming_the_model(tiny_path, tmp_path, damaged, content):
    """The tokenizers library raises a bare Exception ("Error while initializing BPE") for these: it had surfaced as
    the job's failure, not as a damaged model."""
    folder = tmp_path / "damaged_tokenizer"
    shutil.copytree(tiny_path, folder)
    (folder / "tokenizer" / damaged).write_bytes(content)
    with pytest.raises(ModelNotAvailableError, match="'.*damaged_tokenizer' are not available.*tokenizer files unreadable"):
        StableDiffusionGuidance.from_pretrained(str(folder), local_files_only=True)


@pytest.mark.parametrize("error", ["DefaultCPUAllocator: can't allocate memory: you tried to allocate 3463 bytes",
                                   "CUDA out of memory"])
def test_a_machine_out_of_memory_while_loading_is_not_reported_as_a_missing_model(tiny_path, monkeypatch, error):
    import torch
    from diffusers import UNet2DConditionModel

    def short_of_memory(*_args, **_kwargs):
        raise (torch.OutOfMemoryError if error.startswith("CUDA") else RuntimeError)(error)

    monkeypatch.setattr(UNet2DConditionModel, "from_pretrained", short_of_memory)
    with pytest.raises(RuntimeError, match=error) as raised:
        StableDiffusionGuidance.from_pretrained(str(tiny_path), local_files_only=True)
    assert not isinstance(raised.value, ModelNotAvailableError)


def test_default_model_ids():
    assert SDS_MODEL_ID == "stabilityai/stable-diffusion-2-base"
    assert ATTENTION_MODEL_ID == "CompVis/stable-diffusion-v1-4"


# ----------------------------------------------------------------- prompts


def test_edit_prompt():
    assert edit_prompt("a dog wearing big sunglasses") == "a render of a dog wearing big sunglasses"
    assert edit_prompt("a dog", "side") == "a render of a dog, side view"
    assert edit_prompt("A render of a dog.", "front") == "A render of a dog, front view"
    assert edit_prompt("  a   yarn doll of a dog ") == "a render of a yarn doll of a dog"
    assert edit_prompt("a rendered dog") == "a render of a rendered dog"
    with pytest.raises(ValueError):
        edit_prompt("   ")
    with pytest.raises(ValueError):
        edit_prompt("a dog", "top")


@pytest.mark.parametrize(
    "elevation, azimuth, word",
    [
        (10, 0, "front"), (10, 45, "front"), (10, -45, "front"), (10, 315, "front"),
        (10, 46, "side"), (10, 90, "side"), (10, 270, "side"), (10, -100, "side"),
        (10, 135, "back"), (10, 180, "back"), (10, -170, "back"), (10, 540, "back"),
        (60, 0, "front"), (61, 180, "overhead"), (75, 90, "overhead"),
    ],
)
def test_view_word(elevation, azimuth, word):
    assert view_word(elevation, azimuth) == word


def test_half_precision_model_returns_float32_gradients(tiny_path):
    """The CUDA default is fp16; bf16 on CPU exercises the same casts (UNet in model dtype, grad in fp32)."""
    g = StableDiffusionGuidance.from_pretrained(str(tiny_path), dtype=torch.bfloat16, local_files_only=True)
    assert all(p.dtype == torch.bfloat16 for p in g.unet.parameters())
    assert all(p.dtype == torch.bfloat16 for p in g.text_encoder.parameters())
    latents = torch.randn(1, 4, 16, 16, generator=torch.Generator().manual_seed(7))
    grad, _ = g.sds_grad_on_latents(latents, g.encode_prompts(["a dog"]), torch.tensor([300]),
                                    generator=torch.Generator().manual_seed(0))
    assert grad.dtype == torch.float32 and torch.isfinite(grad).all()
    image = torch.rand(1, 3, 64, 64).requires_grad_(True)
    loss, _ = g.sds_loss(image, g.encode_prompts(["a dog"]), torch.tensor([300]),
                         generator=torch.Generator().manual_seed(0))
    assert loss.dtype == torch.float32
    loss.backward()
    assert image.grad.dtype == torch.float32 and torch.isfinite(image.grad).all() and image.grad.abs().sum() > 0


# ----------------------------------------------------------------- prediction types
def _reparameterised_guidance(tiny_path, kind: str) -> StableDiffusionGuidance:
    """The tiny model turned ``kind``-predicting: its UNet's ε output ε_θ is rewritten as v = √ᾱ·ε_θ − √(1−ᾱ)·x̂_0
    (``"v_prediction"``) or as x̂_0 = (z_t − √(1−ᾱ)·ε_θ) / √ᾱ (``"sample"``).

    ε recovered from it must be ε_θ exactly, so its SDS gradient must be the ε model's.
    """
    from diffusers import DDIMScheduler

    from voxe_core.guidance.loading import load_stable_diffusion

    unet, vae, text_encoder, tokenizer, scheduler = load_stable_diffusion(str(tiny_path), torch.float32, True)
    kind_scheduler = DDIMScheduler.from_config(scheduler.config, prediction_type=kind)
    alphas = kind_scheduler.alphas_cumprod.float()

    def as_kind(module, args, kwargs, output):
        noisy, t = args[0], args[1]
        # In float64: x̂_0 divides by √ᾱ (0.07 at t = 900), which would amplify float32 rounding past the tolerance.
        a = alphas[t.long()].double().reshape(-1, 1, 1, 1)
        eps = output.sample.double()
        x0 = (noisy.double() - (1 - a).sqrt() * eps) / a.sqrt()
        rewritten = a.sqrt() * eps - (1 - a).sqrt() * x0 if kind == "v_prediction" else x0
        return type(output)(sample=rewritten.to(output.sample.dtype))

    unet.register_forward_hook(as_kind, with_kwargs=True)
    return StableDiffusionGuidance(unet, vae, text_encoder, tokenizer, kind_scheduler, model_id=f"tiny-{kind}")


@pytest.mark.parametrize("kind", ["v_prediction", "sample"])
def test_v_and_sample_outputs_are_converted_to_epsilon_for_sds(guidance, tiny_path, kind):
    from voxe_core.guidance.sds import epsilon_from_output

    kind_guidance = _reparameterised_guidance(tiny_path, kind)
    assert (guidance.prediction_type, kind_guidance.prediction_type) == ("epsilon", kind)
    g = torch.Generator().manual_seed(5)
    latents = torch.randn(2, 4, 16, 16, generator=g)
    noise = torch.randn(2, 4, 16, 16, generator=g)
    t = torch.tensor([50, 900])
    cond = guidance.encode_prompts(["a render of a dog, front view", "a render of a cat, side view"])
    scale = 7.5
    expected, (noisy, eps_c) = _expected_sds_grad(guidance, latents, noise, t, cond, scale)  # the ε model's: exact
    with torch.no_grad():
        raw = kind_guidance.unet(noisy, t, encoder_hidden_states=cond).sample
    assert (raw - eps_c).abs().max() > 0.1  # read as ε, the raw output would give another gradient

    # The conversion cancels terms of the raw output's size times its factor in ε̂ (√ᾱ for v, √ᾱ / √(1−ᾱ) for x̂_0):
    # float32 rounding of the raw output, so scaled and by the guidance, is what the comparison can resolve; a wrong
    # conversion is off by > 0.1. (With z_t = 0 the conversion is that factor times the raw output.)
    a = guidance.alphas_cumprod[t].reshape(-1, 1, 1, 1)
    scaled = epsilon_from_output(raw, torch.zeros_like(raw), a, kind)
    atol = 8 * scale * torch.finfo(torch.float32).eps * float(scaled.abs().max())
    grad, _ = kind_guidance.sds_grad_on_latents(latents, cond, t, guidance_scale=scale, noise=noise)
    torch.testing.assert_close(grad, expected, rtol=1e-4, atol=atol)
    x = latents.clone().requires_grad_(True)
    loss, _ = kind_guidance.sds_loss_on_latents(x, cond, t, guidance_scale=scale, noise=noise)
    loss.backward()
    torch.testing.assert_close(x.grad, expected / len(x), rtol=1e-4, atol=atol)  # the surrogate: the batch's mean


def test_epsilon_from_output_inverts_the_v_and_sample_parameterisations():
    from voxe_core.guidance.sds import epsilon_from_output

    g = torch.Generator().manual_seed(0)
    z, eps = torch.randn(3, 4, generator=g), torch.randn(3, 4, generator=g)
    a = torch.tensor([0.999, 0.5, 0.002])[:, None]
    noisy = a.sqrt() * z + (1 - a).sqrt() * eps
    v = a.sqrt() * eps - (1 - a).sqrt() * z
    torch.testing.assert_close(epsilon_from_output(v, noisy, a, "v_prediction"), eps)
    torch.testing.assert_close(epsilon_from_output(z, noisy, a, "sample"), eps, rtol=1e-4, atol=1e-4)
    assert epsilon_from_output(eps, noisy, a, "epsilon") is eps


def test_unknown_prediction_type_is_refused_naming_the_model(tiny_path):
    from diffusers import DDIMScheduler

    from voxe_core.guidance.loading import load_stable_diffusion

    unet, vae, text_encoder, tokenizer, scheduler = load_stable_diffusion(str(tiny_path), torch.float32, True)
    flow = DDIMScheduler.from_config(scheduler.config, prediction_type="flow_prediction")
    with pytest.raises(ValueError, match=r"the scheduler of org/flow-model predicts 'flow_prediction'; SDS here "
                                         r"supports prediction_type 'epsilon', 'v_prediction', 'sample'"):
        StableDiffusionGuidance(unet, vae, text_encoder, tokenizer, flow, model_id="org/flow-model")


@pytest.mark.parametrize("change, refusal", [
    ({"in_channels": 9}, r"the UNet of org/other-model maps 9 channels to 4, its VAE's latents have 4: not a "
                         r"text-to-image Stable Diffusion"),
    ({"addition_embed_type": "text_time", "addition_time_embed_dim": 8, "projection_class_embeddings_input_dim": 56},
     r"the UNet of org/other-model needs conditioning besides the text \(addition_embed_type='text_time': SD-XL's"),
    ({"cross_attention_dim": 64}, r"the UNet of org/other-model reads text embeddings 64 wide \(cross_attention_dim "
                                  r"64\), its text encoder gives 32: the parts are of different models"),
])
def test_a_unet_sds_cannot_drive_is_refused_naming_the_model(tiny_path, change, refusal):
    """An inpainting UNet, an SD-XL one or one of another text width had loaded and failed only at the first SDS
    step, with a shape error or a TypeError naming no model."""
    from diffusers import UNet2DConditionModel

    from voxe_core.guidance.loading import load_stable_diffusion

    _, vae, text_encoder, tokenizer, scheduler = load_stable_diffusion(str(tiny_path), torch.float32, True)
    config = {key: value for key, value in UNet2DConditionModel.load_config(str(tiny_path / "unet")).items()
              if not key.startswith("_")}
    unet = UNet2DConditionModel(**{**config, **change})
    with pytest.raises(ValueError, match=refusal):
        StableDiffusionGuidance(unet, vae, text_encoder, tokenizer, scheduler, model_id="org/other-model")


# ----------------------------------------------------------------- first-use downloads
def test_a_download_is_announced_with_its_size_and_nothing_local_is(tiny_path, tmp_path, monkeypatch):
    from voxe_core.guidance.loading import download_notice

    from huggingface_hub import constants

    # huggingface_hub reads HF_HUB_CACHE once at import; the cache it looks in at call time is this constant.
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "empty-cache"))  # nothing of the hub is cached
    sizes = {"owner/sd": 5_210_000_000}
    assert download_notice("owner/sd", False, sizes.get) == "downloading owner/sd (5.2 GB)"
    assert download_notice("owner/other", False, sizes.get) == "downloading owner/other (size unknown)"
    assert download_notice("owner/sd", True, sizes.get) is None  # offline: nothing will be fetched
    assert download_notice(str(tiny_path), False, sizes.get) is None  # a local folder is never downloaded
    # A cached hub id is read from the cache: no notice; a download cut short goes on, announced.
    snapshot = tmp_path / "empty-cache" / "models--owner--sd" / "snapshots" / "abc123"
    (tmp_path / "empty-cache" / "models--owner--sd" / "refs").mkdir(parents=True)
    (tmp_path / "empty-cache" / "models--owner--sd" / "refs" / "main").write_text("abc123")
    shutil.copytree(tiny_path, snapshot)
    assert download_notice("owner/sd", False, sizes.get) is None
    (snapshot / "unet" / "diffusion_pytorch_model.safetensors").unlink()
    assert download_notice("owner/sd", False, sizes.get) == "downloading owner/sd (5.2 GB)"


def test_a_revision_not_cached_is_announced_though_main_is_cached(tiny_path, tmp_path, monkeypatch):
    """download_notice looked at main's snapshot whatever the revision loading asked for: main cached, a load of
    revision "fp32-fix" downloaded the whole model without a word. The size asked is that revision's too."""
    from huggingface_hub import HfApi, constants

    from diffusers import UNet2DConditionModel

    from voxe_core.guidance.loading import download_notice, load_stable_diffusion

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "cache"))
    repo = tmp_path / "cache" / "models--owner--sd"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text("abc123")
    shutil.copytree(tiny_path, repo / "snapshots" / "abc123")
    sizes = {"owner/sd": 5_210_000_000}
    assert download_notice("owner/sd", False, sizes.get) is None
    assert download_notice("owner/sd", False, sizes.get, revision="fp32-fix") == "downloading owner/sd (5.2 GB)"
    assert download_notice("owner/sd", False, sizes.get, revision="abc123") is None  # the cached commit itself
    asked = []

    def model_info(self, model, revision=None, files_metadata=False):
        asked.append(revision)
        raise OSError("the hub is not reached in tests")

    def from_pretrained(*args, **kwargs):
        raise OSError("the hub is not reached in tests")

    monkeypatch.setattr(HfApi, "model_info", model_info)
    monkeypatch.setattr(UNet2DConditionModel, "from_pretrained", from_pretrained)
    heard = []
    with pytest.raises(ModelNotAvailableError):
        load_stable_diffusion("owner/sd", torch.float32, local_files_only=False, revision="fp32-fix",
                              on_message=heard.append)
    assert heard == ["downloading owner/sd (size unknown)"]
    assert asked == ["fp32-fix"]


def test_a_downloads_announced_size_is_of_the_files_loading_fetches_not_the_whole_repository(monkeypatch):
    """The hub's listing of CompVis/stable-diffusion-v1-4 (its sizes, rounded): its single-file checkpoints, fp16,
    non-EMA and Flax weights and safety checker had been counted too, "(30.6 GB)" announced for a load that fetches
    4.3 GB."""
    from types import SimpleNamespace

    from huggingface_hub import HfApi

    from voxe_core.guidance.loading import download_notice

    listing = {"model_index.json": 541, "sd-v1-4.ckpt": 4_265_380_512, "sd-v1-4-full-ema.ckpt": 7_703_807_346,
               "scheduler/scheduler_config.json": 313, "tokenizer/vocab.json": 1_059_962, "tokenizer/merges.txt": 524_619,
               "tokenizer/special_tokens_map.json": 472, "tokenizer/tokenizer_config.json": 806,
               "text_encoder/config.json": 592, "text_encoder/model.safetensors": 492_265_874,
               "text_encoder/pytorch_model.bin": 492_305_335, "text_encoder/model.fp16.safetensors": 246_144_152,
               "unet/config.json": 743, "unet/diffusion_pytorch_model.safetensors": 3_438_167_534,
               "unet/diffusion_pytorch_model.bin": 3_438_354_725, "unet/diffusion_pytorch_model.fp16.safetensors":
               1_719_125_304, "unet/diffusion_pytorch_model.non_ema.bin": 3_438_354_725,
               "unet/diffusion_flax_model.msgpack": 3_438_167_536, "vae/config.json": 551,
               "vae/diffusion_pytorch_model.safetensors": 334_643_268, "vae/diffusion_pytorch_model.bin": 334_707_217,
               "safety_checker/pytorch_model.bin": 1_216_064_769}
    info = SimpleNamespace(siblings=[SimpleNamespace(rfilename=name, size=size) for name, size in listing.items()])
    monkeypatch.setattr(HfApi, "model_info", lambda self, model, revision=None, files_metadata=False: info)
    fetched = sum(size for name, size in listing.items() if name.endswith(("json", ".txt")) or name in (
        "text_encoder/model.safetensors", "unet/diffusion_pytorch_model.safetensors",
        "vae/diffusion_pytorch_model.safetensors"))
    assert round(fetched / 1e9, 1) == 4.3
    assert download_notice("owner/not-cached-here", False) == "downloading owner/not-cached-here (4.3 GB)"


def test_loading_a_local_model_says_nothing_about_downloads(tiny_path):
    heard = []
    StableDiffusionGuidance.from_pretrained(str(tiny_path), device="cpu", on_message=heard.append)
    assert heard == []


def test_loading_says_nothing_of_the_accelerate_it_does_without(tiny_path):
    """Every load of the UNet and the VAE had logged diffusers' "Cannot initialize model with low cpu memory usage
    because `accelerate` was not found ... Defaulting to `low_cpu_mem_usage=False`" (twice per model a worker loads):
    the loading asks for what diffusers would fall back to."""
    import logging
    import warnings

    from voxe_core.guidance.loading import load_stable_diffusion

    library, records = logging.getLogger("diffusers"), []
    handler = logging.Handler()
    handler.emit = records.append
    level = library.level
    library.addHandler(handler)
    library.setLevel(logging.WARNING)
    try:
        with warnings.catch_warnings(record=True) as warned:
            warnings.simplefilter("always")
            assert load_stable_diffusion(str(tiny_path), torch.float32, True)[0] is not None
    finally:
        library.removeHandler(handler)
        library.setLevel(level)
    said = [r.getMessage() for r in records] + [str(w.message) for w in warned]
    assert not [text for text in said if "low_cpu_mem_usage" in text or "accelerate" in text], said


@pytest.mark.parametrize("resolution", [0, -64, 2.5, True])
def test_a_resolution_that_is_no_positive_whole_number_is_refused_before_the_weights_load(resolution, tiny_path,
                                                                                        monkeypatch):
    """0 had silently meant the model's own resolution, -64 failed at the first SDS step ("Input and output sizes
    should be greater than 0") after the weights had loaded, 2.5 ran as 2 and True as 1."""
    import voxe_core.guidance.sds as sds

    def load_stable_diffusion(*args, **kwargs):
        raise AssertionError("the weights were loaded")

    monkeypatch.setattr(sds, "load_stable_diffusion", load_stable_diffusion)
    with pytest.raises(ValueError, match=rf"^resolution must be a positive whole number of pixels \(None: the "
                                         rf"model's\), got {re.escape(repr(resolution))}$"):
        StableDiffusionGuidance.from_pretrained(str(tiny_path), device="cpu", local_files_only=True,
                                                resolution=resolution)


def test_cuda_graphs_are_refused_off_cuda_and_leave_gradient_free_encodes_eager(guidance, tiny_path):
    """CUDA graphs (voxe_core.guidance.cuda_graphs) are a CUDA-only option, refused at once elsewhere; the encoder's
    graph records only an encode with gradient, so the attention pass's encode is the eager one (bench/gpu.py
    measures the graphs themselves on the lent GPU)."""
    from voxe_core.guidance.cuda_graphs import GraphedEncoder

    with pytest.raises(ValueError, match="cuda_graphs needs a CUDA device; this guidance is on cpu"):
        StableDiffusionGuidance.from_pretrained(str(tiny_path), device="cpu", local_files_only=True, cuda_graphs=True)
    encoder = GraphedEncoder(lambda x: guidance.vae.encode(x).latent_dist.parameters)
    x = torch.rand(1, 3, guidance.resolution, guidance.resolution) * 2 - 1
    with torch.no_grad():
        torch.testing.assert_close(encoder(x), guidance.vae.encode(x).latent_dist.parameters)
    with pytest.raises(ValueError, match="CUDA graphs need a CUDA device, got a tensor on cpu"):
        encoder(x.requires_grad_(True))


def test_a_capture_the_libraries_refuse_turns_the_graphs_off_with_a_warning(guidance, tiny_path):
    fresh = StableDiffusionGuidance.from_pretrained(str(tiny_path), device="cpu", local_files_only=True)
    calls = []

    def refused(*args):
        calls.append(args)
        raise RuntimeError("operation not permitted when stream is capturing")

    fresh._graphed_unet = refused  # as a CUDA guidance whose capture fails
    assert fresh.cuda_graphs
    generator = torch.Generator().manual_seed(0)
    latents, noise = torch.randn(1, 4, 8, 8, generator=generator), torch.randn(1, 4, 8, 8, generator=generator)
    text = guidance.encode_prompts(["a dog"])
    with pytest.warns(RuntimeWarning, match="CUDA graphs turned off for .*: operation not permitted when stream"):
        grad, _ = fresh.sds_grad_on_latents(latents, text, [500], noise=noise)
    assert len(calls) == 1 and fresh.cuda_graphs is False
    expected, _ = guidance.sds_grad_on_latents(latents, text, [500], noise=noise)
    torch.testing.assert_close(grad, expected)  # the eager network answered
    fresh.sds_grad_on_latents(latents, text, [500], noise=noise)
    assert len(calls) == 1  # and answers from then on


def test_the_compiled_encoder_matches_the_eager_one_and_compiles_only_the_sds_steps_encode(guidance, tiny_path):
    """A real ``torch.compile`` trace (dynamo's eager backend: inductor's code generation takes this CPU ~30 s) of the
    tiny model's encoder gives the eager latents and the eager gradient, its first call probing the forward and
    backward on a copy; encodes without gradient or under autocast never reach the compiled encoder (bench/gpu.py,
    section j, measures inductor's)."""
    from voxe_core.guidance.compiled import CompiledEncoder

    traced = []

    def compile(moments):
        compiled = torch.compile(moments, backend="eager", dynamic=False)
        return lambda x: traced.append(tuple(x.shape)) or compiled(x)

    fresh = StableDiffusionGuidance.from_pretrained(str(tiny_path), device="cpu", local_files_only=True)
    assert fresh.compile_encoder is False  # off the GPU by default
    fresh._encoder = CompiledEncoder(fresh._encode_moments, compile=compile)
    assert fresh.compile_encoder and fresh.encoder_compile_seconds is None
    images = torch.rand(1, 3, 24, 24, generator=torch.Generator().manual_seed(0))
    results = []
    for encoder_of in (fresh, guidance):
        x = images.clone().requires_grad_(True)
        latents = encoder_of.encode_images(x, sample=False)
        (latents * torch.randn(latents.shape, generator=torch.Generator().manual_seed(1))).sum().backward()
        results.append((latents.detach(), x.grad))
    size = guidance.resolution
    assert traced == [(1, 3, size, size)] * 2  # the probe's, then the encode's
    assert fresh.encoder_compile_seconds > 0 and guidance.encoder_compile_seconds is None
    torch.testing.assert_close(results[0][0], results[1][0])
    torch.testing.assert_close(results[0][1], results[1][1])
    with torch.no_grad():
        fresh.encode_images(images)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        fresh.encode_images(images.clone().requires_grad_(True))
    assert traced == [(1, 3, size, size)] * 2


def test_a_backward_compile_the_libraries_refuse_falls_back_before_the_edits_backward():
    """AOTAutograd compiles the backward lazily, at the first backward: the probe makes it fail inside the encoder's
    fallback rather than in the edit's ``loss.backward()`` (a small convolution stands in for the encoder)."""
    from functorch.compile import make_boxed_func
    from torch._dynamo.backends.common import aot_autograd

    from voxe_core.guidance.compiled import CompiledEncoder

    def refuse(graph, inputs):
        raise RuntimeError("no backward for you")

    backend = aot_autograd(fw_compiler=lambda graph, inputs: make_boxed_func(graph.forward), bw_compiler=refuse)
    conv = torch.nn.Conv2d(3, 8, 3, padding=1).requires_grad_(False)
    moments = lambda x: conv(x).tanh()  # noqa: E731
    encoder = CompiledEncoder(moments, compile=lambda f: torch.compile(f, backend=backend, dynamic=False))
    images = torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(0))
    x, expected = (images.clone().requires_grad_(True) for _ in range(2))
    with pytest.warns(RuntimeWarning, match="torch.compile turned off for the VAE encoder: .*no backward for you"):
        encoder(x).sum().backward()  # the eager graph's backward: nothing left to compile
    moments(expected).sum().backward()
    assert encoder.compiled is None
    torch.testing.assert_close(x.grad, expected.grad)


def test_a_compile_the_libraries_refuse_turns_it_off_with_a_warning(guidance, tiny_path):
    from voxe_core.guidance.compiled import CompiledEncoder

    calls = []

    def refused(x):
        calls.append(x)
        raise RuntimeError("backend='inductor' raised: no working C compiler")

    fresh = StableDiffusionGuidance.from_pretrained(str(tiny_path), device="cpu", local_files_only=True)
    fresh._encoder = CompiledEncoder(fresh._encode_moments, compile=lambda moments: refused)
    images = torch.rand(1, 3, 24, 24, generator=torch.Generator().manual_seed(0))
    with pytest.warns(RuntimeWarning, match="torch.compile turned off for the VAE encoder: .*no working C compiler"):
        latents = fresh.encode_images(images.clone().requires_grad_(True), sample=False)
    assert len(calls) == 1 and fresh.compile_encoder is False
    torch.testing.assert_close(latents, guidance.encode_images(images, sample=False))  # the eager encoder answered
    fresh.encode_images(images.clone().requires_grad_(True), sample=False)
    assert len(calls) == 1  # and answers from then on


def test_the_worker_keeps_its_cache_size_of_guidances_and_frees_the_least_recently_used(tiny_path, tmp_path,
                                                                                          monkeypatch):
    """The worker had kept every guidance it loaded: after a local job SD-2 and SD-1.4 both stayed resident."""
    import weakref
    from collections import OrderedDict

    from voxe_service.settings import Settings
    from worker import runtime

    monkeypatch.setattr(runtime, "_GUIDANCE_CACHE", OrderedDict())
    sds, attention, third = str(tiny_path), str(tmp_path / "attention"), str(tmp_path / "third")
    shutil.copytree(tiny_path, attention)
    shutil.copytree(tiny_path, third)
    assert Settings().guidance_cache_size == 2  # the default: a local job's SDS and attention models
    one = Settings(guidance_cache_size=1)
    edit = weakref.ref(runtime.get_guidance(sds, "cpu", one))
    runtime.get_guidance(attention, "cpu", one)
    assert edit() is None  # freed, not only forgotten
    assert list(runtime._GUIDANCE_CACHE) == [(attention, "cpu")]

    two = Settings()
    kept = runtime.get_guidance(attention, "cpu", two)
    runtime.get_guidance(sds, "cpu", two)
    assert runtime.get_guidance(attention, "cpu", two) is kept  # used last: sds is the least recent now
    runtime.get_guidance(third, "cpu", two)
    assert list(runtime._GUIDANCE_CACHE) == [(attention, "cpu"), (third, "cpu")]


@pytest.mark.parametrize("variable, keyword, other", [("VOXE_CUDA_GRAPHS", "cuda_graphs", "compile_encoder"),
                                                       ("VOXE_COMPILE_ENCODER", "compile_encoder", "cuda_graphs")])
@pytest.mark.parametrize("setting, expected", [("true", None), ("false", False)])
def test_the_workers_speed_up_settings_reach_the_guidance(variable, keyword, other, setting, expected, monkeypatch,
                                                          tmp_path):
    """Each setting reaches its own keyword (true: from_pretrained's default, on CUDA), the other left at its default."""
    from collections import OrderedDict

    from voxe_service.settings import Settings
    from worker import runtime

    asked = {}
    monkeypatch.setattr(StableDiffusionGuidance, "from_pretrained", lambda path, **kwargs: asked.update(kwargs))
    monkeypatch.setattr(runtime, "_GUIDANCE_CACHE", OrderedDict())
    monkeypatch.setenv(variable, setting)
    runtime.get_guidance(str(tmp_path), "cpu", Settings())
    assert asked[keyword] is expected and asked[other] is None


def test_the_worker_names_its_guidance_by_the_model_asked_for_not_the_folder_it_resolves_to(monkeypatch):
    """"tiny" resolves to a folder under this machine's model_dir; edit checkpoints record the guidance's model_id,
    which another worker resuming the job must match: the name, the same on every machine."""
    from collections import OrderedDict

    from voxe_service.settings import Settings
    from worker import runtime

    asked = {}
    monkeypatch.setattr(StableDiffusionGuidance, "from_pretrained",
                        lambda path, **kwargs: asked.update(kwargs, path=path))
    monkeypatch.setattr(runtime, "_GUIDANCE_CACHE", OrderedDict())
    monkeypatch.setattr(runtime, "resolve_model", lambda model, settings: f"/var/voxe/models/{model}-stable-diffusion")
    runtime.get_guidance("tiny", "cpu", Settings())
    assert (asked["path"], asked["name"]) == ("/var/voxe/models/tiny-stable-diffusion", "tiny")


def test_the_transformers_required_is_the_one_the_offline_word_check_reads_as():
    """clip_pieces (the API's edit-word check) reads prompts as transformers 5.x's fast CLIP tokenizer does; 4.x's
    slow one lower-cases whole words and splits CJK characters apart, yet pyproject.toml had allowed 4.40."""
    import tomllib
    from importlib.metadata import version
    from pathlib import Path

    from packaging.requirements import Requirement

    project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
    required = next(r for r in map(Requirement, project["dependencies"]) if r.name == "transformers")
    assert not required.specifier.contains("4.57.3") and required.specifier.contains(version("transformers"))


SD2_BASE_FILES = [  # stabilityai/stable-diffusion-2-base's listing: variants, Flax and single-file checkpoints beside
    ".gitattributes", "README.md", "model_index.json", "512-base-ema.ckpt", "512-base-ema.safetensors",
    "feature_extractor/preprocessor_config.json", "scheduler/scheduler_config.json",
    "text_encoder/config.json", "text_encoder/model.safetensors", "text_encoder/model.fp16.safetensors",
    "text_encoder/pytorch_model.bin", "text_encoder/pytorch_model.fp16.bin", "text_encoder/flax_model.msgpack",
    "tokenizer/merges.txt", "tokenizer/special_tokens_map.json", "tokenizer/tokenizer_config.json", "tokenizer/vocab.json",
    *(f"{part}/{name}" for part in ("unet", "vae") for name in (
        "config.json", "diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.fp16.safetensors",
        "diffusion_pytorch_model.bin", "diffusion_pytorch_model.fp16.bin", "diffusion_flax_model.msgpack",
        "diffusion_pytorch_model.non_ema.safetensors")),
]


def _advised(command: str) -> dict:
    """What the `hf` CLI makes of an advised `hf download` (its own parser; snapshot_download's arguments caught)."""
    import shlex

    import huggingface_hub.cli.download as download
    from click.testing import CliRunner
    from huggingface_hub.cli.hf import app

    asked = {}
    real, download.snapshot_download = download.snapshot_download, lambda **kwargs: asked.update(kwargs) or "/dev/null"
    try:
        assert CliRunner().invoke(app, shlex.split(command)[1:]).exit_code == 0
    finally:
        download.snapshot_download = real
    return asked


def test_the_advised_download_fetches_the_files_loading_reads_not_the_whole_repository(tiny_path):
    """`hf download stabilityai/stable-diffusion-2-base` had been advised (README, docker files, the not-available
    errors): it fetches the whole repository, fp16, non-EMA, Flax and single-file checkpoints, tens of GB. The advice
    now names loading's files (files_loaded, which the first-download size counts), as the `hf` CLI reads it."""
    from huggingface_hub.utils import filter_repo_objects

    from voxe_core.guidance.loading import download_command, files_loaded, not_available_message

    asked = _advised(download_command("owner/sd", revision="v2"))
    assert (asked["repo_id"], asked["revision"]) == ("owner/sd", "v2")

    def selected(names):
        return sorted(filter_repo_objects(names, allow_patterns=asked["allow_patterns"],
                                          ignore_patterns=asked["ignore_patterns"]))

    tiny = sorted(str(p.relative_to(tiny_path)) for p in tiny_path.rglob("*") if p.is_file())
    assert selected(tiny) == sorted(files_loaded(tiny)) and "unet/diffusion_pytorch_model.safetensors" in tiny
    extra = set(selected(SD2_BASE_FILES)) - set(files_loaded(SD2_BASE_FILES))
    assert set(files_loaded(SD2_BASE_FILES)) <= set(selected(SD2_BASE_FILES))
    # Only the torch archives beside the safetensors loading reads: no variant, Flax, checkpoint or other folder
    assert extra == {"unet/diffusion_pytorch_model.bin", "vae/diffusion_pytorch_model.bin", "text_encoder/pytorch_model.bin"}
    sharded = ["unet/config.json", "unet/diffusion_pytorch_model.safetensors.index.json",
               "unet/diffusion_pytorch_model-00001-of-00002.safetensors",
               "unet/diffusion_pytorch_model-00002-of-00002.safetensors",
               "unet/diffusion_pytorch_model-00001-of-00002.fp16.safetensors"]
    assert selected(sharded) == sorted(files_loaded(sharded))
    for offline in (True, False):
        assert f"`{download_command('owner/sd', revision='v2')}`" in not_available_message(
            "owner/sd", None, offline=offline, revision="v2")


def test_the_advised_clip_download_fetches_its_loadings_files():
    """The CLIP model's advice (evaluation's error, the 409 naming a missing model) had been the whole repository too
    (openai/clip-vit-base-patch32: TensorFlow and Flax weights beside): now the files its loading checks."""
    from huggingface_hub.utils import filter_repo_objects

    from voxe_core.evaluate import _clip_not_available
    from voxe_core.guidance.loading import download_command
    from voxe_service.model_inventory import how_to_provide, how_to_repair

    listing = [".gitattributes", "README.md", "config.json", "flax_model.msgpack", "merges.txt", "model.safetensors",
               "model.fp16.safetensors", "preprocessor_config.json", "special_tokens_map.json", "tf_model.h5",
               "tokenizer.json", "tokenizer_config.json", "vocab.json"]
    asked = _advised(download_command("openai/clip-vit-base-patch32", clip=True))
    assert sorted(filter_repo_objects(listing, allow_patterns=asked["allow_patterns"],
                                      ignore_patterns=asked["ignore_patterns"])) == [
        "config.json", "merges.txt", "model.safetensors", "preprocessor_config.json", "special_tokens_map.json",
        "tokenizer.json", "tokenizer_config.json", "vocab.json"]
    clip = download_command("owner/clip", clip=True)
    assert f"`{clip}`" in _clip_not_available("owner/clip", "x") and f"`{clip}`" in how_to_provide("clip", "owner/clip")
    assert f"`{clip} --force-download`" in how_to_repair("clip", "owner/clip")
    assert f"`{download_command('owner/sd')}`" in how_to_provide("attention", "owner/sd")


def test_the_docs_advise_the_download_loading_reads():
    """README, docker/env.example and docker-compose.yml advise the same command the code gives, not a bare one."""
    from pathlib import Path

    from voxe_core.guidance.loading import download_command

    root = Path(__file__).resolve().parents[1]
    for doc in ("README.md", "docker/env.example", "docker-compose.yml"):
        text = (root / doc).read_text(encoding="utf-8")
        assert f"worker {download_command(SDS_MODEL_ID)}" in text, doc
        assert f"worker hf download {SDS_MODEL_ID}\n" not in text and f"worker hf download {SDS_MODEL_ID}`" not in text
