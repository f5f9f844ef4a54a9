"""The chapter pages' HTML: one layout (``templates/chapter.html``) filled with each page's own parts
(``templates/pages/<slug>.html``).

A page file holds only what is its own, as named blocks; each block starts with a line ``<!--block NAME-->`` and
runs to the next one. ``explain`` (the chapter's text) and ``legend`` (the map's legend entries) are required;
``heading`` (default "N · Title"), ``head`` (extra markup in <head>, e.g. a style), ``view`` (below the legend),
``side`` (below the numbers), ``after`` (below the view and the side), ``scripts`` (after lab.js) and
``canvas_height`` (pixels, default 540) are optional. The page title, the links to the previous and next chapters
and every element lab.js needs come from the layout and ``slam2d.web.pages.PAGES``. Standard library only
(``string.Template``): serving the lab needs no template engine.
"""

from __future__ import annotations

import html
import re
from functools import cache
from pathlib import Path
from string import Template

from slam2d.web.pages import PAGE_BY_SLUG, PAGES

TEMPLATES = Path(__file__).parent / "templates"
REQUIRED = ("explain", "legend")
OPTIONAL = {"heading": None, "head": "", "view": "", "side": "", "after": "", "scripts": "", "canvas_height": "540"}
_MARKER = re.compile(r"^<!--block ([a-z_]+)-->$")


def parse_blocks(text: str, source: str) -> dict[str, str]:
    """``<!--block NAME-->`` sections of a page file -> {name: content}; ValueError naming ``source``:line for an
    unknown or repeated block, text before the first block, or a missing required block."""
    blocks: dict[str, list[str]] = {}
    current: list[str] | None = None
    for n, line in enumerate(text.splitlines(keepends=True), start=1):
        m = _MARKER.match(line.strip())
        if m:
            name = m.group(1)
            if name not in REQUIRED and name not in OPTIONAL:
                raise ValueError(f"{source}:{n}: unknown block {name!r}; blocks: {[*REQUIRED, *OPTIONAL]}")
            if name in blocks:
                raise ValueError(f"{source}:{n}: block {name!r} appears twice")
            current = blocks[name] = []
        elif current is not None:
            current.append(line)
        elif line.strip():
            raise ValueError(f"{source}:{n}: text before the first <!--block NAME--> line")
    missing = [b for b in REQUIRED if b not in blocks]
    if missing:
        raise ValueError(f"{source}: missing block(s) {missing}")
    return {k: "".join(v) for k, v in blocks.items()}


def _nav(slug: str) -> str:
    i = next(k for k, p in enumerate(PAGES) if p.slug == slug)
    links = ['<a href="/">slam2d lab</a>']
    if i > 0:
        p = PAGES[i - 1]
        links.append(f'<a href="/lab/{p.slug}">← {p.number} {html.escape(p.title)}</a>')
    if i + 1 < len(PAGES):
        p = PAGES[i + 1]
        links.append(f'<a href="/lab/{p.slug}">{p.number} {html.escape(p.title)} →</a>')
    return " ".join(links)


@cache
def render_chapter(slug: str) -> str:
    """The full HTML of chapter page ``slug`` (KeyError for an unknown slug)."""
    page = PAGE_BY_SLUG[slug]
    path = TEMPLATES / "pages" / f"{slug}.html"
    blocks = parse_blocks(path.read_text(encoding="utf-8"), str(path))
    title = f"{page.number} · {html.escape(page.title)}"
    fill = {k: v for k, v in OPTIONAL.items() if v is not None}
    fill.update({k: v.rstrip("\n") if k in ("explain", "legend", "heading", "canvas_height") else v
                 for k, v in blocks.items()})
    fill.setdefault("heading", title)
    layout = Template((TEMPLATES / "chapter.html").read_text(encoding="utf-8"))
    return layout.substitute(fill, title=title, slug=slug, nav=_nav(slug))
