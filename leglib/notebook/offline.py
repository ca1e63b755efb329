"""Reports that work without internet: the maths as MathML, the animation player's buttons
as characters; and :func:`unrendered_tables`, the check that a report's tables rendered.

nbconvert's HTML leaves TeX in the page for MathJax, which it loads from a CDN, and
matplotlib's animation player draws its buttons with Font Awesome, also from a CDN: opened
offline (a report mailed to a supervisor, a lab PC) the equations show as raw
``$\\displaystyle ...$`` and the buttons are blank. Here the TeX is turned into MathML once,
when the report is written (latex2mathml; browsers render MathML themselves), and the
player's icons into Unicode characters, so a report needs nothing from the network.
"""

from __future__ import annotations

import re

from ..plots import player_html

# $$...$$ (display) or $...$ (inline), not after a backslash; code is set apart first
_MATH = re.compile(r"(?<!\\)\$\$(.+?)(?<!\\)\$\$|(?<![\\$])\$(?!\s)([^$\n]+?)(?<![\s\\])\$(?!\d)", re.S)
_CODE = re.compile(r"(```.*?```|~~~.*?~~~|`[^`\n]*`)", re.S)


def tex_to_mathml(tex: str, display: bool = False) -> str:
    """One formula (without its dollars) as a MathML ``<math>`` element."""
    from latex2mathml.converter import convert  # load time: latex2mathml, only when a report is written

    tex = tex.strip()
    if tex.startswith(r"\displaystyle"):
        tex, display = tex[len(r"\displaystyle"):], True
    try:
        return convert(tex, display="block" if display else "inline")
    except Exception as exc:  # noqa: BLE001 - any parser failure: the formula stays as TeX, said in the page
        return f'<code class="leglib-tex" title="not converted: {type(exc).__name__}">{_escape(tex)}</code>'


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def markdown_math(text: str) -> str:
    """Markdown with every ``$...$`` and ``$$...$$`` outside code replaced by MathML."""
    def math(m):
        display = m.group(1) is not None
        return tex_to_mathml(m.group(1) if display else m.group(2), display=display)

    parts = _CODE.split(text)
    return "".join(p if k % 2 else _MATH.sub(math, p) for k, p in enumerate(parts))


def latex_output_html(latex: str) -> str:
    """A ``text/latex`` output (sympy's ``$\\displaystyle ...$``) as HTML with MathML."""
    s = latex.strip()
    if s.startswith("$$") and s.endswith("$$"):
        return tex_to_mathml(s[2:-2], display=True)
    if s.startswith("$") and s.endswith("$"):
        return tex_to_mathml(s[1:-1], display=False)
    return markdown_math(s)


def _text(value) -> str:
    return "".join(value) if isinstance(value, list) else str(value)


def offline_notebook(nb) -> int:
    """Rewrite an executed notebook (nbformat node, in place) for an offline report: the maths
    of markdown cells and of markdown and LaTeX outputs as MathML, players without Font
    Awesome. Returns the number of cells changed."""
    changed = 0
    for cell in nb.cells:
        before = str(cell)
        if cell.cell_type == "markdown":
            cell.source = markdown_math(_text(cell.source))
        for out in cell.get("outputs", []):
            data = out.get("data", {})
            if "text/html" in data:
                data["text/html"] = player_html(_text(data["text/html"]))
            elif "text/latex" in data:
                data["text/html"] = latex_output_html(_text(data["text/latex"]))
            elif "text/markdown" in data:
                data["text/markdown"] = markdown_math(_text(data["text/markdown"]))
        changed += str(cell) != before
    return changed


# ---------------------------------------------------------------------------------------
# tables that did not render
# ---------------------------------------------------------------------------------------

# a Markdown table's separator row (|---|:---:|), or a row of cells (| a | b |)
_SEPARATOR = re.compile(r"^\s*\|?\s*:?-{3,}:?\s*(\|\s*:?-{3,}:?\s*)+\|?\s*$")
_ROW = re.compile(r"^\s*\|.*\|.*\|\s*$")
_PROSE = re.compile(r"<(p|li)\b[^>]*>(.*?)</\1>", re.S)
_TAG = re.compile(r"<[^>]+>")


def unrendered_tables(html: str) -> list[str]:
    """Markdown tables an HTML report shows as text: a paragraph or list item holding a
    table's separator row (``|---|---|``) or two or more rows of cells. Markdown renders a
    table only when a blank line sets it apart from the text before it; without one, the
    table is a paragraph of pipes. Returns the start of each such text."""
    found = []
    for m in _PROSE.finditer(html):
        text = _TAG.sub("", m.group(2))
        lines = [ln for ln in text.splitlines() if ln.strip()]
        if any(_SEPARATOR.match(ln) for ln in lines) or sum(bool(_ROW.match(ln)) for ln in lines) >= 2:
            found.append(" ".join(text.split())[:80])
    return found
