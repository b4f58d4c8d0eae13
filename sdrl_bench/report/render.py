"""The report as a list of blocks, rendered twice: Markdown (images as relative files, for a
code host) and one self-contained HTML file (images embedded as base64, equations rendered as
math images by matplotlib's mathtext: no CDN, no network)."""

from __future__ import annotations

import base64
import html
import io
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Sequence

NOT_RUN = "not run"
MISSING = "missing"


@dataclass(frozen=True)
class Cell:
    """One table cell: its text and, optionally, the link it carries (a run in the MLflow UI)."""

    text: str
    url: str | None = None
    runs: bool = False
    """The row's runs column: the one cell whose link the Markdown keeps (numbers stay plain text
    there, so the file reads in a terminal; the HTML links every number)."""


@dataclass
class Heading:
    level: int
    text: str


@dataclass
class Para:
    """A paragraph; `code` spans and [text](url) links are kept in both renderings."""

    text: str


@dataclass
class Table:
    columns: list[str]
    rows: list[list[Cell]]
    caption: str = ""


@dataclass
class Image:
    """A figure file inside the report folder."""

    path: Path
    caption: str


@dataclass
class Equations:
    """A fitted model's equations (one per line, ``x[k+1] = 1 x +0.0015 u ...``)."""

    caption: str
    lines: list[str] = field(default_factory=list)


Block = Heading | Para | Table | Image | Equations


# ---------------------------------------------------------------------- numbers
def fmt(value: object, kind: str = "g", empty: str = NOT_RUN) -> str:
    """A number as the report prints it; None/NaN print as ``empty`` ("not run" or "missing").
    Kinds: "g" (4 significant digits), "e" (scientific, 4 significant digits), "int"
    (thousands separated), "f1", "f2", "f3" (fixed), "pct" (percent). A metric is never shown
    with fewer than 4 significant digits in "g" and "e" (the tests compare them with the store)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return empty
    if isinstance(value, str):
        return value
    v = float(value)  # type: ignore[arg-type]
    if kind == "int":
        return f"{v:,.0f}"
    if kind == "e":
        return f"{v:.3e}"
    if kind in ("f1", "f2", "f3"):
        return f"{v:.{kind[1]}f}"
    if kind == "pct":
        return f"{100 * v:.0f}%"
    return f"{v:.4g}"


# ---------------------------------------------------------------------- Markdown
def _md_cell(c: Cell) -> str:
    text = c.text.replace("|", "\\|")
    return f"[{text}]({c.url})" if c.url and c.runs else text


def render_markdown(blocks: Sequence[Block], folder: Path) -> str:
    """Markdown with images linked relative to ``folder`` (the report's own folder)."""
    out: list[str] = []
    for b in blocks:
        if isinstance(b, Heading):
            out.append(f"{'#' * b.level} {b.text}\n")
        elif isinstance(b, Para):
            out.append(b.text + "\n")
        elif isinstance(b, Table):
            if b.caption:
                out.append(f"*{b.caption}*\n")
            out.append("| " + " | ".join(b.columns) + " |")
            out.append("|" + "---|" * len(b.columns))
            out.extend("| " + " | ".join(_md_cell(c) for c in row) + " |" for row in b.rows)
            out.append("")
        elif isinstance(b, Image):
            out.append(f"![{b.caption}]({b.path.relative_to(folder).as_posix()})\n\n*{b.caption}*\n")
        elif isinstance(b, Equations):
            out.append(f"*{b.caption}*\n\n```\n" + "\n".join(b.lines) + "\n```\n")
    return "\n".join(out)


# ---------------------------------------------------------------------- HTML
_INLINE = re.compile(r"`([^`]+)`|\[([^\]]+)\]\(([^)\s]+)\)")


def _inline_html(text: str) -> str:
    out, pos = [], 0
    for m in _INLINE.finditer(text):
        out.append(html.escape(text[pos:m.start()]))
        if m.group(1) is not None:
            out.append(f"<code>{html.escape(m.group(1))}</code>")
        else:
            out.append(f'<a href="{html.escape(m.group(3))}">{html.escape(m.group(2))}</a>')
        pos = m.end()
    out.append(html.escape(text[pos:]))
    return "".join(out)


_FUNCS = {"sin", "cos", "tan", "exp", "log", "tanh", "sqrt"}


def to_mathtext(equation: str) -> str:
    """A SINDy equation line as matplotlib mathtext: ``x[k+1]`` becomes x subscript k+1,
    names become upright text, ``*`` a thin space, known functions their operators."""
    eq = re.sub(r"([A-Za-z_]\w*)\[k\+1\]", "\\1\x00", equation.strip())
    eq = re.sub(r"(\d) 1(?=\s|$)", r"\1", eq)  # the constant feature "1" after its coefficient

    def name(m: re.Match) -> str:
        word = m.group(0)
        if word in _FUNCS:
            return "\\" + word
        return "\\mathrm{" + word.replace("_", "\\_") + "}"

    eq = re.sub(r"(?<![\d.])[A-Za-z_]\w*", name, eq)
    eq = eq.replace("\x00", "_{k+1}").replace("*", "\\,").replace("%", "\\%")
    eq = re.sub(r"(?<=\d)e([+-]?\d+)", r"\\times10^{\1}", eq)
    return re.sub(r"(?<=[}\w)]) (?=\\(?:mathrm|sin|cos|tan|exp|log|tanh|sqrt)\b)", r"\\,", eq)  # visible products


def _split_terms(equation: str, per_line: int = 6) -> list[str]:
    """Long right-hand sides wrapped after every ``per_line`` terms."""
    lhs, _, rhs = equation.partition("=")
    terms = re.split(r"\s(?=[+-]\s?\d)", rhs.strip())
    chunks = [" ".join(terms[i:i + per_line]) for i in range(0, len(terms), per_line)] or [""]
    return [f"{lhs.strip()} = {chunks[0]}"] + [f"\\quad {c}" for c in chunks[1:]]


def equation_png(equation: str, dpi: int = 110) -> bytes | None:
    """The equation rendered by matplotlib mathtext as PNG bytes; None if it cannot parse."""
    from matplotlib import mathtext

    buf = io.BytesIO()
    try:
        mathtext.math_to_image(f"${equation}$", buf, dpi=dpi, format="png")
    except Exception:  # a term mathtext does not parse: the caller shows the plain text
        return None
    return buf.getvalue()


def _equations_html(b: Equations) -> str:
    parts = [f"<figure class='eq'><figcaption>{_inline_html(b.caption)}</figcaption>"]
    for line in b.lines:
        for piece in _split_terms(line):
            cont = piece.startswith("\\quad ")
            tex = "\\quad " + to_mathtext(piece[len("\\quad "):]) if cont else to_mathtext(piece)
            png = equation_png(tex)
            if png is None:
                parts.append(f"<pre>{html.escape(piece)}</pre>")
            else:
                data = base64.b64encode(png).decode()
                parts.append(f"<div><img class='math' alt='{html.escape(piece)}' src='data:image/png;base64,{data}'></div>")
    # the same equations as plain text, to copy
    parts.append("<pre class='eqtext'>" + html.escape("\n".join(b.lines)) + "</pre>")
    parts.append("</figure>")
    return "\n".join(parts)


_STYLE = """body{font-family:system-ui,sans-serif;max-width:1500px;margin:2em auto;padding:0 1em;color:#222}
div.scroll{overflow-x:auto;margin:.5em 0 1.5em}
table{border-collapse:collapse;font-size:.85em}th,td{border:1px solid #ccc;padding:3px 6px;text-align:right}
td{white-space:nowrap}td:last-child{white-space:normal;text-align:left;min-width:16em}
th{background:#f2f2f2}td:first-child,th:first-child{text-align:left}figure{margin:1em 0}
img.fig{max-width:100%;border:1px solid #ddd}img.math{margin:2px 0}code{background:#f4f4f4;padding:0 3px}
figcaption{font-style:italic;color:#555;margin:.3em 0}.caption{font-style:italic;color:#555}
pre.eqtext{white-space:pre-wrap;font-size:.85em;background:#f8f8f8;padding:.4em}"""


def render_html(blocks: Sequence[Block], title: str) -> str:
    """One self-contained HTML page: styles inline, images embedded as base64."""
    out = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
           f"<style>{_STYLE}</style></head><body>"]
    for b in blocks:
        if isinstance(b, Heading):
            out.append(f"<h{b.level}>{_inline_html(b.text)}</h{b.level}>")
        elif isinstance(b, Para):
            out.append(f"<p>{_inline_html(b.text)}</p>")
        elif isinstance(b, Table):
            if b.caption:
                out.append(f"<p class='caption'>{_inline_html(b.caption)}</p>")
            out.append("<div class='scroll'><table><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in b.columns) + "</tr>")
            for row in b.rows:
                cells = [f"<a href='{html.escape(c.url)}'>{html.escape(c.text)}</a>" if c.url else html.escape(c.text)
                         for c in row]
                out.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
            out.append("</table></div>")
        elif isinstance(b, Image):
            data = base64.b64encode(b.path.read_bytes()).decode()
            out.append(f"<figure><img class='fig' alt='{html.escape(b.caption)}' src='data:image/png;base64,{data}'>"
                       f"<figcaption>{html.escape(b.caption)}</figcaption></figure>")
        elif isinstance(b, Equations):
            out.append(_equations_html(b))
    out.append("</body></html>")
    return "\n".join(out)
