"""A result read from a file shows where it came from, and a "Made by an older version"
notice once a commit since changed the code it depends on (leglib.notebook.sources over
leglib._version.staleness), for every kind a notebook reads: a sweep, an identified leg, a
saved design, the robustness table."""

import json
import subprocess

import pytest

from leglib import _version
from leglib import model as M
from leglib.design import saved
from leglib.design import statefeedback as SF
from leglib.notebook import sources
from leglib.params import load_leg


@pytest.fixture
def repo(tmp_path):
    """A git checkout with a file in each part of leglib a result can depend on; returns
    (root, git, first commit)."""
    root = tmp_path / "repo"

    def git(*args):
        return subprocess.run(["git", "-C", str(root), *args], check=True, capture_output=True,
                              text=True).stdout.strip()

    for rel in ("leglib/twin/kernel.py", "leglib/identify/friction.py", "leglib/design/statefeedback.py",
                "leglib/design/gainmap.py", "leglib/notebook/widgets.py", "README.md"):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text("a = 1\n")
    git("init", "-q")
    git("config", "user.email", "t@example.org")
    git("config", "user.name", "t")
    git("add", ".")
    git("commit", "-q", "-m", "first")
    return root, git, git("rev-parse", "HEAD")


def _change(root, git, rel, message):
    (root / rel).write_text((root / rel).read_text() + "b = 2\n")
    git("commit", "-q", "-am", message)


def test_staleness_counts_only_the_code_a_result_depends_on(repo):
    root, git, first = repo
    deps = ("leglib/twin",)
    assert _version.staleness(first, deps, repo=root) is None
    _change(root, git, "README.md", "docs only")
    _change(root, git, "leglib/notebook/widgets.py", "a panel")
    assert _version.staleness(first, deps, repo=root) is None
    _change(root, git, "leglib/twin/kernel.py", "the twin's friction changes")
    notice = _version.staleness(first, deps, what="This sweep", rerun="Measure it again.", repo=root)
    assert notice == (f"Made by an older version: 1 commit(s) since {first[:7]} changed the code it depends on "
                      f"(latest: {git('rev-parse', '--short', 'HEAD')} the twin's friction changes). Measure it again.")
    # it says when it cannot tell
    assert "does not say which commit" in _version.staleness(None, deps, what="This sweep", repo=root)
    assert "does not say which commit" in _version.staleness("unknown", deps, repo=root)
    assert "does not have" in _version.staleness("0123abc", deps, repo=root)
    assert "git is not available" in _version.staleness(first, deps, repo=root / "nowhere")


def _sweep(directory, commit, backend="virtual"):
    directory.mkdir()
    name = "20261202_070740_lg0bbca83aafe9_batch"
    (directory / f"{name}.csv").write_text("t\n0\n")
    (directory / f"{name}.json").write_text(json.dumps({
        "git_commit": commit, "leglib_version": "0.1.0", "backend": backend, "twin_seed": 11,
        "twin_plant": "leglib/params/plant_default.toml"}))
    (directory / "sweep.json").write_text(json.dumps({"device": {"backend": backend}, "git_commit": commit}))
    return directory


def test_a_sweep_says_who_measured_it_and_that_the_twin_changed_since(repo, tmp_path):
    root, git, first = repo
    s = sources.sweep(_sweep(tmp_path / "sweep", first), repo=root)
    assert s.notice is None and not s.stale
    assert s.commits == {first: 1} and s.dates == ("2026-12-02 07:07", "2026-12-02 07:07")
    assert "backend virtual" in s.text() and "plant default" in s.text() and "seed 11" in s.text()
    _change(root, git, "leglib/identify/friction.py", "identification only")      # not the sweep's code
    assert sources.sweep(tmp_path / "sweep", repo=root).notice is None
    _change(root, git, "leglib/twin/kernel.py", "the twin changes")
    s = sources.sweep(tmp_path / "sweep", repo=root)
    assert s.stale and "the twin changes" in s.notice
    assert s.markdown().startswith("**Made by an older version") and s.to_dict()["stale"] is True
    # measured on the real leg: the twin's changes do not make it older
    real = sources.sweep(_sweep(tmp_path / "real", first, backend="usb"), repo=root)
    assert real.notice is None


def test_an_identified_leg_without_a_commit_or_from_an_older_one_says_so(repo, tmp_path):
    root, git, first = repo
    path = tmp_path / "friction_identified.json"
    path.write_text(json.dumps({"backend": "virtual", "leg": {}, "friction": {}}))
    s = sources.identified(path, repo=root)
    assert "does not say which commit made it" in s.notice and not s.stale
    path.write_text(json.dumps({"backend": "virtual", "provenance": {"git_commit": first, "date": "2026-12-02T07:05:24"}}))
    assert sources.identified(path, repo=root).notice is None
    _change(root, git, "leglib/identify/friction.py", "friction fit changes")
    s = sources.identified(path, repo=root)
    assert s.stale and "friction fit changes" in s.notice and "notebook 02_friction_fitting" in s.notice
    assert "2026-12-02 07:05" in s.text()


def test_a_saved_design_from_an_older_commit_shows_its_notice(repo, tmp_path):
    root, git, first = repo
    d = SF.place_poles(M.linearize(load_leg("thesis")))
    path = saved.save(tmp_path / "design.json", d, linearization={"leg": "thesis"})
    doc = json.loads(path.read_text())
    doc["provenance"]["git_commit"] = first
    path.write_text(json.dumps(doc))
    s = sources.design(path, repo=root)
    assert s.notice is None and s.what == "The saved state-feedback design"
    _change(root, git, "leglib/design/gainmap.py", "the map changes")       # not a state-feedback design's code
    assert sources.design(path, repo=root).notice is None
    _change(root, git, "leglib/design/statefeedback.py", "placement changes")
    assert sources.design(path, repo=root).stale


def test_the_robustness_table_goes_through_the_same_check(repo):
    root, git, first = repo
    doc = {"commit": first[:7], "date": "2026-12-01T10:50:36+00:00", "payload": 0.0}
    s = sources.table(doc, "robustness.json", repo=root)
    assert s.notice is None and "payload 0 kg" in s.text()
    _change(root, git, "leglib/design/gainmap.py", "the map changes")
    s = sources.table(doc, "robustness.json", repo=root)
    assert s.stale and "make robustness" in s.notice and "the code it scores" in s.notice
