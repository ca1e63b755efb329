import os

from leglib.device.virtual import wire as F

os.environ.setdefault("MPLBACKEND", "Agg")

import pytest  # noqa: E402

from leglib.params import load_leg  # noqa: E402


@pytest.fixture(scope="session")
def leg():
    return load_leg("thesis")


@pytest.fixture(scope="session")
def processed(tmp_path_factory):
    """Notebook 02 run once (smoke): its output directory and metrics. Its identified leg
    (``processed/friction_identified.json``) is what notebook 03 reads."""
    import json

    from leglib.notebook.run import execute, notebook_paths

    nb02 = notebook_paths()[1]
    out = tmp_path_factory.mktemp("nb02")
    execute(nb02, out, {"smoke": True, "raw_dir": str(out / "raw"), "processed_dir": str(out / "processed")},
            html=False)
    return out, json.loads((out / "metrics" / f"{nb02.stem}.json").read_text())


@pytest.fixture(autouse=True)
def _fresh_virtual_devices():
    """Each test starts without virtual ODrives: they live for the process under their
    seed (leglib.virtual_odrive.find_any), so tests would otherwise share devices."""
    F.forget()
    yield
