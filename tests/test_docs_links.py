"""Every relative link of README.md and docs/*.md reaches a file that exists, and a #fragment a
heading of that file (GitHub's anchor rule), so a page moved or a heading renamed shows here; every test
a page cites (`tests/FILE.py::Class::test_name`, or `tests/FILE.py` (`test_a`, `test_b`)) exists."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"(?<!\!)\[[^\]]*\]\(([^)\s]+)\)|!\[[^\]]*\]\(([^)\s]+)\)")


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation but '-' and '_' dropped, spaces to '-'."""
    text = re.sub(r"[`*]", "", heading.strip().lower())
    text = "".join(ch for ch in text if ch.isalnum() or ch in " -_")
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    out, seen, fenced = set(), {}, False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        m = None if fenced else re.match(r"#{1,6} (.+)", line)
        if m:
            base = slug(m.group(1))
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.add(base if n == 0 else f"{base}-{n}")
    return out


def links(page: Path) -> list[str]:
    text, fenced, found = page.read_text().splitlines(), False, []
    for line in text:
        if line.startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            for m in LINK.finditer(re.sub(r"`[^`]*`", "", line)):
                found.append(m.group(1) or m.group(2))
    return found


def test_slug_follows_github():
    assert slug("Ablation: what each part buys (`splat ablate`)") == "ablation-what-each-part-buys-splat-ablate"
    assert slug("Plane normals (`--loss.plane-normals`, preset rows `plane-normals`)") == \
        "plane-normals---lossplane-normals-preset-rows-plane-normals"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_resolve(page: Path):
    bad = []
    for target in links(page):
        if re.match(r"[a-z]+:", target):  # http(s), mailto: not checked here
            continue
        path, _, fragment = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            bad.append(f"{target} (no such file)")
        elif fragment and dest.suffix == ".md" and fragment not in anchors(dest):
            bad.append(f"{target} (no heading with that anchor in {dest.name})")
    assert not bad, f"{page.relative_to(REPO)}: " + "; ".join(bad)


CITED = re.compile(r"tests/(\w+\.py)((?:::[\w]+)+)")
CITED_LIST = re.compile(r"tests/(\w+\.py)` \(((?:`\w+`(?:, )?)+)\)")


def cited_tests(text: str) -> list[tuple[str, str]]:
    """(test file, name) for every test a page names, in either way it names them."""
    found = [(m.group(1), name) for m in CITED.finditer(text) for name in m.group(2).split("::")[1:]]
    found += [(m.group(1), name) for m in CITED_LIST.finditer(text) for name in re.findall(r"`(\w+)`", m.group(2))]
    return found


def test_cited_tests_are_found_in_either_form():
    text = "`tests/test_a.py::TestX::test_y` and `tests/test_b.py` (`test_c`, `test_d`)"
    assert cited_tests(text) == [("test_a.py", "TestX"), ("test_a.py", "test_y"), ("test_b.py", "test_c"),
                                 ("test_b.py", "test_d")]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_cited_tests_exist(page: Path):
    """A test renamed, moved to another file or deleted leaves the page citing it wrong."""
    bad = []
    for file, name in cited_tests(page.read_text()):
        path = REPO / "tests" / file
        if not path.is_file():
            bad.append(f"tests/{file} (no such file)")
        elif not re.search(rf"^\s*(?:def|class) {name}\b", path.read_text(), re.M):
            bad.append(f"tests/{file}::{name} (not defined there)")
    assert not bad, f"{page.relative_to(REPO)}: " + "; ".join(sorted(set(bad)))
