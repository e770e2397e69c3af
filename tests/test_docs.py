"""The README and docs/ link only to files inside the repository, and those files exist.

Someone who clones the repository has nothing beside it (no ``../shared``), so a relative
link that leaves the checkout, or names a file that is not there, is broken for them.
Links inside code (fenced blocks and inline spans) are text, not links, and are skipped;
links with a scheme (``https:``, ``mailto:``) and pure anchors (``#...``) are not checked.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

_FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,}).*?^ {0,3}\1[^\S\n]*$", re.MULTILINE | re.DOTALL)
_CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1", re.DOTALL)
#: ``[text](target "title")`` and ``![alt](target)``; the text may hold one level of brackets.
_INLINE = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*(<[^>]*>|[^\s)]+)(?:\s+[\"'(][^)]*)?\)")
#: ``[label]: target`` reference definitions.
_REFERENCE = re.compile(r"^ {0,3}\[[^\]]+\]:\s*(<[^>]*>|\S+)", re.MULTILINE)
_HTML = re.compile(r"""\b(?:href|src)\s*=\s*["']([^"']+)["']""", re.IGNORECASE)
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")


def link_targets(markdown: str) -> list[str]:
    """The link targets of a Markdown text, outside code, in order of appearance."""
    text = _FENCE.sub("", markdown)
    text = _CODE_SPAN.sub("", text)
    found = [(m.start(), m.group(1)) for m in _INLINE.finditer(text)]
    found += [(m.start(), m.group(1)) for m in _REFERENCE.finditer(text)]
    found += [(m.start(), m.group(1)) for m in _HTML.finditer(text)]
    return [target.strip("<>") for _, target in sorted(found)]


def broken_links(document: Path, root: Path = ROOT) -> list[str]:
    """The relative links of ``document`` that leave ``root`` or name no existing file."""
    root = root.resolve()
    problems = []
    for target in link_targets(document.read_text(encoding="utf-8")):
        if _SCHEME.match(target) or target.startswith("#"):
            continue
        path_part = target.split("#", 1)[0].split("?", 1)[0]
        resolved = (document.parent / path_part).resolve()
        if not resolved.is_relative_to(root):
            problems.append(f"{target}: leaves the repository")
        elif not resolved.exists():
            problems.append(f"{target}: no such file in the repository")
    return problems


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_stay_in_the_repository_and_exist(document: Path) -> None:
    assert broken_links(document) == []


def test_the_method_and_the_formats_are_documented_in_the_repository() -> None:
    readme = link_targets((ROOT / "README.md").read_text(encoding="utf-8"))
    assert "docs/method.md" in readme and "docs/formats.md" in readme
    for document in DOCUMENTS:
        assert "../shared/METHOD.md" not in document.read_text(encoding="utf-8")
        assert "../shared/FORMAT.md" not in document.read_text(encoding="utf-8")


def test_link_targets_reads_links_and_skips_code() -> None:
    text = "\n".join(
        [
            "See [`docs/a.md`](docs/a.md) and ![figure](img/b.png 'title'), [c][ref].",
            'A [link [with] brackets](c.md#part) and <a href="d.html">d</a>.',
            "[ref]: <e.md>",
            "Code is not a link: `[x](f.md)`, nor is",
            "```sh",
            "cat [y](g.md)",
            "```",
            "[web](https://example.org/h.md) [anchor](#i)",
        ]
    )
    assert link_targets(text) == [
        "docs/a.md",
        "img/b.png",
        "c.md#part",
        "d.html",
        "e.md",
        "https://example.org/h.md",
        "#i",
    ]


def test_broken_links_are_found(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "here.md").write_text("x")
    document = tmp_path / "README.md"
    document.write_text(
        "[ok](docs/here.md#top) [gone](docs/missing.md) [out](../shared/METHOD.md) "
        "[web](https://example.org) [anchor](#top)"
    )
    assert broken_links(document, tmp_path) == [
        "docs/missing.md: no such file in the repository",
        "../shared/METHOD.md: leaves the repository",
    ]
