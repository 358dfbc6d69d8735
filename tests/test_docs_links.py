"""The documentation's links lead somewhere: every relative link of the README and docs/*.md (and of the
checkpoints' PROVENANCE.md, the behaviour folders' TRAINED_WITH.md, research/README.md and results/README.md) names
a file of the repository and, into a Markdown file, one of its headings; and nothing in the repository points at the design
sketch outside it, which a clone does not have."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted(
    [ROOT / "README.md", *ROOT.glob("docs/*.md"), *ROOT.glob("checkpoints/*/PROVENANCE.md")]
    + [*ROOT.glob("behaviour/*/TRAINED_WITH.md"), ROOT / "research" / "README.md"]
    + [ROOT / "results" / "README.md"]
)
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
CODE = re.compile(r"`[^`\n]*`")

# What lies outside the repository: the parent folder's design sketch (the project's own account of the system is
# docs/architecture.md). Written in pieces so that this file does not match itself.
OUTSIDE = [re.compile(re.escape(".." + "/shared")), re.compile(re.escape("shared/" + "DESIGN" + ".md"))]
DESIGN = re.compile(r"\b" + re.escape("DESIGN" + ".md"))
SKIP_TOP = {".git", ".venv", "data", "runs", "run", "out", "build", "logs"}  # git-ignored at the root
SKIP_ANY = {"__pycache__", ".pytest_cache", ".ruff_cache", "tb", "_resume"}
BINARY = {".safetensors", ".png", ".mp4", ".gif", ".jpg", ".npz", ".npy", ".whl", ".so", ".pyc", ".h5"}


def prose(text: str) -> str:
    """The text without fenced code blocks and inline code spans, whose brackets are not links."""
    return CODE.sub("", FENCE.sub("", text))


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: markup dropped, lower case, punctuation other than - and _ removed, spaces
    made hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link's text stays
    text = text.replace("`", "").replace("*", "").strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """Every heading anchor of a Markdown page (a repeated heading gets -1, -2, ... as on GitHub)."""
    seen: dict[str, int] = {}
    out = set()
    for line in FENCE.sub("", page.read_text()).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        s = slug(m.group(1))
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return out


def relative_links(page: Path) -> list[str]:
    return [
        t
        for t in LINK.findall(prose(page.read_text()))
        if not re.match(r"^[a-z][a-z0-9+.-]*:", t, re.I)  # http:, https:, mailto:, data:
    ]


def test_the_pages_have_links():
    assert len(PAGES) > 10
    assert len(relative_links(ROOT / "README.md")) >= 10
    assert (ROOT / "docs" / "README.md").exists() or (ROOT / "docs" / "index.md").exists()


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page):
    broken = []
    for target in relative_links(page):
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            broken.append(f"{target}: no {dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest}")
        elif not dest.is_relative_to(ROOT):
            broken.append(f"{target}: outside the repository")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(f"{target}: no heading #{anchor} in {dest.relative_to(ROOT)}")
    assert not broken, broken


def test_the_docs_index_links_every_docs_page():
    index = next(p for p in (ROOT / "docs" / "README.md", ROOT / "docs" / "index.md") if p.exists())
    linked = {(index.parent / t.partition("#")[0]).resolve() for t in relative_links(index)}
    unlisted = [p.name for p in ROOT.glob("docs/*.md") if p != index and p.resolve() not in linked]
    assert not unlisted, f"{index.relative_to(ROOT)} does not link {unlisted}"


def _repository_text_files():
    for path in ROOT.rglob("*"):
        rel = path.relative_to(ROOT)
        ignored = rel.parts[0] in SKIP_TOP or any(p in SKIP_ANY or p.endswith(".egg-info") for p in rel.parts)
        if ignored:
            continue
        if not path.is_file() or path.suffix in BINARY or path.stat().st_size > 5_000_000:
            continue
        try:
            yield rel, path.read_text()
        except UnicodeDecodeError:
            continue


def test_nothing_points_outside_the_repository():
    hits = []
    design_here = (ROOT / ("DESIGN" + ".md")).exists()
    for rel, text in _repository_text_files():
        for n, line in enumerate(text.splitlines(), 1):
            if any(p.search(line) for p in OUTSIDE) or (not design_here and DESIGN.search(line)):
                hits.append(f"{rel}:{n}: {line.strip()[:120]}")
    assert not hits, "link to docs/architecture.md (or another page of docs/) instead:\n" + "\n".join(hits)
