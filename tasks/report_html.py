"""One self-contained HTML page from figures, tables and PNG pictures (``btf report``).

Pure: it takes bytes and text and returns text. Pictures are embedded as ``data:`` URLs, the
style is inline, there is no script and no network reference, so the page opens the same in
any browser, offline, and can be mailed or archived as one file.
"""

from __future__ import annotations

import base64
import html
import re
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Picture:
    """A PNG and its caption."""

    caption: str
    png: bytes


@dataclass(frozen=True)
class Table:
    """A header row and rows of cells (already formatted as text)."""

    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]


@dataclass(frozen=True)
class Section:
    """A part of the page: a title, paragraphs, links, tables, pictures, commands."""

    title: str
    paragraphs: tuple[str, ...] = ()
    tables: tuple[Table, ...] = ()
    pictures: tuple[Picture, ...] = ()
    commands: tuple[str, ...] = field(default=())
    links: tuple[tuple[str, str], ...] = ()  # (text, address), after the paragraphs


NUMBER = re.compile(r"^-?[\d.,]+( ?(x|%|s|MiB|GiB))?$")  # right-aligned cells

STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 72em; color: #222;
       padding: 0 1em; }
h1 { font-size: 1.6em; } h2 { font-size: 1.25em; margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.8em 0; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; }
td.n { text-align: right; font-variant-numeric: tabular-nums; }
.pictures { display: flex; flex-wrap: wrap; gap: 0.8em; }
figure { margin: 0; } figcaption { font-size: 0.85em; color: #555; max-width: 16em; }
img { image-rendering: pixelated; width: 16em; height: auto; border: 1px solid #ddd; }
pre { background: #f4f4f4; padding: 0.6em; overflow-x: auto; font-size: 0.85em; }
"""


def _cell(text: str, tag: str) -> str:
    cls = ' class="n"' if tag == "td" and NUMBER.match(text) else ""
    return f"<{tag}{cls}>{html.escape(text)}</{tag}>"


def _table(table: Table) -> str:
    head = "".join(_cell(h, "th") for h in table.header)
    body = "".join("<tr>" + "".join(_cell(c, "td") for c in row) + "</tr>"
                   for row in table.rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _picture(p: Picture) -> str:
    data = base64.b64encode(p.png).decode("ascii")
    caption = html.escape(p.caption)
    return (f'<figure><img src="data:image/png;base64,{data}" alt="{caption}">'
            f"<figcaption>{caption}</figcaption></figure>")


def render(title: str, intro: str, sections: list[Section]) -> str:
    """The page."""
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
             f"<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>",
             f"<h1>{html.escape(title)}</h1>", f"<p>{html.escape(intro)}</p>"]
    for s in sections:
        parts.append(f"<h2>{html.escape(s.title)}</h2>")
        parts += [f"<p>{html.escape(t)}</p>" for t in s.paragraphs]
        parts += [f'<p><a href="{html.escape(href)}">{html.escape(text)}</a></p>'
                  for text, href in s.links]
        parts += [_table(t) for t in s.tables]
        if s.pictures:
            parts.append('<div class="pictures">' + "".join(map(_picture, s.pictures))
                         + "</div>")
        if s.commands:
            parts.append("<pre>" + html.escape("\n".join(s.commands)) + "</pre>")
    parts.append("</body></html>")
    return "\n".join(parts)
