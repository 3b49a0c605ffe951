"""Every relative link and image in the README, docs/ and the results notes under ablations/ points at a file or folder
that exists, and a `#anchor` into a Markdown file at one of its headings (GitHub's slugs)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.helpers import ROOT

PAGES = [ROOT / "README.md", *sorted(ROOT.glob("docs/**/*.md")), *sorted(ROOT.glob("ablations/**/*.md"))]
# [text](target), ![alt](target "title"), <img src="target">, [ref]: target
LINK = re.compile(r"\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)|<img\s[^>]*src=\"([^\"]+)\"|^\s*\[[^\]]+\]:\s+(\S+)",
                  re.MULTILINE)
FENCED = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)
CODE = re.compile(FENCED.pattern + r"|`[^`\n]+`", re.MULTILINE | re.DOTALL)  # links inside code are text


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, markup and punctuation dropped, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    found, seen = set(), {}
    for h in re.findall(r"^#{1,6}\s+(.+?)\s*#*\s*$", FENCED.sub("", page.read_text()), re.MULTILINE):
        s = slug(h)
        n = seen.get(s, 0)
        seen[s] = n + 1
        found.add(s if n == 0 else f"{s}-{n}")
    return found


def dangling(page: Path) -> list[str]:
    """The relative links of `page` whose file, folder or anchor does not exist."""
    bad = []
    for m in LINK.finditer(CODE.sub("", page.read_text())):
        target = next(g for g in m.groups() if g)
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            bad.append(target)
        elif anchor and dest.suffix == ".md" and anchor.lower() not in anchors(dest):
            bad.append(f"{target} (no such heading)")
    return bad


def test_pages_are_found():
    assert len(PAGES) > 10 and ROOT / "docs" / "results.md" in PAGES and ROOT / "ablations/results/README.md" in PAGES


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_relative_links_resolve(page):
    assert not dangling(page), f"{page.relative_to(ROOT)}: links to nothing: {dangling(page)}"


def test_a_broken_link_is_found(tmp_path):
    (tmp_path / "a.md").write_text("# Title\n\n## The sweep's table\n")
    page = tmp_path / "p.md"
    page.write_text("[ok](a.md#the-sweeps-table) ![img](missing.png) [x](a.md#nope) `[code](nowhere.md)`\n"
                    "```\n[fenced](nowhere.md)\n```\n[web](https://example.org/x.md)\n")
    assert dangling(page) == ["missing.png", "a.md#nope (no such heading)"]
