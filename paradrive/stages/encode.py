"""The ``encode`` stage (``stages/encode.yaml``, build-scoped, after ``manifest``): the build's
latent cache for Wan2.1 trainers, :func:`paradrive.wan.encode.encode_build` on the published
pairs. It runs only when asked: ``--stages ...,encode``, or ``encode.vae`` set (the stage file's
``enabled_by``)."""

from __future__ import annotations

from typing import Any

from paradrive.contracts.base import BuildContext, StageParams
from paradrive.wan.encode import EncodeSettings, encode_build


class Params(StageParams):
    vae: str | None
    text_encoder: str | None
    device: str
    dtype: str
    compute_dtype: str
    batch: int
    shard_pairs: int
    num_frames: int | None
    size: list[int] | None
    resize: str

    def settings(self) -> EncodeSettings:
        values = self.model_dump()
        values["size"] = None if self.size is None else tuple(self.size)
        return EncodeSettings(**values)


class EncodeRecord(dict):
    """The latent index the stage published, summarised for the stage's marker."""

    def summary(self) -> dict[str, Any]:
        return {"pairs": self["totals"]["pairs"], "videos": self["totals"]["videos"],
                "shards": len(self["shards"]), "bytes": self["totals"]["bytes"]}


def run(ctx: BuildContext[Params]) -> EncodeRecord:
    return EncodeRecord(encode_build(ctx.build_dir, ctx.params.settings(), log=ctx.log,
                                     fingerprint=ctx.fingerprint, progress=ctx.progress))
