"""Batch re-runs: a 6-run grid on a Dask LocalCluster, failures reported, reruns skipped."""

import json
import os
import sys
import threading
import time

import pytest

from leglib.notebook import batch

SPEC = """
name = "{name}"
notebooks = ["01_derivation"]
[parameters]
smoke = true
[grid]
torque_step = [0.002, 0.006]
grid_n = [{bad}, 6]
"""


@pytest.fixture(scope="module")
def cluster():
    dd = pytest.importorskip("dask.distributed")
    c = dd.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    yield c
    c.close()


@pytest.mark.notebook
def test_four_runs_on_a_local_cluster_with_a_failure_and_a_rerun(tmp_path, cluster):
    """Four runs of notebook 01 on two worker processes (more runs than workers), two of
    them refused by the notebook: each failure is its run's alone and named; the rerun
    retries only those. (Six runs, three of each, cost a third more and showed nothing more.)"""
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC.format(name="demo", bad=2))  # grid_n = 2 is refused by notebook 01
    results = batch.run_batch(spec, tmp_path / "out", cluster=cluster, progress=False)
    assert len(results) == 4
    done = [r for r in results.values() if r["status"] == "done"]
    failed = [r for r in results.values() if r["status"] == "failed"]
    assert len(done) == 2 and len(failed) == 2
    for r in failed:
        assert r["notebook"] == "01_derivation" and r["cell"] is not None
        assert "grid_n" in r["error"]
    for r in done:
        assert r["metrics"]["01_derivation"]["eq511_max_rel_error"] < 0.01
    root = tmp_path / "out" / "demo"
    index = (root / "index.html").read_text()
    assert index.count("<tr>") == 5 and "failed" in index
    assert (root / "summary.png").stat().st_size > 1000
    # a rerun skips the finished runs and retries the failed ones
    stamps = {p: (json.loads(p.read_text())["status"], p.stat().st_mtime_ns) for p in root.glob("*/status.json")}
    again = batch.run_batch(spec, tmp_path / "out", cluster=cluster, progress=False)
    assert sorted(s for s, _ in stamps.values()) == ["done", "done", "failed", "failed"]
    for p, (status, t) in stamps.items():
        assert (p.stat().st_mtime_ns == t) == (status == "done"), (p, status)   # only the failed ones ran again
    assert sorted(r["status"] for r in again.values()) == ["done", "done", "failed", "failed"]


def test_bad_specs_are_named(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('name = "x"\nnotebooks = ["99_nope"]\n')
    with pytest.raises(batch.SpecError, match="notebook '99_nope' not found"):
        batch.load_spec(p)
    p.write_text('notebooks = ["01_derivation"]\n')
    with pytest.raises(batch.SpecError, match="field 'name'"):
        batch.load_spec(p)
    # a parameter no notebook of the spec takes would be dropped silently: refused
    p.write_text('name = "x"\nnotebooks = ["01_derivation"]\n[grid]\nseed = [1, 2]\n')
    with pytest.raises(batch.SpecError, match=r"grid\.seed is not a parameter of 01_derivation"):
        batch.load_spec(p)
    p.write_text('name = "x"\nnotebooks = ["04_pid_sweeps", "05_validation"]\n[grid]\npayload_mass = [0.0]\n')
    assert batch.load_spec(p)["grid"] == {"payload_mass": [0.0]}


def test_cli_reports_a_bad_spec_without_a_traceback(tmp_path, capsys):
    from leglib.notebook.cli import main
    p = tmp_path / "s.toml"
    p.write_text('name = "x"\nnotebooks = ["01_derivation"]\n[parameters]\npayload = 1.0\n')
    assert main(["batch", str(p), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "parameters.payload is not a parameter of 01_derivation" in err
    assert not (tmp_path / "out").exists()  # nothing ran


@pytest.mark.parametrize("text,message", [
    ('name = "x"\nnotebooks = ["01_derivation"]\nnotebook = ["02_friction_fitting"]\n',
     "unknown key 'notebook'; did you mean 'notebooks'?"),
    ('name = "x"\nnotebooks = ["01_derivation"]\n[parameter]\nsmoke = true\n',
     "unknown key 'parameter'; did you mean 'parameters'?"),
    ('name = ".."\nnotebooks = ["01_derivation"]\n', "field 'name' must be a plain directory name"),
    ('name = "a/b"\nnotebooks = ["01_derivation"]\n', "field 'name' must be a plain directory name"),
    ('name = "' + "a" * 300 + '"\nnotebooks = ["01_derivation"]\n', "at most 64 characters"),
    ('name = "x"\nnotebooks = ["../notebooks/01_derivation"]\n', "is not a notebook name"),
    ('name = "x"\nnotebooks = [1]\n', "1 is not a notebook name"),
    ('name = "x"\nnotebooks = ["01_derivation"]\n[parameters]\nsmoke = "no"\n',
     "parameters.smoke = 'no': expected bool"),
    ('name = "x"\nnotebooks = ["01_derivation"]\n[grid]\ngrid_n = [6, 6]\n', "grid.grid_n repeats a value"),
    ('name = "x"\nnotebooks = ["01_derivation"]\n[grid]\ngrid_n = [6.5]\n', "grid.grid_n = 6.5: expected int"),
    ('name = "x"\nnotebooks = ["01_derivation"]\n[parameters]\ngrid_n = 6\n[grid]\ngrid_n = [7]\n',
     "grid_n is both in [parameters] and in [grid]"),
    ('name = "x"\nnotebooks = ["01_derivation"]\n[parameters]\ngird_n = 6\n', "did you mean 'grid_n'?"),
])
def test_spec_refuses_unknown_keys_bad_names_and_types(tmp_path, text, message):
    p = tmp_path / "s.toml"
    p.write_text(text)
    with pytest.raises(batch.SpecError) as err:
        batch.load_spec(p)
    assert message in str(err.value) and str(p) in str(err.value)
    assert len(str(err.value)) < 500


@pytest.mark.parametrize("values", ["[0, 0.0]", "[0.5, 0.25, 0.50]", "[1, 1.0, 2]"])
def test_grid_values_repeat_by_value(tmp_path, values):
    """0 and 0.0 are one payload: a grid naming both would run the same point twice."""
    p = tmp_path / "s.toml"
    p.write_text(f'name = "x"\nnotebooks = ["04_pid_sweeps"]\n[grid]\npayload_mass = {values}\n')
    with pytest.raises(batch.SpecError, match=r"grid\.payload_mass repeats a value") as err:
        batch.load_spec(p)
    assert str(p) in str(err.value)
    p.write_text('name = "x"\nnotebooks = ["04_pid_sweeps"]\n[grid]\npayload_mass = [0, 0.5]\n')
    assert len(batch.runs_of(batch.load_spec(p))) == 2


@pytest.mark.parametrize("table,key", [("parameters", "figures_dir"), ("parameters", "metrics_path"),
                                       ("grid", "figures_dir"), ("grid", "metrics_path")])
def test_parameters_the_batch_sets_are_refused(tmp_path, table, key):
    """A run's figures and metrics go to its own directory: a spec's own value would be
    silently replaced, so it is refused with the reason."""
    value = '"/tmp/mine"' if table == "parameters" else '["/tmp/a", "/tmp/b"]'
    p = tmp_path / "s.toml"
    p.write_text(f'name = "x"\nnotebooks = ["04_pid_sweeps"]\n[{table}]\n{key} = {value}\n')
    with pytest.raises(batch.SpecError) as err:
        batch.load_spec(p)
    msg = str(err.value)
    assert str(p) in msg and f"{table}.{key}" in msg and "the batch sets it" in msg


def test_every_problem_of_a_spec_in_one_message(tmp_path):
    """Three typos: one error that names the file and all three fields, not one per try."""
    p = tmp_path / "s.toml"
    p.write_text('name = "x"\nnotebook = ["04_pid_sweeps"]\nnotebooks = ["04_pid_sweeps"]\n'
                 '[parameters]\nsmok = true\n[grid]\npaylod_mass = [0.0, 0.5]\n')
    with pytest.raises(batch.SpecError) as err:
        batch.load_spec(p)
    msg = str(err.value)
    assert msg.startswith(f"{p}: 3 problems: ")
    assert "unknown key 'notebook'; did you mean 'notebooks'?" in msg
    assert "parameters.smok is not a parameter" in msg and "did you mean 'smoke'?" in msg
    assert "grid.paylod_mass is not a parameter" in msg and "did you mean 'payload_mass'?" in msg
    assert "\n" not in msg and len(msg) < 600
    # many problems: still one bounded message that says how many
    lines = ['name = "a/b"', 'notebooks = ["04_pid_sweeps"]', "[parameters]"]
    lines += [f"bogus_{k} = {k}" for k in range(40)]
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(batch.SpecError) as err:
        batch.load_spec(p)
    msg = str(err.value)
    assert msg.startswith(f"{p}: 41 problems: ") and "field 'name'" in msg and "more" in msg
    assert len(msg) < 600 + len(str(p))


def test_spec_that_is_not_a_readable_utf8_file(tmp_path):
    p = tmp_path / "s.toml"
    p.write_bytes('name = "caf\u00e9"\nnotebooks = ["01_derivation"]\n'.encode("latin-1"))
    with pytest.raises(batch.SpecError, match=r":1: not UTF-8 text \(byte 0xe9\)"):
        batch.load_spec(p)
    d = tmp_path / "dir.toml"
    d.mkdir()
    with pytest.raises(batch.SpecError, match="not a regular file"):
        batch.load_spec(d)


def test_run_ids_are_plain_directory_names():
    spec = {"name": "x", "notebooks": ["04_pid_sweeps"], "parameters": {},
            "grid": {"plant": ["../../etc", "a" * 300]}}
    ids = [r["id"] for r in batch.runs_of(spec)]
    assert len(set(ids)) == 2
    assert all("/" not in i and len(i) <= 90 and i not in (".", "..") for i in ids)


def test_index_shows_the_payload_study_answer(tmp_path):
    """The index of the payload spec: notebook 05's errors against the payload (with units),
    not the alphabetically first metrics; every run linked to its reports."""
    spec = batch.load_spec("data/batch_payload.toml")
    runs = batch.runs_of(spec)
    results = {}
    for k, r in enumerate(runs):
        (tmp_path / r["id"]).mkdir()
        for nb in spec["notebooks"]:
            (tmp_path / r["id"] / f"{nb}.html").write_text("<html></html>")
        err = 0.01 * (k + 1)  # errors growing with the payload, as a study would show
        results[r["id"]] = {"status": "done", "params": r["params"], "metrics": {
            "04_pid_sweeps": {"achievable": 100, "bldc": {"x": {"zeta": 1.0}}, "counts": {"ok": 300, "unstable": 30},
                              "map_s": 0.5, "sweep_s": 2.0},
            "05_validation": {"summary": {"map": {"median": err, "worst": 2 * err},
                                          "model": {"median": err / 2, "worst": err}},
                              "thesis_target": {"error_zeta": -err, "error_fn": err / 3}}}}
        (tmp_path / r["id"] / "status.json").write_text(json.dumps(results[r["id"]]))
    index = batch.write_index(tmp_path, runs, results, spec["notebooks"]).read_text()
    assert "payload_mass [kg]" in index
    assert "05: map method: median error [%]" in index and "05: model method: worst error [%]" in index
    assert "bldc" not in index and "map_s" not in index and "sweep_s" not in index
    for k, r in enumerate(runs):
        assert f"<a href='{r['id']}/05_validation.html'>" in index and f"<a href='{r['id']}/status.json'>" in index
        assert f"<td>{100 * 0.01 * (k + 1):.4g}</td>" in index  # the map's median error in %
    assert (tmp_path / "summary.png").stat().st_size > 5000
    vals = batch.summary_values(results[runs[-1]["id"]])
    assert vals[("05_validation", "map method: worst error", "%")] == pytest.approx(2 * 0.01 * len(runs) * 100)


# -- a distributed batch when workers die --------------------------------------------------------

_RELEASE = threading.Event()


def _hanging_run(notebooks, params, out_dir):
    """A run that lasts until the test releases it (its worker is closed meanwhile)."""
    _RELEASE.wait(60)
    return {"status": "done", "params": params, "metrics": {}}


def _run_or_die(notebooks, params, out_dir):
    """A run that kills its worker process (grid_n 7) or finishes after a while."""
    if params["grid_n"] == 7:
        os._exit(1)
    time.sleep(3.0)
    return {"status": "done", "params": params, "metrics": {}}


def _spec(values):
    return {"name": "dying", "notebooks": ["01_derivation"], "parameters": {}, "grid": {"grid_n": values}}


@pytest.mark.slow
def test_a_batch_whose_workers_all_die_ends_with_the_runs_pending(tmp_path, monkeypatch, capsys):
    """Every worker gone: the batch does not wait forever; it says so, records the runs not
    finished as pending with the reason and writes the index."""
    dd = pytest.importorskip("dask.distributed")
    monkeypatch.setattr(batch, "run_one", _hanging_run)
    _RELEASE.clear()
    cluster = dd.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None)
    try:
        def close_worker():
            time.sleep(1.0)
            worker = next(iter(cluster.workers.values()))
            cluster.sync(worker.close)

        killer = threading.Thread(target=close_worker, daemon=True)
        killer.start()
        t0 = time.monotonic()
        results = batch.run_batch(_spec([6, 7, 8]), tmp_path, cluster=cluster, progress=False,
                                  no_worker_timeout=2.0)
        assert time.monotonic() - t0 < 25
    finally:
        _RELEASE.set()
        cluster.close()
    assert len(results) == 3
    for r in results.values():
        assert r["status"] == "pending" and "no Dask worker was alive for 2 s" in r["error"]
    assert "no Dask worker was alive for 2 s; 3 run(s) left pending" in capsys.readouterr().err
    root = tmp_path / "dying"
    index = (root / "index.html").read_text()
    assert index.count("<tr>") == 4 and index.count("pending") >= 3
    for run_id in results:
        assert json.loads((root / run_id / "status.json").read_text())["status"] == "pending"


@pytest.mark.slow
def test_a_killed_worker_fails_its_run_only(tmp_path, monkeypatch):
    """A run whose worker died more often than the scheduler allows (KilledWorker) is
    recorded failed with the reason; the run on the healthy worker is recorded done; the
    index is written; nothing raises."""
    dd = pytest.importorskip("dask.distributed")
    import cloudpickle
    import dask

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    monkeypatch.setattr(batch, "run_one", _run_or_die)
    try:
        with dask.config.set({"distributed.scheduler.allowed-failures": 0,
                              "distributed.scheduler.worker-saturation": 1.0}):
            cluster = dd.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
            try:
                results = batch.run_batch(_spec([6, 7]), tmp_path, cluster=cluster, progress=False,
                                          no_worker_timeout=20.0)
            finally:
                cluster.close()
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    by_n = {r["params"]["grid_n"]: (k, r) for k, r in results.items()}
    assert by_n[6][1]["status"] == "done"
    killed_id, killed = by_n[7]
    assert killed["status"] == "failed" and killed["error"].startswith("KilledWorker: the Dask worker running")
    root = tmp_path / "dying"
    assert json.loads((root / killed_id / "status.json").read_text())["status"] == "failed"
    index = (root / "index.html").read_text()
    assert index.count("<tr>") == 3 and "KilledWorker" in index
