"""jsonschema's IRI checks load on first use (leglib.notebook.deferred): nbformat imports
without building rfc3987_syntax's parsers, and the checks answer as rfc3987_syntax does."""

import subprocess
import sys

import pytest

pytest.importorskip("rfc3987_syntax")

SCRIPT = r"""
import json, sys
import leglib.notebook                      # installs the stand-in
import nbformat                             # -> jsonschema -> its format checkers
loaded_at_import = "rfc3987_syntax.syntax_helpers" in sys.modules
import jsonschema
checker = jsonschema.FormatChecker()
values = ["http://example.com/\u00fc", "not an iri ::", "urn:isbn:0451450523", "", "http://[::1]:80/a?b#c",
          "ht tp://x", "//host/path", "#frag"]
checks = [[checker.conforms(v, fmt) for v in values] for fmt in ("iri", "iri-reference")]
from rfc3987_syntax.syntax_helpers import is_valid_syntax   # the real module, now imported
truth = [[is_valid_syntax(term, v) for v in values] for term in ("iri", "iri_reference")]
real = sys.modules["rfc3987_syntax"]
from leglib.notebook import deferred
print(json.dumps({"loaded_at_import": loaded_at_import, "checks": checks, "truth": truth,
                  "stand_in_left": bool(getattr(real, "_leglib_stand_in", False)),
                  "answers_after": deferred._FINDER.find_spec("rfc3987_syntax") is not None}))
"""


def test_nbformat_imports_without_the_iri_parsers_and_the_checks_answer_as_rfc3987_syntax():
    import json
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["loaded_at_import"] is False
    assert r["checks"] == r["truth"] and True in r["checks"][0] and False in r["checks"][0]
    assert r["stand_in_left"] is False          # sys.modules holds the real module after the first check
    assert r["answers_after"] is False          # and a later import finds the real module, not a stand-in


def test_the_stand_in_answers_only_its_own_name():
    from leglib.notebook import deferred
    assert deferred._FINDER.find_spec("jsonschema") is None
    assert deferred._FINDER.find_spec("rfc3987_syntax_nope") is None
