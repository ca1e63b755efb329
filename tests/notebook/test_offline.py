"""Reports that need no network (leglib.notebook.offline): TeX becomes MathML where it is
maths and stays as it is where it is code or money; the player's icons become characters."""

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook, new_output

from leglib import plots
from leglib.notebook import offline


def test_maths_in_markdown_becomes_mathml_and_code_and_prices_stay():
    text = ("The joint $q_1$, the ratio $$\\frac{l_1}{l_2}$$, code `$x$` and\n```\n$y$\n```\n"
            "a price of $5 and $6, and an escaped \\$z\\$.")
    out = offline.markdown_math(text)
    assert out.count("<math") == 2 and 'display="block"' in out and 'display="inline"' in out
    assert "<mi>q</mi>" in out and "<mfrac>" in out
    assert "`$x$`" in out and "\n$y$\n" in out            # code untouched
    assert "$5 and $6" in out and "\\$z\\$" in out        # not maths
    assert "$q_1$" not in out and "\\frac" not in out


def test_sympy_latex_outputs_get_mathml_html_and_a_bad_formula_says_so():
    html = offline.latex_output_html("$\\displaystyle \\left[\\begin{matrix}1 & 2\\end{matrix}\\right]$")
    assert html.startswith("<math") and 'display="block"' in html and "<mtable>" in html
    bad = offline.tex_to_mathml("\\begin{matrix} 1 & 2")   # never closed
    assert bad.startswith('<code class="leglib-tex" title="not converted')
    assert "\\begin{matrix}" in bad


def test_a_notebook_is_rewritten_in_place():
    nb = new_notebook(cells=[
        new_markdown_cell("$a^2$"),
        new_code_cell("x", outputs=[new_output("execute_result", data={"text/latex": "$\\displaystyle b$",
                                                                        "text/plain": "b"}, execution_count=1)]),
        new_code_cell("y", outputs=[new_output("display_data", data={"text/markdown": "| $c$ |\n|---|"})]),
        new_code_cell("z"),
    ])
    assert offline.offline_notebook(nb) == 3
    assert nb.cells[0].source.startswith("<math")
    assert nb.cells[1].outputs[0].data["text/html"].startswith("<math")
    assert nb.cells[1].outputs[0].data["text/latex"] == "$\\displaystyle b$"   # kept for other readers
    assert "<math" in nb.cells[2].outputs[0].data["text/markdown"]
    nbformat.validate(nb)


def test_the_players_icons_are_characters_and_its_cdn_link_goes():
    from matplotlib._animation_data import DISPLAY_TEMPLATE, STYLE_INCLUDE
    page = STYLE_INCLUDE + DISPLAY_TEMPLATE
    out = plots.player_html(page)
    assert "font-awesome" not in out and 'class="fa ' not in out
    assert out.count('class="leglib-icon"') == page.count('<i class="fa ') == 9
    assert set(plots.PLAYER_ICONS.values()) <= {m.split(">")[1].split("<")[0]
                                               for m in out.split('class="leglib-icon"')[1:]}


def test_a_table_without_a_blank_line_before_it_is_found():
    """Markdown renders a table only after a blank line: without one (notebook 04's ideal-step
    bias table once) it is a paragraph of pipes, which unrendered_tables finds in the HTML a
    report is written as; a rendered table, a pipe in prose or in code is not one."""
    from nbconvert.filters.markdown import markdown2html

    # the table as notebook 04 once wrote it
    glued = ("Ideal 48° steps, fd = 5 Hz: | true ζ | Listing 7.7 ζ | true fn [Hz] |\n|---|---|---|---|\n"
             "| | 0.050 | 0.351 | 5.01 |\n| | 0.100 | 0.182 | 5.03 |")
    apart = "Ideal 48° steps, fd = 5 Hz:\n\n| true ζ | Listing 7.7 ζ | true fn [Hz] |\n|---|---|---|\n| 0.050 | 0.351 | 5.01 |"
    found = offline.unrendered_tables(markdown2html(glued))
    assert len(found) == 1 and found[0].startswith("Ideal 48° steps, fd = 5 Hz: | true ζ |")
    assert "<table>" in markdown2html(apart) and offline.unrendered_tables(markdown2html(apart)) == []
    prose = markdown2html("a | b, and `| x | y |`\n\n```\n| c | d |\n|---|---|\n```")
    assert offline.unrendered_tables(prose) == []
    bullets = markdown2html("- rows:\n  | a | b |\n  | c | d |")
    assert offline.unrendered_tables(bullets)
