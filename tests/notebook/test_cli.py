"""The command line's bad arguments: one line on stderr, exit code 2, no traceback; --help
lists the choices and defaults."""

import subprocess
import sys
from pathlib import Path

import pytest

from leglib.notebook.cli import main
from leglib.params import plant_names

REPO = Path(__file__).resolve().parents[2]
SPEC = 'name = "x"\nnotebooks = ["01_derivation"]\n[grid]\ngrid_n = [6, 7]\n'


def _exit_code(argv):
    try:
        return main(argv)
    except SystemExit as exc:  # argparse's own errors and --help
        return exc.code


def _one_error_line(err: str) -> str:
    assert "Traceback" not in err and err.strip(), err
    last = err.strip().splitlines()[-1]
    assert "error: " in last
    return last


def test_help_lists_the_choices_and_defaults(capsys):
    assert _exit_code(["robustness", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    names = plant_names()
    assert names and all(n in out for n in names)
    assert "(default: reports/robustness)" in out and "0 to 5" in out and "(default: 0)" in out
    assert _exit_code(["batch", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    for text in ("(default: reports/batch)", "(default: 2)", "(default: none, local processes)",
                 "(default: 10 s)", "(default: 120 s)"):
        assert text in out, text
    assert _exit_code(["run", "--help"]) == 0
    assert "(default: reports)" in capsys.readouterr().out


@pytest.mark.parametrize("payload", ["1e9", "-1", "nan", "inf", "heavy"])
def test_robustness_refuses_a_payload_out_of_range(capsys, payload):
    assert _exit_code(["robustness", "--payload", payload, "--out", "/nonexistent/never"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "argument --payload" in line and payload in line


def test_robustness_refuses_an_unknown_plant(capsys):
    assert _exit_code(["robustness", "--plants", "default", "nope"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "invalid choice: 'nope'" in line and "default" in line


@pytest.mark.parametrize("value", ["0", "-3", "many"])
def test_batch_refuses_a_worker_count(tmp_path, capsys, value):
    spec = tmp_path / "s.toml"
    spec.write_text(SPEC)
    assert _exit_code(["batch", str(spec), "--workers", value]) == 2
    assert "argument --workers" in _one_error_line(capsys.readouterr().err)


@pytest.mark.parametrize("address,message", [
    ("foo://host:1", "unknown address scheme 'foo'"),
    ("nonsense", "missing port number"),
    ("tcp://a b:1", "not a scheduler address"),
    ("tcp://127.0.0.1:1", "Timed out trying to connect"),
])
def test_batch_reports_a_bad_scheduler_in_one_line(tmp_path, capsys, address, message):
    spec = tmp_path / "s.toml"
    spec.write_text(SPEC)
    out = tmp_path / "out"
    code = _exit_code(["batch", str(spec), "--out", str(out), "--scheduler", address, "--connect-timeout", "1"])
    line = _one_error_line(capsys.readouterr().err)
    assert code == 2
    assert line.startswith(f"error: --scheduler {address}") or line.startswith(f"error: --scheduler {address!r}")
    assert message in line
    assert not (out / "x").exists()  # nothing ran


@pytest.mark.slow
def test_an_unreachable_scheduler_from_the_shell(tmp_path):
    """The whole command: one line on stderr, exit code 2, nothing complaining at exit."""
    spec = tmp_path / "s.toml"
    spec.write_text(SPEC)
    proc = subprocess.run([sys.executable, "-m", "leglib", "batch", str(spec), "--out", str(tmp_path / "out"),
                           "--scheduler", "tcp://127.0.0.1:1", "--connect-timeout", "1"],
                          capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "error: --scheduler tcp://127.0.0.1:1: cannot connect (Timed out trying to connect to "
        "tcp://127.0.0.1:1 after 1 s)"], proc.stderr


@pytest.mark.parametrize("command", [["run"], ["batch", "SPEC"], ["robustness"]])
def test_an_unwritable_out_is_one_line(tmp_path, capsys, command):
    spec = tmp_path / "s.toml"
    spec.write_text(SPEC)
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    argv = [str(spec) if a == "SPEC" else a for a in command]
    for out, reason in ((blocker / "out", "Not a directory"), (blocker, "exists and is not a directory")):
        assert _exit_code([*argv, "--out", str(out)]) == 2
        line = _one_error_line(capsys.readouterr().err)
        assert line.startswith(f"error: --out {out}") and reason in line


def _quick_run(notebooks, params, out_dir):
    return {"status": "done", "params": params, "metrics": {}}


def test_batch_on_a_live_scheduler(tmp_path, monkeypatch, capsys):
    """A scheduler that answers: the runs go to it and the index is written."""
    dd = pytest.importorskip("dask.distributed")
    from leglib.notebook import batch
    monkeypatch.setattr(batch, "run_one", _quick_run)
    spec = tmp_path / "s.toml"
    spec.write_text(SPEC)
    with dd.LocalCluster(n_workers=1, processes=False, protocol="tcp://", dashboard_address=None) as cluster:
        code = main(["batch", str(spec), "--out", str(tmp_path / "out"), "--scheduler", cluster.scheduler_address])
    out = capsys.readouterr().out
    assert code == 0 and "2 runs done, 0 failed or not run" in out
    assert (tmp_path / "out" / "x" / "index.html").exists()


# ---------------------------------------------------------------------------------------
# python -m leglib design
# ---------------------------------------------------------------------------------------

def test_design_help_lists_the_defaults(capsys):
    assert _exit_code(["design", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    for text in ("{virtual,usb}", "(default: virtual)", "(default: 0.24)", "(default: 5)", "(default: 10)",
                 "1 to 50", "longest run allowed on the real leg [min] (default: 5)", "(default: thesis)",
                 "(default: 10 s)", "(default: not saved)", "Exit code 0 when the target was reached, 1 when not"):
        assert text in out, text
    assert all(n in out for n in plant_names())


@pytest.mark.parametrize("argv, where", [
    (["--zeta", "-1"], "argument --zeta"), (["--fn", "0"], "argument --fn"), (["--fn", "many"], "argument --fn"),
    (["--max-experiments", "0"], "argument --max-experiments"), (["--max-minutes", "0"], "argument --max-minutes"),
    (["--backend", "serial"], "argument --backend"), (["--plant", "nope"], "argument --plant"),
    (["--leg", "nope"], "no parameter set named 'nope'"), (["--odrive-config", "nope"], "odrive_nope.toml"),
    (["--backend", "usb", "--seed", "3"], "--seed, --plant and --payload are the twin's"),
])
def test_design_refuses_a_bad_argument_in_one_line(capsys, argv, where):
    assert _exit_code(["design", *argv]) == 2
    assert where in _one_error_line(capsys.readouterr().err)


def test_design_on_the_twin_reports_the_rehearsal_and_saves(tmp_path, capsys):
    from leglib.design import saved
    path = tmp_path / "designs" / "leg.json"
    code = main(["design", "--seed", "5", "--max-experiments", "4", "--save", str(path)])
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].startswith("rehearsal on the twin: on the leg this run will do the configuration saved (1 reboot), "
                               "2 axes calibrated, 4 steps: about 4")
    assert any(ln.startswith("target zeta 0.24, fn 5 Hz: reached in") for ln in lines) == (code == 0)
    assert any(ln.startswith("Rehearsal on the twin: on the leg this run would do 1 configuration saved, 1 reboot, "
                             "2 axes calibrated") for ln in lines)
    d = saved.load(path, kind="cascade_gains")
    assert d.method == "tune" and d.target == (0.24, 5.0) and f"wrote {path}" in out
    # the final check's (zeta, fn) is stored with its 90 % intervals and printed with them
    if d.measured is not None:
        (zl, zh), (fl, fh) = d.measured_intervals
        assert zl <= d.measured[0] <= zh and fl <= d.measured[1] <= fh
        assert f"wrote {path}: {d}" in out and d.measured_text() in out and "no interval" not in d.measured_text()
    # every experiment's line and table row says its intervals
    steps = [ln for ln in lines if ln.startswith("  experiment ")]
    assert steps and all(ln.endswith(("(90 % intervals)", "-> failed", "-> unstable")) for ln in steps), steps


@pytest.fixture
def twin_on_usb(monkeypatch, tmp_path):
    """``odrive.find_any`` answers with the virtual board of seed 26 (leglib's USB code path)."""
    import functools
    odrive = pytest.importorskip("odrive")
    from leglib.device.virtual import find_any
    monkeypatch.setenv("LEGLIB_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.setattr(odrive, "find_any", functools.partial(find_any, seed=26))


def test_design_on_the_leg_is_refused_past_its_limit_with_the_estimate(twin_on_usb, capsys):
    assert _exit_code(["design", "--backend", "usb", "--max-experiments", "50", "--max-minutes", "1"]) == 2
    captured = capsys.readouterr()
    line = _one_error_line(captured.err)
    assert line.startswith("error: this run (the configuration saved (1 reboot), 2 axes calibrated, 50 steps) takes "
                           "about 3.") and "set --max-minutes to at least 4 to run it" in line
    assert "configure:" not in captured.out                # refused before anything was done


def test_design_on_the_leg_runs_within_its_limit(twin_on_usb, capsys):
    code = main(["design", "--backend", "usb", "--max-experiments", "2"])
    out = capsys.readouterr().out
    assert code in (0, 1)
    assert out.startswith("on the leg: the configuration saved (1 reboot), 2 axes calibrated, 2 steps: about ")
    # a fresh board has the firmware's defaults: pole_pairs, cpr and torque_constant (motor.hpp:19,24,
    # encoder.hpp:27) on both axes, brake_resistance (board.h:41) and enable_brake_resistor differ
    assert "configure: 8 stored value(s) differ" in out and "calibrate: axis0 and axis1 calibrated" in out
    assert "On the leg: 1 configuration saved, 1 reboot, 2 axes calibrated, " in out
