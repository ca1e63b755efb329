"""Notebooks 03 and 04 as a person uses them: JupyterLab in headless Chromium, Run All, one
slider moved with the keyboard; the readout must show exactly what leglib computes for the
new slider value, and the plot must be redrawn. Screenshots go to reports/browser/.

Needs Debian's chromium (``make test`` installs it as root). Outside CI the test skips when
it is missing; with CI=true it fails instead."""

from __future__ import annotations

import ast
import inspect
import json
import os
import secrets
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
import warnings
from pathlib import Path

import conftest
import pytest

from leglib import model as M
from leglib.design import statefeedback as SF
from leglib.notebook import widgets
from leglib.notebook.run import REPO, notebook_paths

# one JupyterLab for the file: under pytest-xdist (make test) its tests stay on one worker
pytestmark = [pytest.mark.browser, pytest.mark.xdist_group("lab")]

CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run"]
SCREENSHOTS = REPO / "reports" / "browser"
RUN_TIMEOUT_S = 300


CHROMIUM = Path("/usr/bin/chromium")  # Debian's package


def _chromium() -> str:
    path = shutil.which("chromium") or (str(CHROMIUM) if CHROMIUM.exists() else None)
    if path is None:
        msg = (f"no Chromium found (looked for `chromium` on PATH and {CHROMIUM}); "
               "install it with `apt-get install chromium` (make test does this when run as root)")
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(msg + " -- CI must run the browser test")
        pytest.skip(msg)
    return path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _notebook(prefix: str) -> Path:
    return next(p for p in notebook_paths() if p.name.startswith(prefix))


def _defaults(path: Path) -> dict:
    import papermill as pm
    return {k: ast.literal_eval(v["default"]) for k, v in pm.inspect_notebook(str(path)).items()}


@pytest.mark.parametrize("ci, outcome", [("", pytest.skip.Exception), ("true", pytest.fail.Exception)])
def test_missing_chromium_skips_outside_ci_and_fails_in_ci(monkeypatch, tmp_path, ci, outcome):
    monkeypatch.setattr(sys.modules[__name__], "CHROMIUM", tmp_path / "chromium")
    monkeypatch.setattr(shutil, "which", lambda name: None)
    monkeypatch.setenv("CI", ci)
    with pytest.raises(outcome, match="no Chromium found"):
        _chromium()


@pytest.fixture(scope="module")
def lab(tmp_path_factory, processed):
    """A JupyterLab server on 127.0.0.1 with a token, serving notebooks 03 and 04 prepared
    (not run) with papermill: smoke mode and every output under a temporary directory."""
    import papermill as pm

    chromium = _chromium()
    for old in [*SCREENSHOTS.glob("*.png"), SLIDER_TIMES]:  # of an earlier run, not of this one
        old.unlink(missing_ok=True)
    root = tmp_path_factory.mktemp("lab")
    out = root / "out"
    prepared = {
        # the panel is what these tests are about, not the runs before it: 1 s experiments, not 4.5 s
        "03": {"smoke": True, "identified_path": str(processed[0] / "processed" / "friction_identified.json"),
               "processed_dir": str(out / "processed"), "duration": 1.0},
        "04": {"smoke": True, "sweep_dir": str(out / "sweep04"), "processed_dir": str(out / "processed")},
    }
    metrics = {}
    for prefix, params in prepared.items():
        nb = _notebook(prefix)
        metrics[prefix] = out / "metrics" / f"{nb.stem}.json"
        params.update(figures_dir=str(out / "figures"), metrics_path=str(metrics[prefix]))
        pm.execute_notebook(str(nb), str(root / nb.name), parameters=params, prepare_only=True,
                            progress_bar=False)
    token = secrets.token_hex(16)
    port = _free_port()
    env = {k: v for k, v in os.environ.items() if k != "MPLBACKEND"}  # the kernel draws inline
    for var, sub in (("JUPYTER_RUNTIME_DIR", "runtime"), ("JUPYTERLAB_WORKSPACES_DIR", "workspaces"),
                     ("JUPYTERLAB_SETTINGS_DIR", "settings"), ("JUPYTER_CONFIG_DIR", "config")):
        env[var] = str(root / ".jupyter" / sub)
    # no news feed or update check: nothing to fetch offline, no toast over the notebook
    settings = root / ".jupyter" / "settings" / "@jupyterlab" / "apputils-extension"
    settings.mkdir(parents=True)
    (settings / "notification.jupyterlab-settings").write_text(
        json.dumps({"fetchNews": "false", "checkForUpdates": False}))
    log = open(root / "jupyterlab.log", "w")
    with conftest.on_any_core():   # the server and its kernels: not on this worker's core alone
        server = subprocess.Popen(
            [sys.executable, "-m", "jupyterlab", "--no-browser", "--ip=127.0.0.1", f"--port={port}",
             f"--IdentityProvider.token={token}", f"--ServerApp.root_dir={root}",
             "--ServerApp.port_retries=0"] + (["--allow-root"] if os.geteuid() == 0 else []),
            env=env, stdout=log, stderr=subprocess.STDOUT, cwd=root)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 90
        while True:
            if server.poll() is not None:
                raise RuntimeError(f"JupyterLab exited ({server.returncode}): "
                                   f"{(root / 'jupyterlab.log').read_text()[-2000:]}")
            try:
                with urllib.request.urlopen(f"{base}/api/status?token={token}", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("JupyterLab did not answer within 90 s: "
                                   f"{(root / 'jupyterlab.log').read_text()[-2000:]}")
            time.sleep(0.5)
        yield {"base": base, "token": token, "root": root, "metrics": metrics, "chromium": chromium}
    finally:
        server.terminate()
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            server.kill()
        log.close()


@pytest.fixture(scope="module")
def browser(lab):
    from playwright.sync_api import sync_playwright
    with conftest.on_any_core():   # playwright's driver and the browser it starts: not on this worker's core alone
        p = sync_playwright().start()
    try:
        b = p.chromium.launch(executable_path=lab["chromium"], headless=True, args=CHROMIUM_FLAGS)
        try:
            yield b
        finally:
            b.close()
    finally:
        p.stop()


def _screenshot(page, name: str, element=None) -> Path:
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    path = SCREENSHOTS / f"{name}.png"
    (element or page).screenshot(path=str(path))
    return path


def _errors(page) -> str:
    """The text of error outputs on the page (tracebacks), for a failure message."""
    texts = page.locator(".jp-OutputArea-output[data-mime-type='application/vnd.jupyter.stderr']").all_inner_texts()
    return "\n".join(t for t in texts if "Error" in t or "Traceback" in t)[-3000:]


def _api(lab, path: str):
    with urllib.request.urlopen(f"{lab['base']}/api/{path}?token={lab['token']}", timeout=10) as r:
        return json.loads(r.read())


def _wait_kernel_ready(lab, name: str, timeout: float = 120.0):
    """Until the notebook's kernel is started, idle, and connected to the page: before that
    Run All would find no kernel to run the cells on."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for session in _api(lab, "sessions"):
            k = session.get("kernel") or {}
            if session.get("path") == name and k.get("execution_state") == "idle" and k.get("connections", 0) > 0:
                return
        time.sleep(0.5)
    pytest.fail(f"{name}: no idle kernel connected to the page within {timeout:.0f} s")


def _run_all(page, lab, prefix: str) -> dict:
    """Open a prepared notebook, Run All from the Run menu, wait until its last cell wrote the
    metrics JSON and the kernel is idle. Returns the metrics."""
    nb = _notebook(prefix)
    # ?reset: a fresh workspace, so this notebook is the only one open
    page.goto(f"{lab['base']}/lab/tree/{nb.name}?reset&token={lab['token']}")
    notebook = page.locator(".jp-NotebookPanel:not(.lm-mod-hidden)")
    idle = notebook.locator(".jp-Notebook-ExecutionIndicator[data-status='idle']")
    idle.wait_for(timeout=120_000)
    _wait_kernel_ready(lab, nb.name)
    page.locator(".jp-StatusBar-Item", has_text="| Idle").first.wait_for(timeout=60_000)
    prompts = notebook.locator(".jp-InputPrompt")
    page.locator(".lm-MenuBar-item", has_text="Run").first.click()
    page.locator(".lm-Menu-item[data-command='runmenu:run-all']").click()
    metrics_path = lab["metrics"][prefix]
    try:
        notebook.locator(".jp-InputPrompt", has_text="*").first.wait_for(timeout=30_000)
    except Exception:  # noqa: BLE001 - a timeout or a closed page: diagnosed below
        if not metrics_path.exists():
            _screenshot(page, f"{nb.stem}_not_started")
            pytest.fail(f"{nb.name}: Run All queued no cell within 30 s")
    deadline = time.monotonic() + RUN_TIMEOUT_S
    quiet = 0
    while not metrics_path.exists():
        page.wait_for_timeout(500)
        busy = prompts.filter(has_text="*").count()
        quiet = quiet + 1 if busy == 0 and idle.count() else 0
        if quiet >= 6:  # 3 s idle with nothing queued and no metrics: a cell failed
            _screenshot(page, f"{nb.stem}_failed")
            pytest.fail(f"{nb.name} stopped before its last cell:\n{_errors(page)}")
        if time.monotonic() > deadline:
            _screenshot(page, f"{nb.stem}_timeout")
            pytest.fail(f"{nb.name} did not finish within {RUN_TIMEOUT_S} s:\n{_errors(page)}")
    idle.wait_for(timeout=60_000)
    return json.loads(metrics_path.read_text())


def _move_slider(page, panel, label: str, expected_value: str, expected_readout, name: str,
                 initial_readout: str = "", check_moved=None):
    """Focus the slider called ``label`` in ``panel``, press ArrowRight once, and wait for the
    slider to show ``expected_value``, the readout to show ``expected_readout`` exactly (or,
    when it is None, to change from ``initial_readout``) and the plot to be redrawn; then
    ``check_moved(readout text)`` when given. Screenshots before and after."""
    from playwright.sync_api import expect

    slider = panel.locator(".widget-slider", has=page.locator(".widget-label", has_text=label)).first
    plot = panel.locator(".widget-output .jp-OutputArea-output img").first
    expect(plot).to_be_visible(timeout=60_000)
    before = plot.get_attribute("src")
    _screenshot(page, f"{name}_before", panel)
    slider.locator(".noUi-handle").first.focus()
    page.keyboard.press("ArrowRight")
    # the slider formats with d3-format, which writes a minus as U+2212
    expect(slider.locator(".widget-readout")).to_have_text(expected_value.replace("-", "\u2212"),
                                                           timeout=30_000)
    readout = panel.locator("code.leglib-readout")
    if expected_readout is not None:
        expect(readout).to_have_text(expected_readout, timeout=120_000)
    else:
        expect(readout).not_to_have_text(initial_readout, timeout=120_000)
    page.wait_for_function(_IMG_CHANGED, arg=[panel.element_handle(), before], timeout=60_000)
    if check_moved is not None:
        check_moved(readout.inner_text())
    after = plot.get_attribute("src")
    _screenshot(page, f"{name}_after", panel)
    return before, after


SLIDER_TIMES = SCREENSHOTS / "slider_times.json"
_IMG_CHANGED = ("([el, old]) => { const img = el.querySelector('.widget-output .jp-OutputArea-output img');"
                " return img !== null && img.getAttribute('src') !== old; }")


def _time_moves(page, panel, label: str, moves: int = 7) -> list[float]:
    """Seconds from a key press on slider ``label`` (left, right, left, ...: a release of
    the slider by keyboard) to the panel's redrawn plot in the page, for ``moves`` moves."""
    slider = panel.locator(".widget-slider", has=page.locator(".widget-label", has_text=label)).first
    plot = panel.locator(".widget-output .jp-OutputArea-output img").first
    slider.locator(".noUi-handle").first.focus()
    times = []
    for k in range(moves):
        before = plot.get_attribute("src")
        t0 = time.perf_counter()
        page.keyboard.press("ArrowLeft" if k % 2 == 0 else "ArrowRight")
        page.wait_for_function(_IMG_CHANGED, arg=[panel.element_handle(), before], timeout=60_000, polling=5)
        times.append(time.perf_counter() - t0)
    return times


def _record_slider_times(prefix: str, label: str, times: list[float]) -> None:
    """The moves' times into reports/browser/slider_times.json (``make bench`` reports them)."""
    import statistics
    record = json.loads(SLIDER_TIMES.read_text()) if SLIDER_TIMES.exists() else {}
    record[prefix] = {"slider": label, "times_s": times, "median_s": statistics.median(times),
                      "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    SLIDER_TIMES.parent.mkdir(parents=True, exist_ok=True)
    SLIDER_TIMES.write_text(json.dumps(record, indent=2))


def _panel(page):
    """The ipywidgets panel: the output area holding leglib's readout."""
    panel = page.locator(".jp-OutputArea-output", has=page.locator("code.leglib-readout")).last
    panel.wait_for(timeout=60_000)
    panel.scroll_into_view_if_needed()
    return panel


def _slider_session(browser, lab, prefix: str, label: str, value_text: str, expected, check_moved=None) -> dict:
    """Run All in notebook ``prefix``; check the panel's readout shows ``initial``; move the
    slider ``label`` one step to ``value_text``; the readout must become ``moved`` and the
    plot must be redrawn. ``expected()`` gives ``(initial, moved)``, called once the notebook
    has run; ``moved`` None: the readout must change, and ``check_moved(its text)`` judges it.
    Returns the notebook's metrics."""
    from playwright.sync_api import expect

    nb = _notebook(prefix)
    page = browser.new_page(viewport={"width": 1500, "height": 1000})
    try:
        metrics = _run_all(page, lab, prefix)
        initial, moved = expected()
        panel = _panel(page)
        expect(panel.locator("code.leglib-readout")).to_have_text(initial, timeout=30_000)
        before, after = _move_slider(page, panel, label, value_text, moved, f"{prefix}_{label.replace(' ', '_')}",
                                     initial, check_moved)
        assert before != after and after.startswith("data:image/png")
        # then the time from a slider's release to the redrawn figure, several moves
        times = _time_moves(page, panel, label)
        _record_slider_times(prefix, label, times)
        _screenshot(page, f"{nb.stem}_page")
    finally:
        page.close()
    return metrics


def _panel_defaults(panel_function) -> dict:
    return {k: p.default for k, p in inspect.signature(panel_function).parameters.items()
            if p.default is not inspect.Parameter.empty}


def test_pole_slider_in_notebook_03(lab, browser):
    from leglib.params import load_leg

    defaults = _defaults(_notebook("03"))
    sys_thesis = M.linearize(load_leg(defaults["leg_name"]))
    # the notebook's panel: centre from its first pole, its observer factor, the panel's spread
    center = float(SF.parse_poles(defaults["poles"])[0].real)
    spread = _panel_defaults(widgets.pole_placement_panel)["spread"]
    factor = defaults["observer_factor"]
    initial = widgets.design_readout(widgets.pole_panel_design(sys_thesis, center, spread, factor))
    moved = widgets.design_readout(widgets.pole_panel_design(sys_thesis, center + 0.5, spread, factor))
    assert initial != moved

    metrics = _slider_session(browser, lab, "03", "pole centre", f"{center + 0.5:.1f}", lambda: (initial, moved))
    assert metrics["eig_K_max_rel_error"] < 1e-6  # the notebook computed sensible things


def _kernel_eval(lab, name: str, expression: str):
    """The value of the JSON-able ``expression`` evaluated in the kernel of the page's notebook
    ``name`` (a second client of the same kernel, through its connection file)."""
    from jupyter_client import BlockingKernelClient

    kernel = next(s["kernel"] for s in _api(lab, "sessions") if s.get("path") == name)
    client = BlockingKernelClient(connection_file=str(lab["root"] / ".jupyter" / "runtime" / f"kernel-{kernel['id']}.json"))
    client.load_connection_file()
    client.start_channels()
    try:
        out = []
        reply = client.execute_interactive(f"import json as _json; print(_json.dumps({expression}))", timeout=120,
                                           output_hook=lambda m: out.append(m["content"].get("text", "")
                                                                            if m["msg_type"] == "stream" else ""))
        assert reply["content"]["status"] == "ok", reply["content"]
        return json.loads("".join(out).strip().splitlines()[-1])
    finally:
        client.stop_channels()


# notebook 04's smoke grid (its check_parameters(smoke=...)); the notebook's metrics must agree
_SMOKE_04 = {"pos_n": 2, "vel_n": 4, "vint_n": 4}
# in notebook 04's kernel: the text leglib computes for the step the panel shows, and its gains
_SHOWN_04 = "[widgets.step_readout(gain_panel.last_step, leg=leg), list(gain_panel.last_step.gains)]"


def test_gain_slider_in_notebook_04(lab, browser):
    """The panel's readout is exactly leglib's text for the step it ran, before and after
    pos_gain moves one slider step, and that step ran with the moved gains. (The step itself
    depends on the device's whole history in the kernel -- the sweep, the design's step, the
    twin's noise going on from session to session as a real board's does -- so the text is
    computed from the step the kernel holds, not from a replay.)"""
    gains = _panel_defaults(widgets.gain_step_panel)
    gains.pop("gm")
    initial_gains = [gains["pos_gain"], gains["vel_gain"], gains["vel_integrator_gain"]]
    moved_gains = [initial_gains[0] + 1.0, *initial_gains[1:]]
    name = _notebook("04").name
    state = {}

    def expected():
        initial, at = _kernel_eval(lab, name, _SHOWN_04)
        assert initial.startswith("zeta = ") and at == pytest.approx(initial_gains, rel=1e-12)
        state["initial"] = initial
        return initial, None

    def check_moved(shown: str):
        text, at = _kernel_eval(lab, name, _SHOWN_04)
        assert at == pytest.approx(moved_gains, rel=1e-12), "the panel's step did not run at the moved gains"
        assert text.startswith("zeta = ") and text != state["initial"]
        assert shown == text

    metrics = _slider_session(browser, lab, "04", "pos_gain", f"{moved_gains[0]:.0f}", expected, check_moved)
    assert metrics["points"] == _SMOKE_04["pos_n"] * _SMOKE_04["vel_n"] * _SMOKE_04["vint_n"]


# ---------------------------------------------------------------------------------------
# the live view: the plot changes in the page while an experiment runs
# ---------------------------------------------------------------------------------------

def _live_notebook(lab, name: str, experiment: str, result) -> Path:
    """A notebook in the server's root: a LiveView shown, then ``experiment`` run (a cell
    that feeds ``view.on_sample``), then the view's and the run's figures written to
    ``result`` (JSON)."""
    import nbformat
    from nbformat.v4 import new_code_cell, new_notebook
    cells = [
        "import json, types\nimport numpy as np\nfrom leglib.notebook import liveview\nfrom leglib.params import load_leg\n"
        "leg = load_leg('thesis')\nview = liveview.LiveView(leg=leg, rate_hz=10).display()",
        experiment,
        f"final = view.stop()\nwith open({str(result)!r}, 'w') as fh:\n    json.dump({{**final, **run_stats}}, fh)",
    ]
    nb = new_notebook(cells=[new_code_cell(c) for c in cells])
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    path = lab["root"] / name
    nbformat.write(nb, str(path))
    return path


def _watch_live_view(browser, lab, path: Path, result: Path, timeout: float = 240.0) -> tuple[list, dict]:
    """Run All on the notebook at ``path``; while it runs, record every distinct picture the
    live view shows. Returns (pictures seen while the experiment cell ran, the result JSON)."""
    page = browser.new_page(viewport={"width": 1400, "height": 900})
    try:
        page.goto(f"{lab['base']}/lab/tree/{path.name}?reset&token={lab['token']}")
        notebook = page.locator(".jp-NotebookPanel:not(.lm-mod-hidden)")
        notebook.locator(".jp-Notebook-ExecutionIndicator[data-status='idle']").wait_for(timeout=120_000)
        _wait_kernel_ready(lab, path.name)
        page.locator(".jp-StatusBar-Item", has_text="| Idle").first.wait_for(timeout=60_000)
        page.locator(".lm-MenuBar-item", has_text="Run").first.click()
        page.locator(".lm-Menu-item[data-command='runmenu:run-all']").click()
        img = page.locator("img.leglib-liveview").first
        img.wait_for(timeout=120_000)
        experiment = notebook.locator(".jp-Cell").nth(1).locator(".jp-InputPrompt")
        seen, deadline = [], time.monotonic() + timeout
        while not result.exists():
            if time.monotonic() > deadline:
                _screenshot(page, f"{path.stem}_timeout")
                pytest.fail(f"{path.name} did not finish within {timeout:.0f} s:\n{_errors(page)}")
            src = img.get_attribute("src")
            if "*" in (experiment.text_content() or "") and src and (not seen or seen[-1] != src):
                seen.append(src)
                if len(seen) == 3:
                    _screenshot(page, f"{path.stem}_running")
            page.wait_for_timeout(100)
        _screenshot(page, f"{path.stem}_done")
        return seen, json.loads(result.read_text())
    finally:
        page.close()


def test_live_view_redraws_while_a_run_plays(lab, browser):
    """A recorded 5 s run fed to the view at its own 500 Hz pace (liveview.replay, the
    callback an experiment calls): the picture changes in the page while the cell runs."""
    result = lab["root"] / "live_replay.json"
    path = _live_notebook(lab, "live_replay.ipynb", (
        "t = np.arange(2500) * 0.002\ne = 1 - np.exp(-3 * t) * np.cos(12 * t)\n"
        "run = types.SimpleNamespace(t=t, q1=leg.q1 - 0.3 * e, q2=leg.q2 + 0.3 * e,\n"
        "                            iq=np.column_stack([np.exp(-t), -np.exp(-t)]))\n"
        "run_stats = liveview.replay(run, view.on_sample, setpoint=(leg.q1 - 0.3, leg.q2 + 0.3))"), result)
    seen, stats = _watch_live_view(browser, lab, path, result)
    assert len(seen) >= 5, f"the live view changed {len(seen)} times during a 5 s run"
    assert all(s.startswith("blob:") or s.startswith("data:image/png") for s in seen)
    assert stats["received"] == 2500 and stats["dropped"] == 0 and stats["buffered"] == 2500
    assert stats["achieved_period_s"] == pytest.approx(0.002, rel=0.05)   # the loop kept its pace


def test_live_view_redraws_during_a_realtime_step(lab, browser):
    """A 3 s step on the twin paced to the wall clock (realtime=True) with the view's
    on_sample: the picture changes while the step runs, and the step keeps its 2 ms period.
    (The device is configured and calibrated first on virtual time, about 20 s of device
    time, then connected again in real time: the step is what the view watches.)"""
    result = lab["root"] / "live_step.json"
    path = _live_notebook(lab, "live_step.ipynb", (
        "import leglib as lg\n"
        "with lg.connect('virtual', seed=1) as dev:\n"
        "    lg.configure(dev)\n"
        "    lg.calibrate(dev)\n"
        "with lg.connect('virtual', seed=1, realtime=True) as dev:\n"
        "    assert dev.sim.realtime\n"
        "    view.clear()\n"
        "    r = lg.step_response(dev, 50, 0.046, 0.001, duration=3.0, on_sample=view.on_sample)\n"
        "import numpy as np\n"
        "run_stats = {'samples': len(r.t), 'sample_rate_hz': r.meta['sample_rate_hz'], 'completed': r.completed,\n"
        "             'abort_reason': r.abort_reason, 'median_period_s': float(np.median(np.diff(r.t))),\n"
        "             'max_gap_s': float(np.max(np.diff(r.t))), 'first_s': float(r.t[0]), 'last_s': float(r.t[-1])}"),
        result)
    seen, stats = _watch_live_view(browser, lab, path, result)
    assert len(seen) >= 3, f"the live view changed {len(seen)} times during a 3 s realtime step"
    assert stats["dropped"] == 0
    if not stats["completed"]:
        # the one acceptable abort: the host lost the CPU for longer than the step's 0.5 s
        # watchdog (a loaded machine); the device -- and the twin -- then disarm the motors
        # (fail-safe), which is what must have happened
        assert "WATCHDOG_TIMER_EXPIRED" in (stats["abort_reason"] or "") and stats["max_gap_s"] >= 0.45, \
            f"the realtime step aborted: {stats['abort_reason']} (longest sample gap {stats['max_gap_s']:.3f} s)"
        warnings.warn(f"the host stalled {stats['max_gap_s']:.2f} s during the realtime step; the watchdog "
                      f"disarmed the motors as on the device")
        return
    assert stats["received"] >= stats["samples"] > 0     # every sample the step took reached the view
    # the sampling keeps its requested 2 ms period (the median: a host that loses the CPU
    # skips a slot now and then, which lowers the mean rate, not the period)
    assert stats["median_period_s"] == pytest.approx(0.002, rel=0.05)
    # sampling went on throughout: from the step's first slot to its last, with no gap as long
    # as the step's 0.5 s watchdog (a longer one disarms the motors: the branch above). How
    # many slots a loaded host skips -- the mean rate, 327 and 243 Hz in two CI runs on a
    # 2-core machine with the other test worker busy -- is a benchmark's matter (make bench
    # liveview_sampling), not this test's.
    assert stats["first_s"] < 0.05 and stats["last_s"] > 3.0 - 0.05, (stats["first_s"], stats["last_s"])
    assert stats["max_gap_s"] < 0.5, stats["max_gap_s"]
    if stats["sample_rate_hz"] < 250:
        warnings.warn(f"the realtime step sampled at a mean {stats['sample_rate_hz']:.0f} Hz of 500 (a loaded host "
                      f"skipped slots; the longest gap {stats['max_gap_s'] * 1e3:.0f} ms)")


# ---------------------------------------------------------------------------------------
# a report read offline: maths rendered, the animation player working, nothing fetched
# ---------------------------------------------------------------------------------------

def test_a_report_works_offline(browser, tmp_path):
    """A report written by leglib (execute -> to_html) opened with every network request
    refused: the maths of markdown cells and of sympy's outputs are MathML the browser lays
    out (no TeX left in the text), and the animation player's buttons show and step frames."""
    import nbformat
    from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

    from leglib.notebook.run import execute
    nb = new_notebook(cells=[
        new_markdown_cell("# Offline\nThe joint $q_1$ and the ratio $$\\frac{l_1}{l_2} = \\sqrt{2}$$ and `$not maths$`."),
        new_code_cell("import sympy as sp\nq = sp.symbols('q1')\nsp.Matrix([[sp.cos(q), sp.Rational(1, 3)]])"),
        new_code_cell("import numpy as np, matplotlib.pyplot as plt\nfrom matplotlib.animation import FuncAnimation\n"
                      "from leglib import plots\nfig, ax = plt.subplots(figsize=(3, 2))\nline, = ax.plot([0, 1], [0, 0])\n"
                      "anim = FuncAnimation(fig, lambda k: line.set_ydata([0, k]), frames=4, interval=100)\n"
                      "plots.show_animation(anim)"),
    ])
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    path = tmp_path / "offline.ipynb"
    nbformat.write(nb, str(path))
    report = execute(path, tmp_path / "out", html=True).with_suffix(".html")

    fetched = []
    page = browser.new_page()
    try:
        def refuse(route):
            if route.request.url.startswith("file:"):
                route.continue_()
            else:
                fetched.append(route.request.url)
                route.abort()
        page.route("**/*", refuse)
        page.goto(report.as_uri())
        text = page.locator("body").inner_text()
        assert "$" not in text.replace("$not maths$", ""), "TeX left in the page"
        assert "\\frac" not in text and "\\displaystyle" not in text and "\\left" not in text
        maths = page.locator("math")
        assert maths.count() >= 3  # q_1, the fraction, the sympy matrix
        for k in range(maths.count()):
            box = maths.nth(k).bounding_box()
            assert box is not None and box["width"] > 5 and box["height"] > 5, f"formula {k} not laid out"
        # the player: buttons with visible characters; one step forward shows another frame
        buttons = page.locator(".anim-buttons button")
        assert buttons.count() == 9
        labels = [buttons.nth(k).inner_text().strip() for k in range(buttons.count())]
        assert all(labels) and len(set(labels)) == 9, labels
        # characters a common font has (Geometric Shapes, Basic Latin), not tofu boxes
        assert all(ord(c) < 0x80 or 0x25A0 <= ord(c) <= 0x25FF or c == "\u2212" for c in "".join(labels)), labels
        frame = page.locator(".animation img").first
        before = frame.get_attribute("src")
        page.locator(".anim-buttons button[title='Next frame']").click()
        assert frame.get_attribute("src") != before
        _screenshot(page, "offline_report")
    finally:
        page.close()
    # the page asked the network only for what it does without (MathJax, require.js): the
    # refusals did not cost a formula or a button (checked above)
    assert not any("font-awesome" in u for u in fetched)
