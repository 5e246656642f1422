"""A static HTML report (one index.html beside its PNGs) that a quality engineer opens without reading code.

Small on purpose: sections of paragraphs, tables and figures, escaped text, no scripts except a check that every
image loaded (the rendering test reads it), no external resources.
"""

from __future__ import annotations

import html
import os
import pathlib
from collections.abc import Sequence
from dataclasses import dataclass, field

CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
h1 { border-bottom: 3px solid #2a6; } h2 { margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.8em 0; } td, th { border: 1px solid #ccc; padding: 3px 8px; }
th { background: #eef; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
figure { display: inline-block; margin: 0.5em; vertical-align: top; } figcaption { font-size: 0.85em; color: #555; }
img { max-width: 560px; border: 1px solid #ddd; } .bad { color: #b00; font-weight: bold; } .good { color: #070; }
.note { background: #ffd; padding: 0.5em 1em; border-left: 4px solid #cc0; }
"""

# Marks the page with how many images failed to load; tests/demo/test_report.py reads it in headless Chromium.
CHECK_SCRIPT = """
window.addEventListener('load', () => {
  const images = Array.from(document.images);
  const broken = images.filter(img => !(img.complete && img.naturalWidth > 0)).map(img => img.getAttribute('src'));
  document.body.dataset.images = images.length; document.body.dataset.broken = broken.join(' ');
});
"""


@dataclass
class Section:
    title: str
    parts: list[str] = field(default_factory=list)

    def text(self, paragraph: str, css: str = "") -> Section:
        cls = f' class="{css}"' if css else ""
        self.parts.append(f"<p{cls}>{html.escape(paragraph)}</p>")
        return self

    def table(self, headers: Sequence[str], rows: Sequence[Sequence[object]], caption: str = "") -> Section:
        head = "".join(f"<th>{html.escape(str(h))}</th>" for h in headers)
        body = "".join("<tr>" + "".join(_cell(value) for value in row) + "</tr>" for row in rows)
        cap = f"<caption>{html.escape(caption)}</caption>" if caption else ""
        self.parts.append(f"<table>{cap}<tr>{head}</tr>{body}</table>")
        return self

    def figures(self, images: Sequence[tuple[pathlib.Path, str]], root: pathlib.Path) -> Section:
        for path, caption in images:
            src = html.escape(os.path.relpath(path, root))
            self.parts.append(f'<figure><img src="{src}" alt="{html.escape(caption)}">'
                              f"<figcaption>{html.escape(caption)}</figcaption></figure>")
        return self


def _cell(value: object) -> str:
    """A table cell: numbers right-aligned with 4 decimals; (text, css-class) tuples styled."""
    if isinstance(value, tuple):
        text, css = value
        return f'<td class="{css}">{html.escape(str(text))}</td>'
    if isinstance(value, float):
        return f'<td class="num">{value:.4f}</td>'
    if isinstance(value, int) and not isinstance(value, bool):
        return f'<td class="num">{value}</td>'
    return f"<td>{html.escape(str(value))}</td>"


@dataclass
class Report:
    title: str
    subtitle: str = ""
    sections: list[Section] = field(default_factory=list)

    def section(self, title: str) -> Section:
        self.sections.append(Section(title))
        return self.sections[-1]

    def write(self, path: pathlib.Path) -> pathlib.Path:
        toc = "".join(f'<li><a href="#s{i}">{html.escape(s.title)}</a></li>' for i, s in enumerate(self.sections))
        body = "".join(f'<h2 id="s{i}">{html.escape(s.title)}</h2>' + "".join(s.parts)
                       for i, s in enumerate(self.sections))
        path.write_text(
            f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(self.title)}"
            f"</title><style>{CSS}</style><script>{CHECK_SCRIPT}</script></head><body>"
            f"<h1>{html.escape(self.title)}</h1><p>{html.escape(self.subtitle)}</p><ul>{toc}</ul>{body}</body></html>\n"
        )
        return path
