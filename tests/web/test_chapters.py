"""The chapter pages' HTML: one layout filled with each page's own blocks (slam2d.web.chapters)."""

from __future__ import annotations

import re

import pytest

from slam2d.web.chapters import TEMPLATES, parse_blocks, render_chapter
from slam2d.web.pages import PAGES

#: what lab.js looks up on every chapter page
LAB_IDS = ("world", "status", "notices", "controls", "numbers", "errors")


@pytest.mark.parametrize("slug", [p.slug for p in PAGES])
def test_every_chapter_renders_the_shared_markup_once_with_its_own_parts(slug: str) -> None:
    page = next(p for p in PAGES if p.slug == slug)
    text = render_chapter(slug)
    assert f'<body data-page="{slug}">' in text
    assert f"<title>{page.number} · {page.title} — slam2d lab</title>" in text
    for id_ in LAB_IDS:
        assert text.count(f'id="{id_}"') == 1, id_
    assert text.count('<script type="module" src="/static/js/lab.js"></script>') == 1
    assert not re.search(r"\$\{(title|slug|nav|heading|head|explain|legend|view|side|after|scripts|canvas_height)\}",
                         text) and "<!--block" not in text
    own = parse_blocks((TEMPLATES / "pages" / f"{slug}.html").read_text(), slug)
    assert own["legend"].strip() in text and own["explain"].strip() in text


def test_chapter_navigation_links_the_previous_and_next_chapter() -> None:
    for i, page in enumerate(PAGES):
        header = re.search(r"<header>(.*)</header>", render_chapter(page.slug)).group(1)  # type: ignore[union-attr]
        links = re.findall(r'href="([^"]+)"', header)
        want = ["/"] + ([f"/lab/{PAGES[i - 1].slug}"] if i else []) + (
            [f"/lab/{PAGES[i + 1].slug}"] if i + 1 < len(PAGES) else [])
        assert links == want, page.slug


def test_page_files_keep_only_their_own_markup() -> None:
    """The shared layout is not repeated in a page file."""
    for page in PAGES:
        text = (TEMPLATES / "pages" / f"{page.slug}.html").read_text()
        for shared in ("<html", "<head>", "lab.css", 'id="controls"', 'id="numbers"', "lab.js", "<header>"):
            assert shared not in text, (page.slug, shared)


def test_bad_page_files_are_refused_with_file_and_line() -> None:
    with pytest.raises(ValueError, match=r"x.html:3: unknown block 'sidebar'"):
        parse_blocks("<!--block explain-->\n<p>a</p>\n<!--block sidebar-->\n", "x.html")
    with pytest.raises(ValueError, match=r"x.html:1: text before the first"):
        parse_blocks("<p>a</p>\n<!--block explain-->\n", "x.html")
    with pytest.raises(ValueError, match=r"x.html:3: block 'explain' appears twice"):
        parse_blocks("<!--block explain-->\na\n<!--block explain-->\n", "x.html")
    with pytest.raises(ValueError, match=r"x.html: missing block\(s\) \['legend'\]"):
        parse_blocks("<!--block explain-->\na\n", "x.html")
    assert parse_blocks("<!--block explain-->\na\n<!--block legend-->\nb\n", "x.html") == {"explain": "a\n",
                                                                                         "legend": "b\n"}
