"""The suite's own marks. A mark decorates the function below it: written above a helper it
marks the helper, not the test that follows, and nothing says so. That test then misses its
``slow`` rank (tests/conftest.py runs the long tests first and ``-m "not slow"`` leaves them
out of the quick loop), so it runs late, in the quick loop, and at the end of the suite."""

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def _mark_name(decorator: ast.expr) -> str | None:
    """``"notebook"`` for ``@pytest.mark.notebook`` or ``@pytest.mark.notebook(...)``."""
    node = decorator.func if isinstance(decorator, ast.Call) else decorator
    if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute)
            and node.value.attr == "mark" and isinstance(node.value.value, ast.Name)
            and node.value.value.id == "pytest"):
        return node.attr
    return None


def marks_on_helpers(source: str) -> list[tuple[int, str, str]]:
    """(line, mark, function) for every ``pytest.mark`` on a function pytest does not
    collect (a name not starting with ``test``)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("test"):
            found += [(d.lineno, name, node.name) for d in node.decorator_list if (name := _mark_name(d))]
    return found


def test_a_mark_on_a_helper_is_found():
    source = ("import pytest\n\n@pytest.mark.notebook\ndef _helper():\n    pass\n\n"
              "@pytest.mark.slow\n@pytest.mark.parametrize('x', [1])\ndef test_x(x):\n    pass\n")
    assert marks_on_helpers(source) == [(3, "notebook", "_helper")]


def test_no_mark_decorates_a_helper():
    found = [f"{path.relative_to(TESTS.parent)}:{line}: @pytest.mark.{mark} on {name}()"
             for path in sorted(TESTS.rglob("*.py"))
             for line, mark, name in marks_on_helpers(path.read_text())]
    assert not found, "marks on functions pytest does not collect:\n" + "\n".join(found)
