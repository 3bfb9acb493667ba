"""Report content as plain blocks, rendered to Markdown (images linked) and HTML (embedded)."""

from __future__ import annotations

import base64
import html
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class Para:
    text: str


@dataclass
class Note:
    """A stage whose outputs are missing: "not run yet: run `biopsynav <stage> CASE`"."""

    text: str


@dataclass
class Image:
    path: Path
    caption: str


@dataclass
class GridTable:
    """A table: ``header`` (n,), ``rows`` of n strings."""

    header: list[str]
    rows: list[list[str]]


@dataclass
class Pre:
    text: str


@dataclass
class Section:
    """A titled part of the report; ``folded`` shows only its title until opened (HTML)."""

    title: str
    blocks: list = field(default_factory=list)
    level: int = 2
    folded: bool = False


CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1100px;
margin:2em auto;padding:0 1em;color:#222;line-height:1.45}
h1{border-bottom:2px solid #446;padding-bottom:.2em}h2{border-bottom:1px solid #ccd;
margin-top:2em}table{border-collapse:collapse;margin:.6em 0;font-size:.92em}
td,th{border:1px solid #ccd;padding:.25em .6em;text-align:right}th{background:#eef}
td:first-child,th:first-child{text-align:left}img{max-width:100%;border:1px solid #ddd}
figure{margin:1em 0}figcaption{font-size:.9em;color:#555}
.note{background:#fff6dd;border-left:4px solid #e0a800;padding:.5em .8em}
pre{background:#f6f6f8;padding:.6em;overflow-x:auto;font-size:.85em}
details{margin-top:2em}summary{font-size:1.3em;font-weight:bold;cursor:pointer;
border-bottom:1px solid #ccd}
code{background:#f0f0f4;padding:0 .2em}
"""


def to_markdown(title: str, sections: list[Section], base: Path) -> str:
    """Markdown with images linked relative to ``base`` (the case folder)."""
    out = [f"# {title}", ""]
    for s in sections:
        out += [f"{'#' * s.level} {s.title}", ""]
        for b in s.blocks:
            out += _md_block(b, base) + [""]
    return "\n".join(out)


def _md_block(b, base: Path) -> list[str]:
    if isinstance(b, Para):
        return [b.text]
    if isinstance(b, Note):
        return [f"> **{b.text}**"]
    if isinstance(b, Image):
        return [f"![{b.caption}]({_relative(b.path, base)})", "", f"*{b.caption}*"]
    if isinstance(b, GridTable):
        cells = [[c.replace("|", "\\|") for c in row] for row in [b.header, *b.rows]]
        lines = ["| " + " | ".join(cells[0]) + " |",
                 "|" + "|".join(":---" if i == 0 else "---:" for i in range(len(b.header)))
                 + "|"]
        return lines + ["| " + " | ".join(r) + " |" for r in cells[1:]]
    if isinstance(b, Pre):
        return ["```", b.text, "```"]
    raise TypeError(type(b))


def _relative(path: Path, base: Path) -> str:
    try:
        return Path(path).resolve().relative_to(Path(base).resolve()).as_posix()
    except ValueError:
        return Path(path).name


def to_html(title: str, sections: list[Section]) -> str:
    """Self-contained HTML: inline CSS, images as base64 data URIs, no external reference."""
    body = [f"<h1>{html.escape(title)}</h1>"]
    for s in sections:
        head, blocks = html.escape(s.title), [_html_block(b) for b in s.blocks]
        if s.folded:
            body += [f"<details><summary>{head}</summary>", *blocks, "</details>"]
        else:
            body += [f"<h{s.level}>{head}</h{s.level}>", *blocks]
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{html.escape(title)}</title><style>{CSS}</style></head>\n<body>\n"
            + "\n".join(body) + "\n</body></html>\n")


def _inline_code(text: str) -> str:
    """Escape text and turn `code` spans into <code> elements."""
    parts = html.escape(text).split("`")
    return "".join(f"<code>{p}</code>" if i % 2 else p for i, p in enumerate(parts))


def _html_block(b) -> str:
    if isinstance(b, Para):
        return f"<p>{_inline_code(b.text)}</p>"
    if isinstance(b, Note):
        return f"<p class=\"note\">{_inline_code(b.text)}</p>"
    if isinstance(b, Image):
        data = base64.b64encode(Path(b.path).read_bytes()).decode("ascii")
        return (f"<figure><img alt=\"{html.escape(b.caption)}\" "
                f"src=\"data:image/png;base64,{data}\"><figcaption>{html.escape(b.caption)}"
                "</figcaption></figure>")
    if isinstance(b, GridTable):
        head = "".join(f"<th>{html.escape(c)}</th>" for c in b.header)
        rows = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>"
                       for r in b.rows)
        return f"<table><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>"
    if isinstance(b, Pre):
        return f"<pre>{html.escape(b.text)}</pre>"
    raise TypeError(type(b))
