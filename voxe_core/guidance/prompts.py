"""The prompt the diffusion model sees: "a render of <text>[, <view> view]" (SPEC §2), view words from the pose."""

from __future__ import annotations

import re
import unicodedata
from typing import Sequence

RENDER_PREFIX = "a render of"
VIEW_WORDS = ("front", "side", "back", "overhead")
AUTHORS_FRONT_AZIMUTH_DEG = 270.0
"""Azimuth (degrees, ``spherical_poses``: eye = r·(cos az, sin az, ·)) of the object's front: the authors'
code calls a camera "front" when its right vector points along +x, i.e. a camera on the −y axis."""


def view_word(elevation_deg: float, azimuth_deg: float) -> str:
    """The view word for a camera pose, appended to the prompt as the authors do. SPEC gives no angles and the
    authors' versions differ (overhead above 55° or 60°, back beyond 120° of yaw); these are ours:

    ``overhead`` when the elevation above the horizon is more than 60°; else by
    azimuth (degrees, any range, 0 = the object's front in the caller's pose
    convention): ``front`` when within ±45° of 0, ``back`` within ±45° of 180,
    ``side`` otherwise. Boundaries (exactly ±45°, ±135°) go to front/back.
    """
    if elevation_deg > 60.0:
        return "overhead"
    az = (float(azimuth_deg) + 180.0) % 360.0 - 180.0  # [-180, 180)
    if abs(az) <= 45.0:
        return "front"
    if abs(az) >= 135.0:
        return "back"
    return "side"


def pose_view_word(elevation_deg: float, azimuth_deg: float, front_azimuth_deg: float = AUTHORS_FRONT_AZIMUTH_DEG) -> str:
    """View word of a pose whose azimuth is measured in the spherical_poses convention."""
    return view_word(float(elevation_deg), float(azimuth_deg) - float(front_azimuth_deg))


def prompt_text(user_text: str) -> str:
    """The user's prompt as the model reads it, before any prefix: whitespace collapsed, trailing full stops dropped."""
    return " ".join(str(user_text).split()).rstrip(". ").strip()


def edit_prompt(user_text: str, view_word: str | None = None) -> str:
    """``"a render of <text>[, <view> view]"`` (SPEC §2).

    The text is :func:`prompt_text`'s. The prefix is not
    doubled when the user already wrote it (any case). ``view_word`` is one of
    :data:`VIEW_WORDS` or ``None`` for no view suffix.
    """
    text = prompt_text(user_text)
    if not text:
        raise ValueError("the edit prompt is empty")
    if text.lower() == RENDER_PREFIX:
        raise ValueError("the edit prompt has only the prefix 'a render of' and no content")
    if not text.lower().startswith(RENDER_PREFIX + " "):
        text = f"{RENDER_PREFIX} {text}"
    if view_word is not None:
        if view_word not in VIEW_WORDS:
            raise ValueError(f"unknown view word {view_word!r}; expected one of {VIEW_WORDS}")
        text = f"{text}, {view_word} view"
    return text


def without_view_word(prompt: str) -> str:
    """``prompt`` without the ", <view> view" that :func:`edit_prompt` appends (as it is when it has none).

    Examples:
        >>> without_view_word("a render of a dog with a saddle on its back, back view")
        'a render of a dog with a saddle on its back'
    """
    for word in VIEW_WORDS:
        if prompt.endswith(suffix := f", {word} view"):
            return prompt[: -len(suffix)]
    return prompt


TEXT_ENCODER_TOKENS = 77
"""What Stable Diffusion's CLIP text encoder reads (1.x and 2.x alike), its start and end tokens included."""

# CLIP's pre-tokenizer ('s|'t|'re|'ve|'m|'ll|'d|\p{L}+|\p{N}|[^\s\p{L}\p{N}]+): a contraction, a run of letters, one
# number, or a run of other marks; BPE then makes each piece one token or more. Python's re has no \p{...} (its \w
# counts ½ or ² as letters), so the classes are Unicode's categories.
_CONTRACTION = re.compile(r"'s|'t|'re|'ve|'m|'ll|'d")


def _piece_class(character: str) -> str:
    """"L" (a letter), "N" (a number), " " (space) or "" (any other mark), as CLIP's pattern classes them."""
    if character.isspace():
        return " "
    category = unicodedata.category(character)[0]
    return category if category in "LN" else ""


def clip_pieces(text: str) -> list[str]:
    """The pre-token pieces of ``text`` as CLIP's tokenizer reads it: in NFC (a decomposed accent is no piece of its
    own there) and lower case, character by character as its normalizer lowers (str.lower() makes a word-final
    capital sigma the final ς, the tokenizer σ). BPE makes each piece one token or more, the last one ending the word.

    Examples:
        >>> clip_pieces("A dog's hat, front view")
        ['a', 'dog', "'s", 'hat', ',', 'front', 'view']
        >>> clip_pieces("café½ 12_x!?")
        ['café', '½', '1', '2', '_', 'x', '!?']
    """
    text, pieces, at = "".join(c.lower() for c in unicodedata.normalize("NFC", text)), [], 0
    while at < len(text):
        if contraction := _CONTRACTION.match(text, at):
            pieces.append(contraction.group())
            at = contraction.end()
            continue
        kind, end = _piece_class(text[at]), at + 1
        if kind == " ":
            at = end
            continue
        if kind != "N":  # (one number is a piece alone)
            while end < len(text) and _piece_class(text[end]) == kind:
                end += 1
        pieces.append(text[at:end])
        at = end
    return pieces


def _names(piece: str) -> bool:
    """Whether a piece names something: a word, a number or a symbol (an "other symbol", as an emoji or "♥" is, or a
    currency's), not punctuation alone, a mathematical or modifier mark ("^^", "+", "|") nor a contraction's ending
    ("'s")."""
    return not _CONTRACTION.fullmatch(piece) and any(unicodedata.category(c) in _NAMING_CATEGORIES or
                                                     unicodedata.category(c)[0] in "LN" for c in piece)


_NAMING_CATEGORIES = ("So", "Sc")


def names_something(text: str) -> bool:
    """Whether ``text`` names anything as the model reads it: a word, a number or a symbol ("🐶", "$"), not
    punctuation or marks alone ("---", "'", "^^")."""
    return any(map(_names, clip_pieces(text)))


CLIP_SPECIAL_TOKENS = ("<|startoftext|>", "<|endoftext|>")
"""CLIP's tokenizer reads each, written out in a text, as the text's start or end (no word starts after it)."""


def check_no_special_tokens(text: str, what: str) -> None:
    """ValueError naming ``what`` where ``text`` writes out one of :data:`CLIP_SPECIAL_TOKENS`: the service and the
    CLI refuse it alike (``voxe edit`` had run a whole edit towards a prompt the model read as ending there)."""
    if special := [token for token in CLIP_SPECIAL_TOKENS if token in text]:
        raise ValueError(f"{what} contains {' and '.join(map(repr, special))}, which the model reads as the start or "
                         "end of its text, not as words: remove it")


_STRAIGHT_QUOTES = str.maketrans("‘’‚‛′“”„‟″", "'" * 5 + '"' * 5)


def _why_not_found(word: str, text: str, pieces: list[str]) -> str:
    """What to say beyond "does not occur as whole words", where the cause is likely: quotes other than the prompt's
    (’ against '), or the word inside a longer one ("glasses" in "sunglasses"), told how to separate it when that
    one is in a script written without spaces (Chinese, Japanese, Thai): such text is one word to CLIP.
    (transformers 4.x's slow tokenizer, without ftfy, puts spaces round each CJK character; 5.x's does not.)"""
    if _is_run(clip_pieces(word.translate(_STRAIGHT_QUOTES)), clip_pieces(text.translate(_STRAIGHT_QUOTES))):
        return ": its apostrophes and quotes must be the prompt's own (’ is not ', ” is not \")"
    sub = clip_pieces(word)
    if len(sub) == 1 and (whole := next((piece for piece in pieces if sub[0] in piece), None)):
        if not any(unicodedata.name(c, "").startswith(_UNSPACED_SCRIPTS) for c in whole):
            return f": {sub[0]!r} is part of the word {whole!r}"
        return (f": the model reads {whole!r} as one word (text written without spaces, as Chinese is, is one word "
                "to it): name all of it, or separate the edit word from the words around it with spaces in the prompt")
    return ""


_UNSPACED_SCRIPTS = ("CJK ", "HIRAGANA ", "KATAKANA", "HALFWIDTH KATAKANA ", "THAI ", "LAO ", "KHMER ", "MYANMAR ",
                     "TIBETAN ")
"""Unicode names' beginnings of the characters of scripts written without spaces between words."""


def _is_run(sub: list[str], pieces: list[str]) -> bool:
    return any(pieces[i:i + len(sub)] == sub for i in range(len(pieces) - len(sub) + 1))


def check_edit_words_name_an_edit(text: str, edit_words: Sequence[str]) -> None:
    """ValueError naming the problem when ``edit_words`` cannot name an edit of ``text`` as the model reads both
    (:func:`clip_pieces`: in NFC, any case, whole words as the guidance's ``token_spans`` finds them): a word of
    punctuation alone (a symbol, "🎩", names something), one whose pieces are no run of the text's, or words leaving
    no word of the text to name the object (its punctuation alone would).

    Examples:
        >>> check_edit_words_name_an_edit("a sunglasses-wearing dog's hat", ["Sunglasses", "dog"])
        >>> check_edit_words_name_an_edit("big sunglasses, party hat", ["big sunglasses", "party hat"])
        Traceback (most recent call last):
        ...
        ValueError: the edit words ['big sunglasses', 'party hat'] cover the whole prompt 'big sunglasses, party hat', punctuation aside: nothing names the object; some other word of the prompt must
    """
    pieces, covered = clip_pieces(text), set()
    for word in edit_words:
        sub = clip_pieces(word)
        if not any(map(_names, sub)):
            raise ValueError(f"edit word {word!r} names nothing: it is punctuation alone (a mark such as ^ + | too, "
                             "or a contraction's ending, \"'s\"); name a word, number or symbol of the prompt")
        starts = [i for i in range(len(pieces) - len(sub) + 1) if pieces[i:i + len(sub)] == sub]
        if not starts:
            raise ValueError(f"edit word {word!r} does not occur in the prompt {text!r} as whole words"
                             + _why_not_found(word, text, pieces))
        covered.update(i + k for i in starts for k in range(len(sub)))
    if all(i in covered or not _names(piece) for i, piece in enumerate(pieces)):
        raise ValueError(f"the edit words {list(edit_words)} cover the whole prompt {text!r}, punctuation "
                         "aside: nothing names the object; some other word of the prompt must")


def tokens_at_least(text: str) -> int:
    """A lower bound of the CLIP tokens of ``text`` with the start and end tokens: its pieces, plus two."""
    return len(clip_pieces(text)) + 2


def check_edit_words_read(user_text: str, edit_words: list[str], view_words: bool = True) -> None:
    """ValueError naming the first edit word whose pieces are no run of the pieces of the prompt's own text as the
    model reads it (each prompt the refinement gives its attention model: "a render of <text>", with each view word
    unless ``view_words`` is off), where the guidance's ``token_spans`` looks for its tokens, after the whole edit.
    Punctuation at a word's edge is read with the punctuation beside it: "hat." at the prompt's end is read as
    "hat" then ", front view" (the full stop dropped), "hat!" as "hat" then "!,", and a symbol ending the prompt as
    one piece with the view word's comma ("🎩,"): said as such, as no spelling of the word finds it there.

    Examples:
        >>> check_edit_words_read("a dog wearing a hat!", ["hat"])
        >>> check_edit_words_read("a dog wearing a hat!", ["hat!"])
        Traceback (most recent call last):
        ...
        ValueError: edit word 'hat!' does not occur in the prompt as the model reads it, 'a render of a dog wearing a hat!, front view' (its pieces 'hat' '!' are no run of the prompt's; punctuation is read together with the punctuation beside it): name it as the prompt writes it, without the punctuation around it
    """
    for view in VIEW_WORDS if view_words else (None,):
        prompt = edit_prompt(user_text, view)
        pieces, text_end = clip_pieces(prompt), len(clip_pieces(without_view_word(prompt)))
        for word in edit_words:
            sub = clip_pieces(word)
            if not _occurs(sub, pieces[:text_end]):
                shown = " ".join(repr(piece) for piece in sub)
                said = f"edit word {word!r} does not occur in the prompt as the model reads it, {prompt!r}"
                if view is not None and _names(sub[-1]) and _occurs(sub, clip_pieces(edit_prompt(user_text))):
                    # Only the view word's comma is in the way, of a symbol ending the prompt ("a dog in a 🎩"): the
                    # advice below had told the user to drop punctuation the word does not hold.
                    raise ValueError(f"{said}: the view words append ', {view} view' to the prompt, and the model "
                                     f"reads their comma together with the symbol ending it ({pieces[text_end - 1]!r} "
                                     "is one piece): end the prompt with another word, or turn view_words off")
                raise ValueError(f"{said} (its pieces {shown} are no run of the prompt's; punctuation is read together "
                                 "with the punctuation beside it): name it as the prompt writes it, without the "
                                 "punctuation around it")


def _occurs(sub: list[str], pieces: list[str]) -> bool:
    """Whether the pieces ``sub`` are a run of ``pieces``."""
    return any(pieces[i:i + len(sub)] == sub for i in range(len(pieces) - len(sub) + 1))


def tokens_read(tokenizer, max_position_embeddings: int) -> int:
    """The tokens a model's text encoder reads: its positions, or fewer where its tokenizer cuts there (a tokenizer
    config without ``model_max_length`` says 1e30)."""
    return int(min(tokenizer.model_max_length, max_position_embeddings))


def check_prompt_tokens(user_text: str, tokenizer, limit: int, view_words: bool = True) -> None:
    """ValueError when a prompt an edit gives the diffusion model ("a render of <text>", with each view word unless
    ``view_words`` is off) is more tokens under the model's ``tokenizer`` (CLIPTokenizer; start and end tokens
    included) than its text encoder reads (``limit``: :func:`tokens_read`): the exact count
    :func:`check_prompt_length` bounds from below, for a caller holding the tokenizer (a worker, before a job's
    fit: the guidance would refuse it only at the edit)."""
    for view in VIEW_WORDS if view_words else (None,):
        prompt = edit_prompt(user_text, view)
        if (tokens := len(tokenizer(prompt).input_ids)) > limit:
            raise ValueError(f"the prompt {prompt!r} is {tokens} tokens as the model's tokenizer reads it; its text "
                             f"encoder reads {limit}, its start and end tokens included: shorten it")


def word_token_spans(tokenizer, prompt: str, words: Sequence[str]) -> list[int]:
    """Positions in the token sequence of ``prompt`` under ``tokenizer`` (CLIPTokenizer; 0 is the start token) of
    every occurrence of each word, as the guidance's ``token_spans`` finds them: every sub-token of a multi-token
    word or phrase, only whole words (an occurrence starts a word: "shade" is not found in "lampshade"), only in
    the prompt's own text, before its view word. Sorted, without duplicates; ValueError naming a word not found."""
    if isinstance(words, str):
        words = [words]
    ids = tokenizer(prompt).input_ids
    # CLIP's BPE ends each word's last token with "</w>": a word starts after one, or after the start token.
    tokens = tokenizer.convert_ids_to_tokens(ids)
    starts = {1} | {i + 1 for i, token in enumerate(tokens) if token.endswith("</w>")}
    text_end = 1 + len(tokenizer(without_view_word(prompt), add_special_tokens=False).input_ids)
    positions: set[int] = set()
    for word in words:
        sub = tokenizer(word, add_special_tokens=False).input_ids
        if not sub:
            raise ValueError(f"{word!r} has no tokens")
        found = [i for i in starts if i + len(sub) <= text_end and ids[i : i + len(sub)] == sub]
        if not found:
            raise ValueError(f"{word!r} does not occur in the prompt {prompt!r} (tokens {tokenizer.tokenize(prompt)})")
        for i in found:
            positions.update(range(i, i + len(sub)))
    return sorted(positions)


def check_edit_words_tokens(user_text: str, edit_words: Sequence[str], tokenizer, view_words: bool = True) -> None:
    """ValueError naming the first edit word ``tokenizer`` (the attention model's) does not find where the
    refinement looks for it (:func:`word_token_spans`): in the prompt's own text, then in "a render of <text>" with
    each view word unless ``view_words`` is off. For a caller holding the tokenizer (a worker, before a job's fit):
    :func:`check_edit_words_read` reads the prompt as the tokenizer should, this one as it does."""
    prompts = [prompt_text(user_text)] + [edit_prompt(user_text, view) for view in
                                          (VIEW_WORDS if view_words else (None,))]
    for prompt in prompts:
        word_token_spans(tokenizer, prompt, edit_words)


def check_prompt_length(user_text: str, view_words: bool = True) -> None:
    """ValueError when "a render of <text>, overhead view" (the longest prompt an edit gives the diffusion model;
    without ``view_words``, no view) surely holds more tokens than its text encoder reads
    (:func:`tokens_at_least`): the guidance's own tokenizer may still refuse a prompt this passes, where BPE
    splits a word.

    Examples:
        >>> check_prompt_length("a microphone wearing big sunglasses")
        >>> check_prompt_length("a mic " + "very " * 70 + "shiny")
        Traceback (most recent call last):
        ...
        ValueError: the prompt is at least 81 tokens as the model sees it ("a render of a mic very very ve..., overhead view"); its text encoder reads 77, its start and end tokens included: shorten it
    """
    check_text_length(edit_prompt(user_text, "overhead" if view_words else None), "the prompt", "shorten it")


def check_text_length(text: str, what: str, remedy: str) -> None:
    """ValueError naming ``what`` (and ``remedy``) when ``text`` surely holds more tokens than a CLIP text encoder
    reads (:func:`tokens_at_least`); the encoder would cut it there and read a shorter text. ValueError too when it
    holds a byte the encoding it was read in had no character for (surrogateescape's: a command line under a locale
    that is not UTF-8 gives one for each byte of "é"): the tokenizer had raised a TypeError, a traceback, after
    the model's load."""
    if (undecoded := re.search("[\udc80-\udcff]", text)) is not None:
        raise ValueError(f"{what} holds {undecoded[0]!r}, a byte that was no text in the encoding it was read in (a "
                         "command line read under a locale that is not UTF-8: LC_ALL=C.UTF-8 or PYTHONUTF8=1 reads "
                         "it whole)")
    if (tokens := tokens_at_least(text)) > TEXT_ENCODER_TOKENS:
        shown = text if len(text) <= 60 else f"{text[:30]}...{text[-15:]}"
        raise ValueError(f'{what} is at least {tokens} tokens as the model sees it ("{shown}"); its text '
                         f"encoder reads {TEXT_ENCODER_TOKENS}, its start and end tokens included: {remedy}")
