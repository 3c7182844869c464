"""The README is a guide: its first screen has the two commands, every section fits a screen, every link resolves."""

import re

import pytest

from conftest import REPO

DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
SCREEN = 60   # lines


def sections(text):
    """(heading, line count) of each ``## `` section, fenced code included."""
    out, heading, count, fenced = [], None, 0, False
    for line in text.splitlines():
        fenced ^= line.startswith("```")
        if line.startswith("## ") and not fenced:
            if heading:
                out.append((heading, count))
            heading, count = line, 0
        count += 1
    return out + ([(heading, count)] if heading else [])


def test_the_first_screen_gives_the_two_commands():
    first = REPO.joinpath("README.md").read_text().splitlines()[:24]
    assert any(line.startswith("make run ") for line in first)
    assert any(line.startswith("make test ") for line in first)
    makefile = REPO.joinpath("Makefile").read_text()
    assert re.search(r"(?m)^run:", makefile) and re.search(r"(?m)^test:", makefile)


def test_no_readme_section_is_longer_than_a_screen():
    long = [(h, n) for h, n in sections(REPO.joinpath("README.md").read_text()) if n > SCREEN]
    assert not long, long


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_every_relative_link_resolves(doc):
    text = doc.read_text()
    anchors = {re.sub(r"[^\w\- ]", "", h.lower()).strip().replace(" ", "-")
               for h in re.findall(r"(?m)^#+ (.*)$", text)}
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if target.startswith(("http://", "https://", "mailto:")):
            continue
        path, _, anchor = target.partition("#")
        if path:
            assert (doc.parent / path).exists(), f"{doc.name}: link to {target} does not resolve"
        elif anchor:
            assert anchor in anchors, f"{doc.name}: no heading for #{anchor}"
