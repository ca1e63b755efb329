"""A live view of an experiment while it runs: joint angles, setpoint, motor currents.

The experiment's polling loop calls :meth:`LiveView.on_sample` once per sample with a dict
``{"t": s, "q1": rad, "q2": rad, "iq": (A, A), "setpoint": (rad, rad) or None}``
(``step_response(..., on_sample=...)``, ``torque_loop(...,
on_sample=...)``; on the twin when connected with ``realtime=True``). The callback only
appends the sample to a bounded queue -- it never draws, never waits for a lock, never
blocks -- so it cannot slow the experiment's sampling.

A separate thread takes the queued samples at a bounded rate (``rate_hz``, default
10 Hz) and has them drawn with matplotlib's Agg renderer into a PNG shown by an
``ipywidgets.Image``; in JupyterLab the image changes while the cell still runs (widget
updates from a thread reach the page without waiting for the cell). No ipympl is needed.

Drawing holds Python's global interpreter lock for milliseconds at a time, which would
delay the experiment's loop in the same process. By default (``renderer="process"``)
the drawing therefore happens in a separate process: the thread here only forwards new
samples through a pipe and passes the PNG on. ``renderer="thread"`` draws in the thread
(no extra process; fine when the sample period is long against a redraw). Either way
only the data lines are redrawn (blitting); the axes are drawn again only when their
limits must grow.

Example
-------
>>> view = liveview.LiveView(leg=leg).display()
>>> with lg.connect("virtual", realtime=True) as dev:
...     lg.configure(dev); lg.calibrate(dev)
...     r = lg.step_response(dev, 50, 0.046, 0.001, on_sample=view.on_sample)
>>> view.stop()          # last redraw; view.stats: samples, redraws, rate, drawing cost

:func:`replay` feeds a recorded run through the same callback at its own pace (to watch
a measurement again, and to test a view without a device); :func:`supports` tells
whether an experiment function takes ``on_sample``.
"""

from __future__ import annotations

import collections
import inspect
import math
import os
import pickle
import select
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ..plots import leg_points
from . import png as _png

FIELDS = ("t", "q1", "q2", "iq1", "iq2", "sp1", "sp2")


def supports(experiment) -> bool:
    """Whether ``experiment`` (e.g. ``leglib.experiments.step.step_response``) takes ``on_sample``."""
    try:
        return "on_sample" in inspect.signature(experiment).parameters
    except (TypeError, ValueError):
        return False


def parse_sample(s: dict) -> tuple:
    """One sample dict -> (t, q1, q2, iq1, iq2, sp1, sp2), NaN for an absent current or
    setpoint. Raises KeyError, TypeError, ValueError or IndexError for a malformed one."""
    t, q1, q2 = float(s["t"]), float(s["q1"]), float(s["q2"])
    iq = s.get("iq")
    i1, i2 = (math.nan, math.nan) if iq is None else (float(iq[0]), float(iq[1]))
    sp = s.get("setpoint")
    s1, s2 = (math.nan, math.nan) if sp is None else (float(sp[0]), float(sp[1]))
    return (t, q1, q2, i1, i2, s1, s2)


class _Buffer:
    """Samples as columns of a (7, max_points) array. A time not after the last one starts
    a new run. When full, every other sample is dropped and from then on only every
    second one is kept (the stride doubles each time): the whole run stays visible, evenly
    thinned."""

    def __init__(self, max_points: int):
        self.data = np.full((len(FIELDS), int(max_points)), np.nan)
        self.reset()
        self.runs = 0

    def add(self, rows) -> None:
        for row in rows:
            if self._seen and row[0] <= self._last_t:
                self.reset()
                self.runs += 1
            self._last_t = row[0]
            keep = self._seen % self.stride == 0
            self._seen += 1
            if not keep:
                continue
            if self.n == self.data.shape[1]:
                half = self.data[:, : self.n : 2].copy()
                self.n = half.shape[1]
                self.data[:, : self.n] = half
                self.stride *= 2
                if (self._seen - 1) % self.stride:
                    continue
            self.data[:, self.n] = row
            self.n += 1

    def reset(self) -> None:
        self.n = 0
        self.stride = 1
        self._seen = 0
        self._last_t = -math.inf

    def view(self) -> np.ndarray:
        return self.data[:, : self.n]


class _Plot:
    """The figure of a live view, drawn from its own :class:`_Buffer` (in the view's thread
    or in the renderer process)."""

    def __init__(self, max_points: int, leg=None, deg: bool = True, title: str = "", figsize=(9.0, 3.0),
                 dpi: int = 72):
        self.buf = _Buffer(max_points)
        self.leg, self.deg, self.title = leg, deg, title
        self._figsize, self._dpi = tuple(figsize), int(dpi)
        self._fig = None
        self.background_draws = 0
        self._leg_points = None
        if leg is not None:
            # import and first call (compilation) now, not in the middle of an experiment
            leg_points(leg, *leg.q0)
            self._leg_points = leg_points

    def draw(self) -> tuple[bytes, float]:
        """(PNG, seconds it took)."""
        t0 = time.perf_counter()
        png = self._render()
        return png, time.perf_counter() - t0

    # -- drawing -----------------------------------------------------------------------
    # Each redraw costs little because the axes (ticks, labels, legends: most of the cost)
    # are drawn only when their limits grow; otherwise the saved background is restored
    # and only the data lines are drawn on it (blitting on the Agg canvas).
    def _figure(self):
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # load time: matplotlib, only when drawing
        from matplotlib.figure import Figure  # load time: matplotlib, only when drawing
        fig = Figure(figsize=self._figsize, dpi=self._dpi)
        FigureCanvasAgg(fig)
        n = 3 if self.leg is not None else 2
        axes = fig.subplots(1, n, gridspec_kw={"width_ratios": [2.2, 2.2, 1.0][:n]})
        unit = "deg" if self.deg else "rad"
        a0, a1 = axes[0], axes[1]
        self._lines = {
            "q1": a0.plot([], [], "-", color="tab:blue", lw=1.2, label="q1")[0],
            "q2": a0.plot([], [], "-", color="tab:orange", lw=1.2, label="q2")[0],
            "sp1": a0.plot([], [], "--", color="tab:blue", lw=0.8, label="q1 setpoint")[0],
            "sp2": a0.plot([], [], "--", color="tab:orange", lw=0.8, label="q2 setpoint")[0],
            "iq1": a1.plot([], [], "-", color="tab:blue", lw=1.0, label="Iq, axis of q1")[0],
            "iq2": a1.plot([], [], "-", color="tab:orange", lw=1.0, label="Iq, axis of q2")[0],
        }
        a0.set_xlabel("t [s]", fontsize=8)
        a0.set_ylabel(f"joint angle [{unit}]", fontsize=8)
        a0.legend(fontsize=7, loc="upper left", ncol=2)
        a1.set_xlabel("t [s]", fontsize=8)
        a1.set_ylabel("Iq [A]", fontsize=8)
        a1.legend(fontsize=7, loc="upper left", ncol=2)
        self._axes = list(axes)
        if self.leg is not None:
            a2 = axes[2]
            self._lines["leg"] = a2.plot([], [], "o-", color="k", lw=2, ms=4)[0]
            self._lines["foot"] = a2.plot([], [], "-", color="tab:red", lw=0.8)[0]
            a2.set_aspect("equal")
            a2.set_title("pose", fontsize=8)
        for ax in axes:
            ax.tick_params(labelsize=7)
        if self.title:
            fig.suptitle(self.title, fontsize=9)
        fig.tight_layout()
        self._text = fig.text(0.005, 0.005, "", fontsize=7, color="0.4")
        for art in [*self._lines.values(), self._text]:
            art.set_animated(True)             # drawn by _render, not with the background
        self._limits = None
        self._background = None
        return fig

    @staticmethod
    def _grow(lim, lo, hi, margin):
        """Limits that contain [lo, hi], grown with ``margin`` headroom only when needed."""
        if not (np.isfinite(lo) and np.isfinite(hi)):
            return lim
        if lim is not None and lim[0] <= lo and hi <= lim[1]:
            return lim
        span = max(hi - lo, 1e-9)
        if lim is not None:
            lo, hi = min(lo, lim[0]), max(hi, lim[1])
            span = max(hi - lo, 1e-9)
        return (lo - margin * span, hi + margin * span)

    def _wanted_limits(self, b):
        scale = 180 / math.pi if self.deg else 1.0
        old = self._limits or (None, None, None, None, None)
        t = b[0]
        tl = old[0]
        if tl is None or t[-1] > tl[1]:
            tl = (0.0, max(1.0, 2.0 * t[-1]))    # doubling: few redraws of the axes per run
        with np.errstate(all="ignore"):
            ang = b[[1, 2, 5, 6]] * scale
            al = self._grow(old[1], np.nanmin(ang), np.nanmax(ang), 0.3)
            cur = b[[3, 4]]
            il = self._grow(old[2], np.nanmin(cur), np.nanmax(cur), 0.3) if np.any(np.isfinite(cur)) else old[2]
        pose = old[3]
        if self.leg is not None:
            step = max(1, self.buf.n // 500)
            pts = self._leg_points(self.leg, b[1, ::step], b[2, ::step]).reshape(-1, 2)
            with np.errstate(all="ignore"):
                lo, hi = np.nanmin(pts, axis=0), np.nanmax(pts, axis=0)
            if np.all(np.isfinite(lo)) and (pose is None or np.any(lo < pose[0]) or np.any(hi > pose[1])):
                c, r = (lo + hi) / 2, max(float(np.max(hi - lo)) / 2, 0.05) * 1.15
                pose = (c - r, c + r)
        return (tl, al, il, pose, None)

    def _render(self) -> bytes:
        """Draw the buffered samples; returns the PNG."""
        if self._fig is None:
            self._fig = self._figure()
        fig, canvas = self._fig, self._fig.canvas
        b = self.buf.view()
        limits = self._wanted_limits(b) if self.buf.n else (self._limits or (None,) * 5)
        if self._background is None or limits != self._limits:
            tl, al, il, pose, _ = limits
            a = self._axes
            if tl is not None:
                a[0].set_xlim(*tl)
                a[1].set_xlim(*tl)
            if al is not None:
                a[0].set_ylim(*al)
            if il is not None:
                a[1].set_ylim(*il)
            if pose is not None:
                a[2].set_xlim(pose[0][0], pose[1][0])
                a[2].set_ylim(pose[0][1], pose[1][1])
            self._limits = limits
            canvas.draw()
            self._background = canvas.copy_from_bbox(fig.bbox)
            self.background_draws += 1
        else:
            canvas.restore_region(self._background)
        scale = 180 / math.pi if self.deg else 1.0
        t = b[0]
        L = self._lines
        for k, row in (("q1", 1), ("q2", 2), ("sp1", 5), ("sp2", 6)):
            L[k].set_data(t, b[row] * scale)
        for k, row in (("iq1", 3), ("iq2", 4)):
            L[k].set_data(t, b[row])
        if self.leg is not None and self.buf.n:
            pts = self._leg_points(self.leg, b[1, -1], b[2, -1])
            step = max(1, self.buf.n // 500)
            foot = self._leg_points(self.leg, b[1, ::step], b[2, ::step])[:, 3, :]
            L["leg"].set_data(pts[:, 0], pts[:, 1])
            L["foot"].set_data(foot[:, 0], foot[:, 1])
        self._text.set_text(f"{self.buf.n} samples, t = {t[-1]:.2f} s" if self.buf.n else "waiting for samples")
        for art in L.values():
            art.axes.draw_artist(art)
        fig.draw_artist(self._text)
        return _png.encode(np.asarray(canvas.buffer_rgba()))



def _serve(inp, out) -> None:
    """The renderer process: a :class:`_Plot` fed by pickled messages on ``inp``, answering
    draw requests on ``out`` (``python -m leglib.notebook.liveview``, started by :class:`LiveView`)."""
    plot = None
    while True:
        try:
            msg = pickle.load(inp)
        except EOFError:
            return
        if msg[0] == "options":
            plot = _Plot(**msg[1])
        elif msg[0] == "add":
            plot.buf.add(msg[1])
        elif msg[0] == "reset":
            plot.buf.reset()
        elif msg[0] == "draw":
            try:
                png, cost = plot.draw()
                reply = ("png", png, cost, plot.background_draws)
            except Exception as exc:  # noqa: BLE001 - reported to the view, which shows it
                reply = ("error", f"{type(exc).__name__}: {exc}")
            pickle.dump(reply, out, protocol=pickle.HIGHEST_PROTOCOL)
            out.flush()
        elif msg[0] == "stop":
            return


class LiveView:
    """Buffer samples from an experiment's callback; redraw a plot from a timer thread.

    Parameters
    ----------
    rate_hz : redraws per second at most (each redraw shows every sample received so far)
    max_points : samples kept for drawing; beyond that the buffer is thinned evenly (every
        other sample dropped, then only every second one kept): the whole run stays visible
    queue_size : bound of the queue between the callback and the drawing thread; when the
        drawer falls this far behind, the oldest queued samples are dropped (counted in
        ``stats["dropped"]``), the experiment is never held up
    leg : :class:`leglib.params.LegParams` to draw the leg's pose too (None: no pose panel)
    deg : angles in degrees (else rad)
    title : figure title
    figsize, dpi : the PNG's size (small keeps each redraw cheap)
    renderer : ``"process"`` (draw in a separate process: the experiment's process only
        forwards samples) or ``"thread"`` (draw in the view's thread)

    Attributes
    ----------
    image, status, widget : the ipywidgets (after :meth:`widgets` or :meth:`display`)
    last_png : the latest drawing (PNG bytes)
    errors : messages about ignored samples or failed redraws
    """

    def __init__(self, rate_hz: float = 10.0, max_points: int = 20_000, queue_size: int = 100_000, leg=None,
                 deg: bool = True, title: str = "", figsize=(9.0, 3.0), dpi: int = 72, renderer: str = "process"):
        if not (0 < rate_hz <= 50):
            raise ValueError(f"rate_hz must be in (0, 50], got {rate_hz}")
        if max_points < 10 or queue_size < 1:
            raise ValueError(f"max_points must be >= 10 and queue_size >= 1, got {max_points}, {queue_size}")
        if renderer not in ("process", "thread"):
            raise ValueError(f"renderer must be 'process' or 'thread', got {renderer!r}")
        self.rate_hz = float(rate_hz)
        self.renderer = renderer
        self._options = {"max_points": int(max_points), "leg": leg, "deg": deg, "title": title,
                         "figsize": tuple(figsize), "dpi": int(dpi)}
        self._queue = collections.deque(maxlen=int(queue_size))
        self.received = 0                      # written by the experiment's thread only
        self._drained = 0
        self._buf = _Buffer(max_points)
        self.errors: list[str] = []
        self.redraws = 0
        self.background_draws = 0
        self.draw_seconds: list[float] = []
        self._redraw_times: list[float] = []
        self._lock = threading.Lock()          # the drawing thread against stop()/redraw()/data(), never on_sample
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._plot: _Plot | None = None
        self._proc = None
        self._conn = None
        self.image = None
        self.status = None
        self.widget = None
        self.last_png: bytes | None = None
        self._pending = True                   # samples taken since the last drawing

    # -- the callback ------------------------------------------------------------------
    def on_sample(self, sample: dict) -> None:
        """Take one sample (called from the experiment's loop): O(1), no lock, no drawing."""
        self._queue.append(sample)
        self.received += 1

    # -- buffering ---------------------------------------------------------------------
    def _take(self) -> list:
        """Queued samples as rows, also added to the view's buffer (call under the lock)."""
        rows = []
        q = self._queue
        while True:
            try:
                s = q.popleft()
            except IndexError:
                break
            self._drained += 1
            try:
                rows.append(parse_sample(s))
            except (KeyError, TypeError, ValueError, IndexError) as exc:
                if len(self.errors) < 20:
                    self.errors.append(f"sample {self._drained} ignored: {type(exc).__name__}: {exc} "
                                       f"(expected t, q1, q2, iq (2), setpoint (2) or None)")
        self._buf.add(rows)
        return rows

    def data(self) -> dict:
        """The buffered samples: ``t`` (N,) [s], ``q1``, ``q2`` (N,) [rad], ``iq`` (N, 2) [A],
        ``setpoint`` (N, 2) [rad] (NaN where none). What is queued is taken first (and drawn
        at the next redraw)."""
        with self._lock:
            rows = self._take()
            self._forward(rows)
            b = self._buf.view().copy()
        return {"t": b[0], "q1": b[1], "q2": b[2], "iq": b[3:5].T, "setpoint": b[5:7].T}

    def clear(self) -> None:
        """Forget the buffered samples (the next experiment starts a fresh plot)."""
        with self._lock:
            self._drained += len(self._queue)  # forgotten on purpose, not dropped
            self._queue.clear()
            self._buf.reset()
            if self._conn is not None:
                self._send(("reset",))
            elif self._plot is not None:
                self._plot.buf.reset()
            self._pending = True

    @property
    def stats(self) -> dict:
        """Samples received, buffered and dropped; redraws, their achieved rate [Hz], the
        median cost of one drawing [s] and how often the axes themselves were redrawn."""
        times = self._redraw_times
        rate = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else math.nan
        return {"received": self.received, "buffered": self._buf.n, "queued": len(self._queue),
                "dropped": self.received - self._drained - len(self._queue), "redraws": self.redraws,
                "redraw_rate_hz": rate, "renderer": self.renderer,
                "draw_median_s": statistics.median(self.draw_seconds) if self.draw_seconds else math.nan,
                "background_draws": self.background_draws, "errors": len(self.errors)}

    # -- drawing -----------------------------------------------------------------------
    def _ensure_renderer(self) -> None:
        if self.renderer == "thread":
            if self._plot is None:
                self._plot = _Plot(**self._options)
            return
        if self._proc is None or self._proc.poll() is not None:
            env = dict(os.environ)
            root = str(Path(__file__).resolve().parents[2])  # this leglib, whatever the path
            env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
            env["MPLBACKEND"] = "Agg"
            self._proc = subprocess.Popen([sys.executable, "-m", "leglib.notebook.liveview"], stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, env=env)
            self._conn = True
            self._send(("options", self._options))
            self._send(("add", [tuple(r) for r in self._buf.view().T]))

    def _send(self, msg) -> None:
        pickle.dump(msg, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
        self._proc.stdin.flush()

    def _recv(self, timeout: float):
        ready, _, _ = select.select([self._proc.stdout], [], [], timeout)
        if not ready:
            raise RuntimeError(f"the renderer process did not answer within {timeout:.0f} s")
        try:
            return pickle.load(self._proc.stdout)
        except EOFError:
            raise RuntimeError(f"the renderer process ended (exit code {self._proc.poll()})") from None

    def _forward(self, rows) -> None:
        if not rows:
            return
        self._pending = True
        if self._conn is not None:
            self._send(("add", rows))
        elif self._plot is not None:
            self._plot.buf.add(rows)

    def _draw(self) -> bytes:
        if self._conn is None:
            png, cost = self._plot.draw()
            self.background_draws = self._plot.background_draws
            self.draw_seconds.append(cost)
            return png
        self._send(("draw",))
        msg = self._recv(60.0)
        if msg[0] == "error":
            raise RuntimeError(f"the renderer process failed: {msg[1]}")
        _, png, cost, self.background_draws = msg
        self.draw_seconds.append(cost)
        return png

    def redraw(self) -> bool:
        """Take queued samples and, if there were any (or nothing was drawn yet), draw and
        update the widget. Returns whether it drew."""
        with self._lock:
            self._ensure_renderer()
            self._forward(self._take())
            if not self._pending and self.last_png is not None:
                return False
            png = self._draw()
            self._pending = False
            self._redraw_times.append(time.monotonic())
            self.redraws += 1
            self.last_png = png
        if self.image is not None:
            self.image.value = png
            s = self.stats
            self.status.value = (f"<small>live view: {s['received']} samples, {s['redraws']} redraws, "
                                 f"{s['dropped']} dropped{', ' + self.errors[-1] if self.errors else ''}</small>")
        return True

    # -- the thread ----------------------------------------------------------------------
    def _loop(self):
        period = 1.0 / self.rate_hz
        next_t = time.monotonic()
        while not self._stop.is_set():
            next_t += period
            try:
                self.redraw()
            except Exception as exc:  # noqa: BLE001 - a drawing failure must not end the view silently
                if len(self.errors) < 20:
                    self.errors.append(f"redraw failed: {type(exc).__name__}: {exc}")
            # bounded rate: wait for the next slot (skip slots a slow redraw overran)
            now = time.monotonic()
            if next_t < now:
                next_t = now
            self._stop.wait(next_t - now)

    def start(self) -> "LiveView":
        """Start the renderer, draw once (the figure's set-up is the costly part: done here,
        before the experiment runs) and start the drawing thread (idempotent)."""
        if self.last_png is None:
            self.redraw()
        if self._thread is None or not self._thread.is_alive():
            self._stop.clear()
            self._thread = threading.Thread(target=self._loop, name="leglib-liveview", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> dict:
        """Stop the drawing thread, draw what is left, end the renderer process; returns
        :attr:`stats`."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30)
            self._thread = None
        self.redraw()
        with self._lock:
            if self._proc is not None:
                try:
                    self._send(("stop",))
                    self._proc.stdin.close()
                    self._proc.wait(timeout=10)
                except (OSError, ValueError, __import__("subprocess").TimeoutExpired):
                    self._proc.kill()
                    self._proc.wait(timeout=10)
                self._proc.stdout.close()
                self._proc = None
                self._conn = None
        return self.stats

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()
        return False

    # -- in the notebook -------------------------------------------------------------------
    def widgets(self):
        """The ``ipywidgets`` box (image and a status line), built once."""
        if self.widget is None:
            import ipywidgets as W  # load time: ipywidgets, only inside a notebook
            self.image = W.Image(format="png")
            self.image.add_class("leglib-liveview")
            self.status = W.HTML("<small>live view: waiting for samples</small>")
            self.widget = W.VBox([self.image, self.status])
            if self.last_png is not None:
                self.image.value = self.last_png
        return self.widget

    def display(self) -> "LiveView":
        """Show the view in the notebook and start redrawing; returns the view."""
        from IPython.display import display  # load time: IPython, only inside a notebook
        display(self.widgets())
        return self.start()


def replay(run, on_sample, speed: float = 1.0, setpoint=None) -> dict:
    """Feed a recorded run through ``on_sample`` at its own pace (wall clock / ``speed``),
    as an experiment's polling loop does.

    Parameters
    ----------
    run : anything with ``t``, ``q1``, ``q2`` (N,) arrays; ``iq`` (N, 2) if present
    on_sample : the callback, e.g. :meth:`LiveView.on_sample`
    speed : 1.0 real time, 2.0 twice as fast
    setpoint : (q1, q2) [rad] reported with every sample, or None

    Returns
    -------
    dict
        ``samples``; ``period_s`` the run's median sample period; ``achieved_period_s``
        the median interval between calls; ``late_max_s``, ``late_p99_s`` how late calls
        came against their schedule; ``callback_median_s`` the median cost of one call.
    """
    t = np.asarray(run.t, dtype=float)
    q1, q2 = np.asarray(run.q1, dtype=float), np.asarray(run.q2, dtype=float)
    iq = getattr(run, "iq", None)
    iq = np.full((t.size, 2), math.nan) if iq is None or len(iq) != t.size else np.asarray(iq, dtype=float)
    sp = None if setpoint is None else (float(setpoint[0]), float(setpoint[1]))
    rel = (t - t[0]) / speed
    calls = np.empty(t.size)
    cost = np.empty(t.size)
    start = time.perf_counter()
    for i in range(t.size):
        wait = start + rel[i] - time.perf_counter()
        if wait > 0:
            time.sleep(wait)                   # paced as an experiment's loop: sleeping, not spinning
        c0 = time.perf_counter()
        on_sample({"t": float(t[i]), "q1": float(q1[i]), "q2": float(q2[i]),
                   "iq": (float(iq[i, 0]), float(iq[i, 1])), "setpoint": sp})
        calls[i] = c0
        cost[i] = time.perf_counter() - c0
    late = calls - start - rel
    return {"samples": int(t.size), "period_s": float(np.median(np.diff(t))) / speed if t.size > 1 else math.nan,
            "achieved_period_s": float(np.median(np.diff(calls))) if t.size > 1 else math.nan,
            "late_max_s": float(late.max()), "late_p99_s": float(np.percentile(late, 99)),
            "callback_median_s": float(np.median(cost))}


if __name__ == "__main__":
    # the protocol owns the original stdout; anything printed goes to stderr
    _out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    _serve(sys.stdin.buffer, _out)
