import os

os.environ.setdefault("MPLBACKEND", "Agg")

import pytest  # noqa: E402

from leglib.params import load_leg  # noqa: E402


@pytest.fixture(scope="session")
def leg():
    return load_leg("thesis")
