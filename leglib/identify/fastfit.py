"""Compiled second-order identification of step responses, one or many in one call.

The model is :func:`leglib.identify.step.second_order`'s: ``y = offset + gain h(t - delay)``
with ``h`` the unit step response of ``wn^2 / (s^2 + 2 zeta wn s + wn^2)`` (0 before the
delay). Everything that identification does per response runs in one numba function:
validation (flat, NaN, short, non-step), Savitzky-Golay smoothing, the thesis's log
decrement as the first start (peaks found as scipy.signal.find_peaks finds them, with
prominence), the rise-time starts, and a bounded Levenberg-Marquardt fit with the exact
Jacobian of all five parameters. :func:`identify_batch` loops over a whole sweep in that
one call; a single response is a batch of one, so both give the same numbers by
construction.

Why it is fast: the Jacobian is analytic (no finite differences), the normal equations
(5 x 5) are accumulated in the same pass as the residual, and no Python runs per
iteration. The step response is written in one form valid for every zeta: with
``q = 1 - zeta^2`` and ``x = wn tau``,
``h = 1 - exp(-zeta x) (C + zeta S)``, ``C = cos(sqrt(q) x)``, ``S = sin(sqrt(q) x) / sqrt(q)``
(cosh and sinh when q < 0, 1 and x at q = 0); then ``dh/dx = exp(-zeta x) S`` and
``dh/dzeta = exp(-zeta x) (x C - S) / q``, evaluated by its series near q = 0, so critical
damping needs no special case.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .. import _numba_gc, _numba_inline  # noqa: F401  (before any kernel compiles)
from ..cores import over_cores

# status codes of one response (their messages: _error)
OK, SHORT, NONFINITE, NOT_INCREASING, FLAT, NOT_STEP, ZETA_BOUND, LOW_R2, NO_DECAY = range(9)
MIN_R2 = 0.5          # below this the data is not a second-order step response
ZETA_MAX = 100.0      # upper bound of zeta in the fit
ZETA_MIN = 1e-3       # lower bound of zeta in the fit
# the multi-start stops at a start whose fit explains R2_ENOUGH of the response, or at a
# start that ends in the minimum already found (cost within SAME_COST, zeta and wn within
# SAME_PARAM, relative). On the thesis grid of the default and the four mismatched plants
# (1825 responses) the other starts never found a lower cost after either; they cost
# 40 % of the fitting (2.4 starts a response on average before, 1.3 now)
R2_ENOUGH = 0.995
SAME_COST = 1e-9
SAME_PARAM = 1e-6
# columns of the per-response result row
(C_ZETA, C_WN, C_GAIN, C_OFFSET, C_DELAY, C_R2, C_NPEAKS, C_STEP, C_SPAN, C_NOISE, C_N,
 C_COST, C_STARTS, C_ITERS) = range(14)
N_OUT = 14


# ---------------------------------------------------------------------------------------
# the model
# ---------------------------------------------------------------------------------------

@njit(cache=True)
def _terms(x, zeta, q):
    """(exp(-zeta x) C, exp(-zeta x) S, exp(-zeta x) D) at x = wn tau >= 0, q = 1 - zeta^2,
    with D = (x C - S) / q = dh/dzeta / exp(-zeta x)."""
    qx2 = q * x * x
    small = abs(qx2) <= 1e-3
    if small:
        # series in q x^2, exact to ~1e-13 relative here
        D = x * x * x * (-1.0 / 3.0 + qx2 / 30.0 - qx2 * qx2 / 840.0)
    if q >= 0.0:
        s = math.sqrt(q)
        e = math.exp(-zeta * x)
        C = math.cos(s * x)
        S = math.sin(s * x) / s if s * x > 1e-4 else x * (1.0 - qx2 / 6.0)
        if not small:
            D = (x * C - S) / q
        return e * C, e * S, e * D
    r = math.sqrt(-q)
    if r * x > 20.0:
        # two real exponentials apart: no overflow of cosh against exp
        e1 = math.exp(-x / (zeta + r))    # zeta - r, without cancellation
        e2 = math.exp(-(zeta + r) * x)
        eC = 0.5 * (e1 + e2)
        eS = (e1 - e2) / (2.0 * r)
        return eC, eS, (x * eC - eS) / q
    e = math.exp(-zeta * x)
    C = math.cosh(r * x)
    S = math.sinh(r * x) / r if r * x > 1e-4 else x * (1.0 - qx2 / 6.0)
    if not small:
        D = (x * C - S) / q
    return e * C, e * S, e * D


@njit(cache=True)
def model(t, zeta, wn, gain, offset, delay):
    """The second-order step response ``offset + gain h(t - delay)`` at times ``t`` [s].

    Parameters
    ----------
    t : (N,) float array, times [s]
    zeta : damping ratio [-]
    wn : natural frequency [rad/s]
    gain, offset : in the units of the response
    delay : [s]

    Returns
    -------
    (N,) float array
    """
    out = np.empty(t.size)
    q = 1.0 - zeta * zeta
    for i in range(t.size):
        tau = t[i] - delay
        if tau > 0.0:
            eC, eS, _ = _terms(wn * tau, zeta, q)
            out[i] = offset + gain * (1.0 - (eC + zeta * eS))
        else:
            out[i] = offset
    return out


ANCHOR = 32  # on a uniform grid, samples between direct evaluations of exp, cos, sin


@njit(cache=True)
def _normal_equations(t, y, p, A, g, need_jac, dt):
    """Half the sum of squared residuals at parameters ``p``; with ``need_jac`` also
    J^T J into ``A`` (5 x 5) and J^T r into ``g`` (5,), in the same pass.

    On a uniform grid (``dt`` > 0, the spacing of ``t``) the exponentials and the
    oscillation advance by one complex (or two real) multiplications per sample, and are
    evaluated directly every ``ANCHOR`` samples so that rounding cannot accumulate;
    ``dt`` = 0 evaluates every sample directly.
    """
    zeta, wn, gain, offset, delay = p[0], p[1], p[2], p[3], p[4]
    q = 1.0 - zeta * zeta
    under = q > 0.0
    root = math.sqrt(abs(q))
    # the recurrence loses precision when the oscillation or the split of the two real
    # exponentials moves too little per sample (near critical damping): direct there
    rec = dt > 0.0 and root * wn * dt >= 1e-4
    if rec:
        h_dt = wn * dt
        if under:
            ed = math.exp(-zeta * h_dt)
            rc = ed * math.cos(root * h_dt)
            rs = ed * math.sin(root * h_dt)
        else:
            f1 = math.exp(-h_dt / (zeta + root))
            f2 = math.exp(-(zeta + root) * h_dt)
    inv_root = 1.0 / root if root > 0.0 else 0.0
    inv_q = 1.0 / q if q != 0.0 else 0.0
    ssr = 0.0
    # J^T J and J^T r in registers (the offset's column is 1)
    a00 = a10 = a11 = a20 = a21 = a22 = a30 = a31 = a32 = a33 = 0.0
    a40 = a41 = a42 = a43 = a44 = 0.0
    g0 = g1 = g2 = g3 = g4 = 0.0
    j0 = j1 = j2 = j4 = 0.0
    k = 0
    # recurrence state: exp(-zeta x) (cos, sin)(sqrt(q) x) and exp(-zeta x); or the two
    # real exponentials exp(-(zeta -+ r) x)
    zc = zs = e = e1 = e2 = 0.0
    for i in range(t.size):
        tau = t[i] - delay
        if tau > 0.0:
            x = wn * tau
            if not rec:
                eC, eS, eD = _terms(x, zeta, q)
            else:
                if k == 0:
                    k = ANCHOR
                    e = math.exp(-zeta * x)
                    if under:
                        zc = e * math.cos(root * x)
                        zs = e * math.sin(root * x)
                    else:
                        e1 = math.exp(-x / (zeta + root))
                        e2 = math.exp(-(zeta + root) * x)
                else:
                    if under:
                        zc, zs = zc * rc - zs * rs, zc * rs + zs * rc
                        e *= ed
                    else:
                        e1 *= f1
                        e2 *= f2
                    if (e if under else e1) < 1e-250:
                        # flush: denormals are slow and the terms are nil here
                        zc = zs = e = e1 = e2 = 0.0
                k -= 1
                if under:
                    eC = zc
                    eS = zs * inv_root
                else:
                    eC = 0.5 * (e1 + e2)
                    eS = (e1 - e2) * (0.5 * inv_root)
                qx2 = q * x * x
                if abs(qx2) <= 1e-3:
                    if not under:
                        e = math.sqrt(e1 * e2)
                    eD = e * x * x * x * (-1.0 / 3.0 + qx2 / 30.0 - qx2 * qx2 / 840.0)
                else:
                    eD = (x * eC - eS) * inv_q
            h = 1.0 - (eC + zeta * eS)
            r = offset + gain * h - y[i]
            if need_jac:
                j0 = gain * eD
                j1 = gain * tau * eS
                j2 = h
                j4 = -gain * wn * eS
        else:
            r = offset - y[i]
            if need_jac:
                j0 = j1 = j2 = j4 = 0.0
        ssr += r * r
        if need_jac:
            a00 += j0 * j0
            a10 += j1 * j0
            a11 += j1 * j1
            a20 += j2 * j0
            a21 += j2 * j1
            a22 += j2 * j2
            a30 += j0
            a31 += j1
            a32 += j2
            a33 += 1.0
            a40 += j4 * j0
            a41 += j4 * j1
            a42 += j4 * j2
            a43 += j4
            a44 += j4 * j4
            g0 += j0 * r
            g1 += j1 * r
            g2 += j2 * r
            g3 += r
            g4 += j4 * r
    if need_jac:
        A[0, 0], A[1, 1], A[2, 2], A[3, 3], A[4, 4] = a00, a11, a22, a33, a44
        A[1, 0] = A[0, 1] = a10
        A[2, 0] = A[0, 2] = a20
        A[2, 1] = A[1, 2] = a21
        A[3, 0] = A[0, 3] = a30
        A[3, 1] = A[1, 3] = a31
        A[3, 2] = A[2, 3] = a32
        A[4, 0] = A[0, 4] = a40
        A[4, 1] = A[1, 4] = a41
        A[4, 2] = A[2, 4] = a42
        A[4, 3] = A[3, 4] = a43
        g[0], g[1], g[2], g[3], g[4] = g0, g1, g2, g3, g4
    return 0.5 * ssr


@njit(cache=True)
def _solve_spd(M, b, x):
    """Solve M x = b for a symmetric positive definite 5 x 5 M (Cholesky); False if not
    positive definite."""
    n = b.size
    L = np.zeros((n, n))
    for i in range(n):
        for k in range(i + 1):
            s = M[i, k]
            for m in range(k):
                s -= L[i, m] * L[k, m]
            if i == k:
                if s <= 0.0:
                    return False
                L[i, i] = math.sqrt(s)
            else:
                L[i, k] = s / L[k, k]
    z = np.empty(n)
    for i in range(n):
        s = b[i]
        for m in range(i):
            s -= L[i, m] * z[m]
        z[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = z[i]
        for m in range(i + 1, n):
            s -= L[m, i] * x[m]
        x[i] = s / L[i, i]
    return True


@njit(cache=True)
def _jacobian_normal_equations(t, y, p, A, g, dt):
    """:func:`_normal_equations` with the Jacobian, for a caller outside the kernels. From
    Python the flag would be a plain bool, a third compile of that function beside the two
    the kernels use (their constant ``True`` and ``False`` are typed as literals); through
    here the caller shares the kernels' ``True`` one."""
    return _normal_equations(t, y, p, A, g, True, dt)


@njit(cache=True)
def _levenberg_marquardt(t, y, p, lo, hi, max_iter, dt):
    """Bounded Levenberg-Marquardt from ``p`` (changed in place) with Marquardt's scaling
    (the diagonal of J^T J); a parameter on a bound that the gradient pushes outward is
    held for that iteration, the rest of the step is projected on the box. Returns
    (half the sum of squared residuals, iterations)."""
    A = np.empty((5, 5))
    g = np.empty(5)
    A_new = np.empty((5, 5))
    g_new = np.empty(5)
    M = np.empty((5, 5))
    rhs = np.empty(5)
    dp = np.empty(5)
    trial = np.empty(5)
    held = np.zeros(5, dtype=np.bool_)
    cost = _normal_equations(t, y, p, A, g, True, dt)
    lam = 1e-3
    it = 0
    while it < max_iter:
        it += 1
        dmax = 0.0
        for a in range(5):
            dmax = max(dmax, A[a, a])
        if dmax <= 0.0 or not math.isfinite(cost):
            break
        # held parameters: on a bound with the descent direction (-g) pointing out
        for a in range(5):
            held[a] = (p[a] <= lo[a] and g[a] > 0.0) or (p[a] >= hi[a] and g[a] < 0.0)
        for a in range(5):
            for b in range(5):
                M[a, b] = 0.0 if held[a] or held[b] else A[a, b]
            if held[a]:
                M[a, a] = 1.0
                rhs[a] = 0.0
            else:
                M[a, a] = A[a, a] + lam * max(A[a, a], 1e-12 * dmax)
                rhs[a] = -g[a]
        if not _solve_spd(M, rhs, dp):
            lam *= 10.0
            if lam > 1e20:
                break
            continue
        small_step = True
        for a in range(5):
            trial[a] = min(max(p[a] + dp[a], lo[a]), hi[a])
            if abs(trial[a] - p[a]) > 1e-12 * (abs(p[a]) + 1e-12):
                small_step = False
        if small_step:
            break
        new = _normal_equations(t, y, trial, A_new, g_new, True, dt)
        if new < cost:
            gain = cost - new
            # element by element, not p[:] = trial: a slice assigned from an array makes numba
            # compile its shape-mismatch message (f-strings, str.join) for each rank: 3 to 5
            # of the fit kernels' 21 to 23 CPU-s of compile; the sizes here are fixed
            for a in range(5):
                p[a] = trial[a]
                g[a] = g_new[a]
                for b in range(5):
                    A[a, b] = A_new[a, b]
            cost = new
            lam = max(lam * 0.3, 1e-12)
            if gain <= 1e-13 * cost:
                break
        else:
            lam *= 4.0
            if lam > 1e20:
                break
    return cost, it


# ---------------------------------------------------------------------------------------
# the preparation: smoothing, validation, log decrement
# ---------------------------------------------------------------------------------------

@njit(cache=True)
def _savgol2(y, win):
    """scipy.signal.savgol_filter(y, win, 2) (mode "interp": the edges take the quadratic
    fitted to the first and last windows)."""
    n = y.size
    m = win // 2
    # least-squares quadratic on u = -m..m: P = V (V^T V)^-1 V^T, its rows are the filters
    V = np.empty((win, 3))
    for k in range(win):
        u = float(k - m)
        V[k, 0] = 1.0
        V[k, 1] = u
        V[k, 2] = u * u
    P = V @ np.linalg.inv(V.T @ V) @ V.T
    out = np.empty(n)
    for i in range(m, n - m):
        s = 0.0
        for k in range(win):
            s += P[m, k] * y[i - m + k]
        out[i] = s
    for i in range(m):
        s = 0.0
        e = 0.0
        for k in range(win):
            s += P[i, k] * y[k]
            e += P[win - m + i, k] * y[n - win + k]
        out[i] = s
        out[n - m + i] = e
    return out


@njit(cache=True)
def _peaks(x, min_prominence):
    """Indices of the local maxima of ``x`` with at least ``min_prominence``, as
    scipy.signal.find_peaks(x, prominence=min_prominence) finds them (plateaus give
    their middle; prominence over the whole signal)."""
    n = x.size
    cand = np.empty(n, dtype=np.int64)
    nc = 0
    i = 1
    while i < n - 1:
        if x[i - 1] < x[i]:
            ahead = i + 1
            while ahead < n - 1 and x[ahead] == x[i]:
                ahead += 1
            if x[ahead] < x[i]:
                cand[nc] = (i + ahead - 1) // 2
                nc += 1
                i = ahead
        i += 1
    out = np.empty(nc, dtype=np.int64)
    no = 0
    for c in range(nc):
        # prominent when on both sides the signal falls by min_prominence before it rises
        # above the peak: each side's scan stops as soon as it knows (the same peaks as
        # scanning to the higher point, in time linear in the signal's length)
        # (x[pk] - min(side) >= p holds exactly when x[pk] - x[j] >= p for some j of
        # the side: subtraction rounds monotonically)
        pk = cand[c]
        top = x[pk]
        left = False
        j = pk
        while j >= 0 and x[j] <= top:
            if top - x[j] >= min_prominence:
                left = True
                break
            j -= 1
        if not left:
            continue
        j = pk
        while j <= n - 1 and x[j] <= top:
            if top - x[j] >= min_prominence:
                out[no] = pk
                no += 1
                break
            j += 1
    return out[:no]


@njit(cache=True, inline="always")
def _grid_and_bounds(t, n):
    """The sample spacing when ``t`` (starting at 0) is a uniform grid to 1e-9 of its spacing
    (the model then advances by recurrence), else 0; and the parameters' bounds (zeta, wn,
    gain, offset, delay: the delay within the first half of the record)."""
    dt = t[n - 1] / (n - 1)
    for i in range(n):
        if abs(t[i] - i * dt) > 1e-9 * dt:
            dt = 0.0
            break
    lo = np.array([ZETA_MIN, 1e-2, -np.inf, -np.inf, 0.0])
    hi = np.array([ZETA_MAX, 1e5, np.inf, np.inf, 0.5 * t[n - 1]])
    return dt, lo, hi


@njit(cache=True)
def _fit_one(t_in, y, out):
    """Identify one response; fills ``out`` (N_OUT,) and returns the status code."""
    n = t_in.size
    out[:] = math.nan
    out[C_N] = n
    if n < 20:
        return SHORT
    for i in range(n):
        if not (math.isfinite(t_in[i]) and math.isfinite(y[i])):
            return NONFINITE
    for i in range(n - 1):
        if not t_in[i + 1] - t_in[i] > 0.0:
            return NOT_INCREASING
    t = t_in - t_in[0]
    nh = max(3, n // 50)
    nt = max(5, n // 5)
    y0 = np.mean(y[:nh])
    yf = np.mean(y[n - nt:])
    step = yf - y0
    span = np.max(y) - np.min(y)
    out[C_STEP] = step
    out[C_SPAN] = span
    if span <= 1e-12 * max(1.0, np.max(np.abs(y))):
        return FLAT
    win = max(5, (n // 60) | 1)
    sm = _savgol2(y, win) if n > win else y.copy()
    resid = y - sm
    noise = 1.4826 * np.median(np.abs(resid - np.median(resid)))
    out[C_NOISE] = noise
    if abs(step) < 8.0 * noise or abs(step) < 0.05 * span:
        return NOT_STEP

    # the thesis's log decrement (peak-to-valley amplitudes one period apart): first start
    dev = (sm - yf) / step
    prom = max(0.005, 4.0 * np.std(y[1:] - y[:-1]) / abs(step))   # np.diff's numbers; its compile cost 3 s
    peaks = _peaks(dev, prom)
    valleys = _peaks(-dev, prom)
    n_peaks = peaks.size
    out[C_NPEAKS] = n_peaks
    starts = np.empty((4, 2))
    ns = 0
    pair = np.empty((2, 2), dtype=np.int64)
    npair = 0
    for pk in peaks:
        if npair == 2:
            break
        for v in valleys:
            if v > pk:
                pair[npair, 0] = pk
                pair[npair, 1] = v
                npair += 1
                break
    if npair == 2:
        a1 = dev[pair[0, 0]] - dev[pair[0, 1]]
        a2 = dev[pair[1, 0]] - dev[pair[1, 1]]
        if a2 > 0.0 and a1 > a2:
            delta = math.log(a1 / a2)
            zeta = delta / math.sqrt(4.0 * math.pi ** 2 + delta ** 2)
            fd = 1.0 / (t[pair[1, 0]] - t[pair[0, 0]])
            starts[0, 0] = zeta
            starts[0, 1] = 2.0 * math.pi * fd / math.sqrt(1.0 - zeta ** 2)
            ns = 1
    # rise time gives a scale for wn when there is no oscillation; without two peaks the
    # damping is high, so start there
    t50 = t[n - 1] / 4.0
    for i in range(n):
        if (y[i] - y0) / step > 0.5:
            t50 = t[i]
            break
    zs = (0.2, 0.7, 1.5) if n_peaks >= 2 else (0.9, 1.5, 0.4)
    for z in zs:
        starts[ns, 0] = z
        starts[ns, 1] = 1.8 / max(t50, 1e-3) * (1.0 + 0.6 * z)
        ns += 1

    dt, lo, hi = _grid_and_bounds(t, n)
    ym = np.mean(y)
    sst = 0.0
    for i in range(n):
        sst += (y[i] - ym) ** 2
    best = np.empty(5)
    best_cost = np.inf
    p = np.empty(5)
    used = 0
    iters = 0
    for s in range(ns):
        p[0] = min(max(starts[s, 0], 2e-3), 99.0)
        p[1] = min(max(starts[s, 1], 2e-2), 9e4)
        p[2] = step
        p[3] = y0
        p[4] = 0.0
        cost, k = _levenberg_marquardt(t, y, p, lo, hi, 200, dt)
        used += 1
        iters += k
        # two starts that end in one minimum (the same cost, zeta and wn): the search has
        # found it from both sides, the remaining starts are not tried
        same = (used > 1 and math.isfinite(best_cost) and abs(cost - best_cost) <= SAME_COST * best_cost
                and abs(p[0] - best[0]) <= SAME_PARAM * best[0] and abs(p[1] - best[1]) <= SAME_PARAM * best[1])
        if cost < best_cost:
            best_cost = cost
            for a in range(5):
                best[a] = p[a]
        if same or 2.0 * cost < (1.0 - R2_ENOUGH) * sst:
            break
    if best[0] != 1.0 and abs(best[0] - 1.0) <= 1e-6:
        # the model takes this band as critical damping (no damped frequency): a fit that
        # lands in it is critically damped in the model's own terms
        best[0] = 1.0
        best_cost = _normal_equations(t, y, best, np.empty((5, 5)), np.empty(5), False, dt)
    out[C_ZETA] = best[0]
    out[C_WN] = best[1]
    out[C_GAIN] = best[2]
    out[C_OFFSET] = best[3]
    out[C_DELAY] = best[4]
    out[C_COST] = best_cost
    out[C_STARTS] = used
    out[C_ITERS] = iters
    r2 = 1.0 - 2.0 * best_cost / sst
    out[C_R2] = r2
    if best[0] >= 0.99 * ZETA_MAX:
        return ZETA_BOUND
    if not r2 >= MIN_R2:
        return LOW_R2
    if best[0] <= 1.01 * ZETA_MIN:
        # a bound is not an identified value: the data want no decay (a sustained or
        # growing oscillation), which no step response of a damped system shows
        return NO_DECAY
    return OK


@njit(cache=True)
def _refit_one(t_in, y, p0, out):
    """Fit the model to (``t_in``, ``y``) from the parameters ``p0`` (one start: the
    minimum nearest to them); ``out`` gets zeta, wn, gain, offset, delay (NaN where the fit
    ends on a bound of zeta or does not explain half the response)."""
    n = t_in.size
    out[:] = math.nan
    if n < 20:
        return
    t = t_in - t_in[0]
    dt, lo, hi = _grid_and_bounds(t, n)
    p = np.empty(5)
    for a in range(5):
        p[a] = min(max(p0[a], lo[a]), hi[a])
    cost, _ = _levenberg_marquardt(t, y, p, lo, hi, 200, dt)
    ym = np.mean(y)
    sst = 0.0
    for i in range(n):
        sst += (y[i] - ym) ** 2
    if not (sst > 0.0 and 1.0 - 2.0 * cost / sst >= MIN_R2) or p[0] >= 0.99 * ZETA_MAX or p[0] <= 1.01 * ZETA_MIN:
        return
    for a in range(5):
        out[a] = p[a]


@njit(cache=True, nogil=True)
def _refit_packed(t, y, bounds, p0s, out):
    """:func:`_refit_one` of every packed response from its row of ``p0s``."""
    for k in range(bounds.size - 1):
        a, b = bounds[k], bounds[k + 1]
        _refit_one(t[a:b], y[a:b], p0s[k], out[k])


def refit_from(ts, ys, starts) -> np.ndarray:
    """Fit each response (``ts`` [s], ``ys``, equal-length 1-D arrays) from its own start
    (rows of ``starts``: zeta, wn [rad/s], gain, offset, delay [s]) with one bounded
    Levenberg-Marquardt run, in one compiled call: the minimum nearest to the start, as a
    fit's refits on parts of its record need. Returns (K, 5) parameters (NaN rows for a fit
    that ends on a bound of zeta or explains less than :data:`MIN_R2`)."""
    t, y, bounds = _pack(ts, ys)
    out = np.empty((bounds.size - 1, 5))
    p0s = np.ascontiguousarray(starts, dtype=float).reshape(-1, 5)
    over_cores(lambda k0, k1: _refit_packed(t, y, bounds[k0:k1 + 1], p0s[k0:k1], out[k0:k1]), bounds.size - 1, 4,
               serial_below=PARALLEL_FROM)
    return out


@njit(cache=True, nogil=True)
def _fit_packed(t, y, bounds, out, status):
    """:func:`_fit_one` of every packed response (rows of ``out`` and ``status``); called
    on parts of a batch from threads (:func:`leglib.cores.over_cores`): each response is
    fitted alone, the same numbers."""
    for k in range(bounds.size - 1):
        a, b = bounds[k], bounds[k + 1]
        status[k] = _fit_one(t[a:b], y[a:b], out[k])


@njit(cache=True)
def _shape_row(t, y, out):
    """A response's start (mean of its first n/50 samples, at least 3) and final value (of
    its last n/5, at least 5), its largest excursion beyond the final value in the step's
    direction, and the median of its sample spacings."""
    n = y.size
    out[:] = math.nan
    if n < 2:
        return
    nh = min(n, max(3, n // 50))
    nt = min(n, max(5, n // 5))
    start = np.mean(y[:nh])
    final = np.mean(y[n - nt:])
    sign = 1.0 if final - start > 0.0 else -1.0
    peak = -np.inf
    for i in range(n):
        peak = max(peak, sign * (y[i] - final))
    out[0], out[1], out[2] = start, final, peak
    out[3] = np.median(t[1:] - t[:-1])   # np.diff(t), as above


@njit(cache=True)
def _shapes_packed(t, y, bounds, out):
    for k in range(bounds.size - 1):
        _shape_row(t[bounds[k]:bounds[k + 1]], y[bounds[k]:bounds[k + 1]], out[k])


def _pack(ts, ys):
    """(t, y, bounds): the responses one after another, response k at bounds[k]:bounds[k + 1]."""
    sizes = np.fromiter((np.size(t) for t in ts), dtype=np.int64, count=len(ts))
    bounds = np.zeros(sizes.size + 1, dtype=np.int64)
    np.cumsum(sizes, out=bounds[1:])
    t = np.concatenate([np.asarray(x, dtype=float).ravel() for x in ts]) if len(ts) else np.empty(0)
    y = np.concatenate([np.asarray(x, dtype=float).ravel() for x in ys]) if len(ys) else np.empty(0)
    return t, y, bounds


def _shapes(t, y, bounds) -> np.ndarray:
    out = np.empty((bounds.size - 1, 4))
    _shapes_packed(t, y, bounds, out)
    return out


def shape_numbers(ts, ys) -> np.ndarray:
    """Per response (equal-length 1-D t and y): start, final value, the peak beyond the
    final value in the step's direction, median sample spacing [s] -- what
    :func:`leglib.design.points.step_shape_problem` judges, for many responses in one call."""
    return _shapes(*_pack(ts, ys))


# below this many responses one thread fits them (the thread pool costs more than it gives)
PARALLEL_FROM = 16


# ---------------------------------------------------------------------------------------
# the Python side
# ---------------------------------------------------------------------------------------

def fit_packed(ts, ys):
    """Identify many responses in one compiled call.

    Parameters
    ----------
    ts, ys : sequences of (N_k,) float arrays: times [s] and responses, of any lengths;
        each pair must already have equal 1-D shapes

    Returns
    -------
    status : (K,) int array, ``OK`` or the reason it failed (module constants)
    out : (K, N_OUT) float array, one row per response (columns ``C_*``: zeta [-],
        wn [rad/s], gain, offset, delay [s], r2, n_peaks, step, span, noise, n, cost,
        starts and iterations used)
    """
    return _fit(*_pack(ts, ys))


def _fit(t, y, bounds):
    k = bounds.size - 1
    out = np.empty((k, N_OUT))
    status = np.empty(k, dtype=np.int64)
    # responses handed out a few at a time: their fits differ in cost
    over_cores(lambda k0, k1: _fit_packed(t, y, bounds[k0:k1 + 1], out[k0:k1], status[k0:k1]), k, 4,
               serial_below=PARALLEL_FROM)
    return status, out




