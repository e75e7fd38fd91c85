"""The project's documentation: what code and tests cite exists, links resolve, licence and citation."""

from __future__ import annotations

import os
import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
CITING_DIRS = ("paradrive", "tests", "bench", "scripts", "stages")
CITING_FILES = ("Makefile", "pyproject.toml", ".ci/run", "manifests/SCHEMA.md")
TEXT_SUFFIXES = {".py", ".yaml", ".yml", ".cpp", ".h", ".sh", ".txt", ".md", ".toml", ".cfg", ".json"}
SKIPPED_DIRS = {"__pycache__", ".pytest_cache", ".hypothesis", "results"}

DOC_REFERENCE = re.compile(r"(?<![\w/.-])[\w.-][\w/.-]*\.md\b")
URL = re.compile(r"\b[a-z][a-z0-9+.-]*://\S+")
LINK = re.compile(r"!?\[[^\]]*\]\(([^()\s]+)\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
README_MAX_LINES = 260


def citing_files() -> list[Path]:
    files = [ROOT / name for name in CITING_FILES if (ROOT / name).is_file()]
    for folder in CITING_DIRS:
        for path in sorted((ROOT / folder).rglob("*")):
            if path.is_file() and path.suffix in TEXT_SUFFIXES and not SKIPPED_DIRS & set(path.parts):
                files.append(path)
    return files


def repository_names() -> set[str]:
    """Names of the repository's own Markdown files (hidden folders, such as the environment, left out)."""
    names = set()
    for folder, subfolders, files in os.walk(ROOT):
        subfolders[:] = [d for d in subfolders if not d.startswith(".") and d not in SKIPPED_DIRS | {"data"}]
        names.update(name for name in files if name.endswith(".md"))
    return names


def resolves(reference: str, citing: Path, names: set[str]) -> bool:
    """A reference names a file of the repository: from the root, from docs/, beside the citing
    file, or, written without a folder, by a name some file of the repository has."""
    candidates = (ROOT / reference, ROOT / "docs" / reference, citing.parent / reference)
    if any(c.is_file() and ROOT in c.resolve().parents for c in candidates):
        return True
    return "/" not in reference and reference in names


def markdown_pages() -> list[Path]:
    return [ROOT / "README.md", ROOT / "bench" / "README.md", ROOT / "manifests" / "SCHEMA.md",
            *sorted((ROOT / "docs").rglob("*.md"))]


def heading_anchors(page: Path) -> set[str]:
    """GitHub's anchors of a page's headings (code blocks left out)."""
    text = FENCE.sub("", page.read_text(encoding="utf-8"))
    anchors = set()
    for line in text.splitlines():
        match = re.match(r"#{1,6}\s+(.*)", line)
        if match:
            title = re.sub(r"[^\w\- ]", "", match.group(1).strip().lower())
            anchors.add(title.replace(" ", "-"))
    return anchors


def broken_links(page: Path, root: Path = ROOT) -> list[str]:
    """Relative links of a page that lead to no file inside ``root``, or to no heading there."""
    text = FENCE.sub("", page.read_text(encoding="utf-8"))
    broken = []
    for target in LINK.findall(text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):   # https:, mailto:
            continue
        path_part, _, anchor = target.partition("#")
        linked = (page.parent / path_part).resolve() if path_part else page
        if not linked.exists() or root not in [linked, *linked.parents]:
            broken.append(f"{page.relative_to(root)}: {target} (no such file in the repository)")
        elif anchor and linked.suffix == ".md" and anchor not in heading_anchors(linked):
            broken.append(f"{page.relative_to(root)}: {target} (no heading with that anchor)")
    return broken


def test_code_tests_and_stage_files_cite_only_files_of_the_repository():
    names = repository_names()
    missing = []
    for path in citing_files():
        if path == Path(__file__).resolve():   # its own examples name missing files on purpose
            continue
        for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            for reference in DOC_REFERENCE.findall(URL.sub("", line)):
                if not resolves(reference, path, names):
                    missing.append(f"{path.relative_to(ROOT)}:{number}: {reference}")
    assert not missing, "cited files that are not in the repository:\n" + "\n".join(missing)


def test_the_reference_check_catches_a_missing_file(tmp_path):
    names = repository_names()
    citing = ROOT / "paradrive" / "geometry.py"
    assert resolves("docs/conventions.md", citing, names)
    assert resolves("conventions.md", citing, names)            # from docs/
    assert resolves("SCHEMA.md", citing, names)                 # a file's own name
    assert not resolves("docs/no-such-page.md", citing, names)
    assert not resolves("../outside/NOTES.md", citing, names)
    assert DOC_REFERENCE.findall(URL.sub("", "see https://example.org/x/README.md and docs/a.md")) == ["docs/a.md"]


def test_every_relative_link_of_the_readme_and_the_docs_resolves():
    pages = markdown_pages()
    assert (ROOT / "docs" / "README.md") in pages and len(pages) > 5
    broken = [problem for page in pages for problem in broken_links(page)]
    assert not broken, "\n".join(broken)


def test_a_broken_link_or_anchor_is_reported(tmp_path):
    assert "the-relative-pose" in heading_anchors(ROOT / "docs" / "conventions.md")
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "conventions.md").write_text("# Conventions\n\n## The relative pose, per frame\n")
    (tmp_path / "outside.md").write_text("# Outside\n")
    page = tmp_path / "docs" / "index.md"
    page.write_text("[a](conventions.md#the-relative-pose-per-frame) [b](nowhere.md) "
                    "[c](conventions.md#nothing) [d](https://example.org/x.md) [e](#top)\n"
                    "```\n[f](inside-a-code-block.md)\n```\n# Top\n", encoding="utf-8")
    problems = broken_links(page, root=tmp_path / "docs")
    assert len(problems) == 2, problems
    assert "nowhere.md" in problems[0] and "#nothing" in problems[1]
    page.write_text("[g](../outside.md)\n", encoding="utf-8")
    assert broken_links(page, root=tmp_path / "docs") == ["index.md: ../outside.md (no such file in the repository)"]


def test_the_readme_is_short():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines; move detail into docs/"


def test_licence_and_citation_are_there_and_agree_with_the_package():
    licence = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert "Apache License" in licence and "Version 2.0, January 2004" in licence
    assert "END OF TERMS AND CONDITIONS" in licence
    pyproject = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    version = re.search(r'^version\s*=\s*"([^"]+)"', pyproject, re.M)
    licence_line = re.search(r"^license\s*=.*$", pyproject, re.M)
    assert version and licence_line

    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    for key in ("cff-version", "message", "title", "authors", "version", "license", "references"):
        assert citation.get(key), f"CITATION.cff lacks {key}"
    assert citation["cff-version"] == "1.2.0"
    assert str(citation["version"]) == version.group(1)
    assert citation["license"] in licence_line.group(0)
    titles = [ref["title"] for ref in citation["references"]]
    assert any(title.startswith("ReCamDriving") for title in titles)
    assert all(ref.get("authors") and ref.get("type") for ref in citation["references"])


# A measured figure: a number with its unit (speed ratios, per cent, seconds, minutes, dB, sizes);
# sizes such as 320×192 and goals (after "≤" or "within") are not measurements.
FIGURE = re.compile(r"(?<![\w.×/≤])(?<!≤ )(?<!within )([+−]?\d+(?:\.\d+)?) ?(×(?!\d)|%|s\b|minutes|dB|GB|MB|kB)")


def readme_figures(text: str) -> list[str]:
    return [m.group(0) for m in FIGURE.finditer(text)]


def test_the_readme_s_figures_are_those_of_the_performance_page():
    """Every figure the README quotes is written the same way in docs/performance.md (the current
    figures), so the front page cannot drift from the measurements."""
    current = (ROOT / "docs" / "performance.md").read_text(encoding="utf-8")
    figures = readme_figures((ROOT / "README.md").read_text(encoding="utf-8"))
    assert len(figures) >= 8
    missing = [f for f in figures
               if not re.search(r"(?<![\d.])" + re.escape(f) + r"(?![\d])", current)]
    assert not missing, f"README figures not in docs/performance.md: {missing}"


def test_the_figure_check_sees_a_stale_figure():
    assert readme_figures("about 9 minutes, 2.97× at 320×192, ≤ 3 %, within 1.5 dB, +0.3 % (0.6 %)") == [
        "9 minutes", "2.97×", "+0.3 %", "0.6 %"]
    assert not re.search(r"(?<![\d.])" + re.escape("9 minutes") + r"(?![\d])", "7.9 minutes")
