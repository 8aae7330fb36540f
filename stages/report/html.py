"""A self-contained HTML document: sections of tables and images, images inlined as data URIs.

Kept free of any templating dependency: the page is small and every value is escaped here.
The page carries a tiny script that checks, once loaded, that every image decoded; it
writes the result into ``#image-check`` so a headless browser test can read it back.
"""

from __future__ import annotations

import base64
import html
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ccc; padding-bottom: .2em; margin-top: 2em; }
table { border-collapse: collapse; margin: .5em 0 1em; font-size: .9em; }
th, td { border: 1px solid #ddd; padding: .25em .6em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
td.pass { background: #e3f6e3; } td.fail { background: #fbe3e3; } td.na { color: #999; }
figure { display: inline-block; margin: .5em; vertical-align: top; }
figure img { max-width: 560px; border: 1px solid #ddd; }
figure.wide { display: block; }
figure.wide img { max-width: 100%; }
figcaption { font-size: .85em; color: #555; }
.note { color: #666; font-size: .9em; }
"""

CHECK_SCRIPT = """
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var broken = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); });
  var out = document.getElementById('image-check');
  out.setAttribute('data-images', String(imgs.length));
  out.setAttribute('data-broken', String(broken.length));
  out.setAttribute('data-tables', String(document.querySelectorAll('table').length));
  out.textContent = imgs.length + ' images, ' + broken.length + ' broken';
});
"""


def png_data_uri(path: Path) -> str:
    """The PNG file as a ``data:`` URI (so the report needs no files beside it)."""
    return "data:image/png;base64," + base64.b64encode(Path(path).read_bytes()).decode("ascii")


@dataclass
class Table:
    """A table: header row, body rows of cells (str), optional CSS class per cell."""

    header: Sequence[str]
    rows: list[list[str]] = field(default_factory=list)
    classes: list[list[str]] = field(default_factory=list)
    table_id: str = ""

    def add(self, cells: Sequence[str], cell_classes: Sequence[str] | None = None) -> None:
        self.rows.append([str(c) for c in cells])
        self.classes.append(list(cell_classes) if cell_classes else [""] * len(cells))

    def render(self) -> str:
        head = "".join(f"<th>{html.escape(h)}</th>" for h in self.header)
        body = []
        for cells, classes in zip(self.rows, self.classes):
            tds = "".join(f'<td class="{c}">{html.escape(v)}</td>' if c else f"<td>{html.escape(v)}</td>"
                          for v, c in zip(cells, classes))
            body.append(f"<tr>{tds}</tr>")
        ident = f' id="{html.escape(self.table_id)}"' if self.table_id else ""
        return f"<table{ident}><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


@dataclass
class Section:
    """A titled part of the report holding paragraphs, tables and figures, in order."""

    title: str
    section_id: str
    parts: list[str] = field(default_factory=list)

    def paragraph(self, text: str, css: str = "") -> None:
        cls = f' class="{css}"' if css else ""
        self.parts.append(f"<p{cls}>{html.escape(text)}</p>")

    def table(self, table: Table) -> None:
        self.parts.append(table.render())

    def figure(self, png: Path, caption: str, wide: bool = False) -> None:
        """A picture with its caption (in words); ``wide`` shows it at its own size, not shrunk to a column."""
        css = ' class="wide"' if wide else ""
        self.parts.append(f'<figure{css}><img alt="{html.escape(caption)}" src="{png_data_uri(png)}">'
                          f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def render_document(title: str, subtitle: str, sections: Sequence[Section]) -> str:
    """The whole HTML page."""
    nav = " | ".join(f'<a href="#{s.section_id}">{html.escape(s.title)}</a>' for s in sections)
    body = "".join(f'<section id="{s.section_id}"><h2>{html.escape(s.title)}</h2>{"".join(s.parts)}</section>'
                   for s in sections)
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>"
            f"<p class='note'>{html.escape(subtitle)}</p><nav>{nav}</nav>{body}"
            f"<p class='note' id='image-check'></p><script>{CHECK_SCRIPT}</script></body></html>")
