"""Every relative link and image in README.md and docs/ names a file or folder of the repository.

A Markdown link ``[text](target)`` or image ``![alt](target)`` whose target has no URL scheme is
resolved against the folder of the page that holds it; an ``#anchor`` is dropped first. Links
inside fenced code blocks are not links and are skipped.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
SCHEME = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")


def pages() -> list[Path]:
    """README.md and every Markdown page under docs/."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def relative_links(text: str) -> list[str]:
    """The relative link targets of a Markdown text, outside fenced code blocks."""
    out: list[str] = []
    fenced = False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if fenced:
            continue
        for target in LINK.findall(line):
            if SCHEME.match(target) or target.startswith("#"):
                continue
            out.append(target.split("#", 1)[0])
    return out


def broken_links(page: Path, root: Path = ROOT) -> list[str]:
    """The relative link targets of ``page`` that name nothing inside ``root``."""
    broken = []
    for target in relative_links(page.read_text(encoding="utf-8")):
        path = (page.parent / target).resolve()
        if not path.exists() or not path.is_relative_to(root.resolve()):
            broken.append(target)
    return broken


def test_the_checker_sees_a_broken_link(tmp_path: Path) -> None:
    repo = tmp_path / "repo"
    (repo / "docs").mkdir(parents=True)
    (repo / "docs" / "there.png").write_bytes(b"")
    (tmp_path / "outside.md").write_text("")
    page = repo / "docs" / "page.md"
    page.write_text("[ok](there.png#top) ![gone](missing.png) [web](https://example.org)\n"
                    "```\n[in code](not-a-link.md)\n```\n[anchor](#section)\n"
                    "[out of the repository](../../outside.md)\n")
    assert relative_links(page.read_text()) == ["there.png", "missing.png", "../../outside.md"]
    assert broken_links(page, root=repo) == ["missing.png", "../../outside.md"]


@pytest.mark.parametrize("page", pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves(page: Path) -> None:
    assert broken_links(page) == [], f"{page.relative_to(ROOT)}: broken links"
