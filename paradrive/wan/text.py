"""The empty-prompt text embedding Wan2.1 is trained with, from umT5 in a local folder.

ReCamDriving trains with an empty prompt, so one embedding serves every pair: it is computed once
per build and cached beside the latents. umT5("") is not zeros (the end-of-sequence token still
goes through the encoder), so it cannot be replaced by a zero tensor.

The embedding is stored the way Wan's pipeline hands it to the transformer: the prompt is tokenised
with padding to 512 tokens and an attention mask, encoded, then the rows after the real tokens
(for "": only ``</s>``) are set to zero, giving (512, D) (D = 4096 for umT5-xxl).

A text encoder folder is a Wan2.1 diffusers folder (or any folder) holding ``text_encoder/``
(``UMT5EncoderModel``) and ``tokenizer/``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from paradrive.errors import ConfigError
from paradrive.wan.vae import first_line, weight_errors

__all__ = ["MAX_SEQUENCE_LENGTH", "EMBEDDING_FORM", "text_encoder_folders", "tiny_text_embedding",
           "make_tiny_text_encoder", "empty_prompt_embedding"]

MAX_SEQUENCE_LENGTH = 512
EMBEDDING_FORM = ("umT5 last hidden state of the empty prompt, tokenised to 512 tokens; rows after "
                  "the real tokens zeroed (as Wan's pipeline hands it to the transformer)")
_TINY_WORDS = "a the car road street drive left right lane camera".split()


def text_encoder_folders(path: str | os.PathLike) -> tuple[Path, Path]:
    """``(encoder folder, tokenizer folder)`` of ``path``: a Wan diffusers folder (its
    ``text_encoder/`` and ``tokenizer/``), or the umT5 folder itself with its tokenizer beside
    its config or in a sibling ``tokenizer/``; ConfigError naming ``path`` and the fix otherwise."""
    root = Path(path)
    if (root / "config.json").is_file():
        tokenizer_files = ("tokenizer_config.json", "tokenizer.json", "spiece.model")
        if any((root / name).is_file() for name in tokenizer_files):
            return root, root
        if (root.parent / "tokenizer").is_dir():
            return root, root.parent / "tokenizer"
    encoder, tokenizer = root / "text_encoder", root / "tokenizer"
    missing = [p.name for p in (encoder, tokenizer) if not p.is_dir()]
    if missing:
        raise ConfigError(f"text encoder folder {path} has no {' or '.join(f'{m}/' for m in missing)}; "
                          f"pass a local folder in Wan2.1's diffusers layout holding text_encoder/ "
                          f"(umT5) and tokenizer/ (e.g. Wan2.1-T2V-1.3B-Diffusers)")
    return encoder, tokenizer


def tiny_text_embedding(seed: int, text_dim: int, tokens: int = 8) -> torch.Tensor:
    """The empty prompt's stand-in for the tiny random transformer (``text_encoder: tiny``): a
    fixed random (tokens, text_dim) float32 on the CPU drawn from ``seed``; the training loop and
    ``encode --vae tiny`` draw the same one."""
    g = torch.Generator(device="cpu").manual_seed(int(seed) + 7)
    return torch.randn(tokens, text_dim, generator=g, device="cpu")


def make_tiny_text_encoder(directory: str | os.PathLike, seed: int = 0) -> Path:
    """A tiny random umT5 encoder and a word-level tokenizer saved in Wan's layout under
    ``directory`` (``text_encoder/``, ``tokenizer/``), the same for the same ``seed``; returns
    ``directory``. Built offline: the tokenizer comes from the ``tokenizers`` library."""
    from tokenizers import Tokenizer, models, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast, UMT5Config, UMT5EncoderModel

    root = Path(directory)
    vocab = {"<pad>": 0, "</s>": 1, "<unk>": 2} | {w: i + 3 for i, w in enumerate(_TINY_WORDS)}
    backend = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    backend.pre_tokenizer = pre_tokenizers.Whitespace()
    backend.post_processor = processors.TemplateProcessing(single="$A </s>", special_tokens=[("</s>", 1)])
    PreTrainedTokenizerFast(tokenizer_object=backend, pad_token="<pad>", eos_token="</s>",
                            unk_token="<unk>").save_pretrained(root / "tokenizer")
    config = UMT5Config(vocab_size=len(vocab), d_model=32, d_kv=8, d_ff=64, num_layers=2, num_heads=4,
                        relative_attention_num_buckets=8, relative_attention_max_distance=16,
                        pad_token_id=0, eos_token_id=1, decoder_start_token_id=0)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = UMT5EncoderModel(config)
    model.save_pretrained(root / "text_encoder")
    return root


def _load(path: str | os.PathLike, device: torch.device, dtype: torch.dtype) -> tuple[Any, Any]:
    from transformers import AutoTokenizer, UMT5EncoderModel

    encoder_dir, tokenizer_dir = text_encoder_folders(path)
    try:
        tokenizer = AutoTokenizer.from_pretrained(tokenizer_dir, local_files_only=True)
        model: Any = UMT5EncoderModel.from_pretrained(encoder_dir, local_files_only=True, dtype=dtype)
    except weight_errors() as exc:
        raise ConfigError(f"text encoder folder {path} could not be loaded ({first_line(exc)}); pass a "
                          f"local folder holding umT5 in text_encoder/ and its tokenizer in tokenizer/ "
                          f"(a file cut short, e.g. by an interrupted download, must be fetched again)") from exc
    return tokenizer, model.to(device).eval()


@torch.no_grad()
def empty_prompt_embedding(path: str | os.PathLike, device: str | torch.device = "cpu",
                           dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """umT5's embedding of the empty prompt (see the module docstring), (512, D) float32 on the
    CPU; the encoder runs on ``device`` in ``dtype`` and is released afterwards."""
    device = torch.device(device)
    tokenizer, model = _load(path, device, dtype)
    tokens = tokenizer([""], padding="max_length", max_length=MAX_SEQUENCE_LENGTH, truncation=True,
                       add_special_tokens=True, return_attention_mask=True, return_tensors="pt")
    ids, mask = tokens.input_ids.to(device), tokens.attention_mask.to(device)
    hidden = model(ids, mask).last_hidden_state[0].float()
    keep = int(mask[0].gt(0).sum())
    rows = torch.arange(hidden.shape[0], device=device)[:, None] < keep
    return torch.where(rows, hidden, torch.zeros((), device=device)).cpu()
