"""The paper's table from a scores document (:func:`paradrive.scoring.run.score_videos`): per
dataset, one line per lateral offset ±d (both signs together, as Tables 1 and 2 group them) and
their mean, one column per metric; the CSV with one line per video; the plot against the offset.

Plain data only: the command line draws the table (rich), this module says what is in it.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Column", "COLUMNS", "TableBlock", "paper_table", "csv_text", "write_csv",
           "plot_scores"]


@dataclass(frozen=True)
class Column:
    """One column: its heading, the value's name in the document, the factor it is printed at
    (CLIP-V ×100 as the paper prints it), its format and whether lower is better."""

    heading: str
    name: str
    scale: float = 1.0
    spec: str = ".2f"
    lower_is_better: bool = True
    of: str | None = None     # printed as value/of (frames located of those sampled)


COLUMNS: tuple[Column, ...] = (
    Column("IQ", "iq", lower_is_better=False),
    Column("TCE", "tce"),
    Column("FID", "fid"),
    Column("FVD", "fvd"),
    Column("CLIP-V", "clip_v", scale=100.0, lower_is_better=False),
    Column("RErr", "rerr_deg"),
    Column("TErr", "terr", spec=".3f"),
    Column("TErr m", "terr_m", spec=".3f"),
    Column("RErr m", "rerr_m_deg"),
    Column("located", "located", spec=".1f", lower_is_better=False, of="sampled"),
    Column("PSNR", "psnr", lower_is_better=False),
    Column("SSIM", "ssim", spec=".4f", lower_is_better=False),
)
DATASET_NAMES = {"waymo": "WOD", "nuscenes": "nuScenes", "drivestudio": "DriveStudio",
                 "synthetic": "synthetic", "video": "video"}


@dataclass(frozen=True)
class TableBlock:
    """One dataset's table: its title, headings and lines of cells (strings)."""

    title: str
    headings: list[str]
    lines: list[list[str]]


def _present(doc: dict) -> list[Column]:
    """The columns some group of the document has a value for."""
    groups = [g for cols in doc["table"].values() for g in cols.values()]
    return [c for c in COLUMNS if any(g.get(c.name) is not None for g in groups)]


def _cell(group: dict, column: Column) -> str:
    value = group.get(column.name)
    if value is None:
        return "-"
    text = format(float(value) * column.scale, column.spec)
    of = group.get(column.of) if column.of else None
    return text if of is None else f"{text}/{float(of):g}"


def paper_table(doc: dict) -> list[TableBlock]:
    """The paper's layout: a block per dataset (WOD and nuScenes apart), a line per ±d offset
    and the mean over them; ``located`` is the mean number of frames located a video."""
    columns = _present(doc)
    blocks = []
    for dataset, cols in doc["table"].items():
        lines = [[f"{label} m" if label != "mean" else "mean", str(g["videos"])]
                 + [_cell(g, c) for c in columns] for label, g in cols.items()]
        blocks.append(TableBlock(title=DATASET_NAMES.get(dataset, dataset),
                                 headings=["offset", "videos"] + [c.heading for c in columns],
                                 lines=lines))
    return blocks


def csv_text(doc: dict) -> str:
    """One line per scored video: its row's identity, the video file, every value and the
    error (empty when scored)."""
    rows = doc["rows"]
    names = list(dict.fromkeys(k for r in rows for k in r))
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=names, lineterminator="\n")
    writer.writeheader()
    for r in rows:
        cells = {k: "" if r.get(k) is None else r[k] for k in names}
        if "skipped" in cells:   # metric: why, for the metrics this video has no value of
            cells["skipped"] = "; ".join(f"{m}: {why}" for m, why in (r.get("skipped") or {}).items())
        writer.writerow(cells)
    return out.getvalue()


def write_csv(doc: dict, path: str | Path) -> None:
    from paradrive.io import write_text

    write_text(path, csv_text(doc))


def plot_scores(doc: dict, path: str | Path) -> None:
    """Each measured per-offset value against the signed lateral offset (one panel each)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from paradrive.io import atomic_path

    rows = doc["by_offset"]
    columns = [c for c in COLUMNS if c.name != "located"
               and any(r.get(c.name) is not None for r in rows)] or list(COLUMNS[-2:])
    fig, axes = plt.subplots(1, len(columns), figsize=(max(8.0, 4.2 * len(columns)), 4), squeeze=False)
    offsets = [r["offset_m"] for r in rows]
    for ax, c in zip(axes[0], columns):
        values = [None if r.get(c.name) is None else r[c.name] * c.scale for r in rows]
        ax.plot(offsets, [float("nan") if v is None else v for v in values], "o-")
        ax.set_xlabel("lateral offset (m, left > 0)")
        ax.set_ylabel(f"{c.heading} ({'lower' if c.lower_is_better else 'higher'} is better)")
        ax.grid(alpha=0.3)
    fig.suptitle(f"{Path(doc['videos']).name} against {Path(doc['build']).name}")
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
