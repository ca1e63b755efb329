"""The thesis read as it computed: Listing 7.7 against an independent transcription, the
bias of its estimate, Table 6.1, Listing 7.8, Fig. 6.9's gains, eq. 5.11's inputs, the g2
sign and the virtual leg of eqs. 6.1/6.3."""

import math

import numpy as np
import pytest

from leglib import model as M
from leglib import thesis as T
from leglib.identify.listing77 import ThesisReading, matlab_smooth
from leglib.identify.step import IdentificationError, second_order
from leglib.identify.step import model as _model
from leglib.params import load_leg

# --- an independent, line-by-line transcription of Listing 7.7 --------------------------

def _smooth_listing(y):
    # MATLAB smooth(y) with its default span 5: yy(1) = y(1), yy(2) = (y(1)+y(2)+y(3))/3,
    # yy(k) = mean(y(k-2:k+2)), symmetric at the end
    n = len(y)
    out = []
    for k in range(n):
        h = min(2, k, n - 1 - k)
        out.append(sum(y[k - h:k + h + 1]) / (2 * h + 1))
    return out


def _findpeaks_listing(x, t):
    # MATLAB findpeaks(x, t), default options: a sample above its left neighbour and above
    # the next different sample to its right (a plateau counts once, at its first sample);
    # the first and the last sample are never peaks
    pks, locs = [], []
    n = len(x)
    k = 1
    while k < n - 1:
        if x[k] > x[k - 1]:
            j = k
            while j + 1 < n and x[j + 1] == x[k]:
                j += 1
            if j + 1 < n and x[j + 1] < x[k]:
                pks.append(x[k])
                locs.append(t[k])
            k = j + 1
        else:
            k += 1
    return pks, locs


def identify_params_listing(t, angle1_deg, angle2_deg):
    """Listing 7.7, lines 27-46: returns [wn, xi]."""
    y = [0.16 * math.cos(math.radians(a)) + 0.16 * math.cos(math.radians(b)) for a, b in zip(angle1_deg, angle2_deg)]
    pks, locs = _findpeaks_listing(_smooth_listing([-v for v in y]), list(t))
    if len(pks) == 0:
        return 0.0, 2.0
    if len(pks) == 1:
        return 0.0, 1.0
    delta = -math.log(pks[0] / pks[1])
    xi = delta / math.sqrt((2 * math.pi) ** 2 + delta ** 2)
    wn = 1 / (locs[1] - locs[0])
    return wn, xi


def _angles(zeta, fd, step=48.0, dt=0.002, n=750, noise=0.0, seed=0, quantum=None):
    t = np.arange(n) * dt
    wn = 2 * math.pi * fd / math.sqrt(1 - zeta ** 2)
    a = _model(t, zeta, wn, step, 0.0, 0.0)
    rng = np.random.default_rng(seed)
    a1, a2 = a + noise * rng.standard_normal(n), -a + noise * rng.standard_normal(n)
    if quantum:
        a1, a2 = np.round(a1 / quantum) * quantum, np.round(a2 / quantum) * quantum
    return t, a1, a2


@pytest.mark.parametrize("zeta", [0.05, 0.1, 0.229, 0.4, 0.6])
@pytest.mark.parametrize("fd", [2.0, 5.0, 9.0])
def test_thesis_method_equals_listing_7_7_on_smooth_responses(zeta, fd):
    t, a1, a2 = _angles(zeta, fd)
    wn_l, xi_l = identify_params_listing(t, a1, a2)
    r = second_order(t, M.thesis_listing_height(a1, a2), method="thesis")
    assert isinstance(r, ThesisReading) and r.method == "thesis" and not r.flagged
    assert r.zeta == pytest.approx(xi_l, rel=0.01)
    assert r.fd == pytest.approx(wn_l, rel=0.01)
    assert r.listing_output == pytest.approx((wn_l, xi_l), rel=0.01)


@pytest.mark.parametrize("seed", range(4))
def test_thesis_method_equals_listing_on_quantized_noisy_angles(seed):
    # 4000 counts per motor turn, 1:3 belt: 0.03 deg per count, with noise: plateaus and
    # spurious peaks; the transcription and leglib must still agree peak for peak
    t, a1, a2 = _angles(0.2, 5.0, noise=0.05, seed=seed, quantum=360 / 4000 / 3)
    wn_l, xi_l = identify_params_listing(t, a1, a2)
    r = second_order(t, M.thesis_listing_height(a1, a2), method="thesis")
    assert r.zeta == pytest.approx(xi_l, rel=1e-9, abs=1e-12)
    assert r.listing_output[0] == pytest.approx(wn_l, rel=1e-9)


def test_one_or_no_peak_gives_the_listings_constants_flagged():
    t = np.arange(750) * 0.002
    rising = M.thesis_listing_height(48 * (1 - np.exp(-t / 0.05)), 0 * t)      # -y rises monotonically
    r = second_order(t, rising, method="thesis")
    assert r.zeta == 2.0 and r.flagged and r.n_peaks == 0 and math.isnan(r.fd) and r.listing_output == (0.0, 2.0)
    bump = M.thesis_listing_height(48 * np.exp(-((t - 0.5) / 0.1) ** 2), 0 * t)  # one swing out and back
    r = second_order(t, bump, method="thesis")
    assert r.zeta == 1.0 and r.flagged and r.n_peaks == 1 and r.listing_output == (0.0, 1.0)
    wn_l, xi_l = identify_params_listing(t, 48 * np.exp(-((t - 0.5) / 0.1) ** 2), 0 * t)
    assert (wn_l, xi_l) == (0.0, 1.0)


def test_thesis_method_rejects_bad_data_clearly():
    t = np.arange(10) * 0.01
    with pytest.raises(IdentificationError, match="NaN"):
        second_order(t, np.where(t > 0.05, np.nan, 1.0), method="thesis")
    with pytest.raises(IdentificationError, match="increase"):
        second_order(t[::-1], np.ones(10), method="thesis")
    with pytest.raises(ValueError, match="method must be one of"):
        second_order(t, np.ones(10), method="listing")


def test_matlab_smooth_end_spans():
    y = np.array([1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0])
    s = matlab_smooth(y)
    assert s[0] == 1.0 and s[-1] == 64.0
    assert s[1] == pytest.approx(7 / 3) and s[-2] == pytest.approx(112 / 3)
    assert s[3] == pytest.approx(np.mean(y[1:6]))


def test_listing_height_is_cosine_of_zeroed_degrees():
    assert M.thesis_listing_height(0.0, 0.0) == pytest.approx(0.32)
    assert M.thesis_listing_height(48.0, -48.0) == pytest.approx(0.32 * math.cos(math.radians(48)))
    q = np.radians([267.0, 260.0, 250.0])
    assert M.zeroed_degrees(q) == pytest.approx([0.0, -7.0, -17.0])


# --- the bias of Listing 7.7, and the thesis's numbers in true terms ---------------------

def test_listing_7_7_is_biased_and_falls_with_true_damping():
    rows = T.bias_table(zetas=(0.1, 0.229, 0.4, 0.6), fd=5.0)
    z = [r["thesis_zeta"] for r in rows]
    # the figures for ideal 48-degree steps, re-derived independently above
    for r in rows:
        t, a1, a2 = _angles(r["true_zeta"], 5.0)
        assert r["thesis_zeta"] == pytest.approx(identify_params_listing(t, a1, a2)[1], rel=0.01)
        assert r["thesis_f_hz"] == pytest.approx(5.0, rel=0.01)   # 1/(t2 - t1) is fd
    assert z[0] > 0.1 and all(b < 0.5 * a for a, b in zip([0.229, 0.4, 0.6], z[1:]))
    assert all(b < a for a, b in zip(z, z[1:]))


def test_true_from_reading_inverts_the_listing():
    true = T.true_from_reading(*T.THESIS_RESULT)
    assert 0.02 < true["zeta"] < T.THESIS_RESULT[0]           # far less damped than it reads
    assert true["fd"] == T.THESIS_RESULT[1]
    assert true["fn"] == pytest.approx(true["fd"] / math.sqrt(1 - true["zeta"] ** 2))
    back = T.ideal_reading(true["zeta"], true["fd"])
    assert back.zeta == pytest.approx(T.THESIS_RESULT[0], rel=1e-3)
    with pytest.raises(ValueError, match="not reached"):
        T.true_from_reading(3.0, 5.0)


# --- errata ---------------------------------------------------------------------------------

def test_listing_7_8_and_fig_6_9():
    assert T.LISTING_7_8_TARGET[0] != T.TEXT_TARGET[0]
    on = T.gains_on_listing_grid(T.FIG_6_9_GAINS)
    assert on["pos_gain"]["on_grid"]
    assert not on["vel_gain"]["on_grid"]                       # 0.046 is between 0.0416 and 0.0613
    assert not on["vel_integrator_gain"]["inside"]             # 0.001 below the grid's 0.002
    pos, vel, vint = T.listing_7_4_axes()
    assert vel[2] < 0.046 < vel[3] and vint[0] == 0.002


def test_table_6_1_inconsistencies():
    rows = {r["claim"]: r for r in T.table_6_1_checks()}
    ra = rows["R_a (twice the phase resistance, Krishnan)"]
    assert ra["derived"] == pytest.approx(2 * 0.069) and ra["ratio"] > 8
    assert rows["K_t [N m/A]"]["derived"] == pytest.approx(8.27 / 340)
    assert rows["K_b [V s/rad] (= K_t in SI)"]["ratio"] == pytest.approx(3.0, rel=0.01)
    # t_m = J R_a / K_t^2 holds with K_b = K_t, not with the printed K_b
    assert rows["t_m [s] = J R_a / K_t^2"]["ratio"] == pytest.approx(1.0, rel=0.01)
    assert rows["t_m [s] = J R_a / (K_t K_b)"]["ratio"] == pytest.approx(3.0, rel=0.01)


def test_eq511_inputs_reproduced_whatever_the_guessed_masses():
    leg = load_leg("thesis")
    L = T.eq511_lumped(leg.q0, leg.g)
    assert L["d11"] == pytest.approx(1 / 324.85) and L["c22"] == pytest.approx(30.22 / 308.35)
    rows = T.eq511_sensitivity(leg, masses=(0.085, 0.1, 0.115))
    for r in rows:
        # the thesis form is an input: reproduced by construction for every guess
        assert np.allclose(r["thesis_A"], M.THESIS_A, rtol=0.01, atol=0.01)
        assert r["lc3_on_link"] and r["lc4_on_link"] and r["Jd_positive"]
    # the exact model's A is an output: it moves with the guess
    a10 = [r["A10"] for r in rows]
    assert abs(a10[0] / a10[2] - 1) > 0.2
    middle = rows[1]
    assert middle["lc3"] == pytest.approx(leg.lc3, rel=1e-4) and middle["Jd1"] == pytest.approx(leg.Jd1, rel=1e-4)
    # too light a lower link puts its centre of mass beyond the link: not physical
    light = T.eq511_sensitivity(leg, masses=(0.07,))[0]
    assert not (light["lc3_on_link"] and light["lc4_on_link"])


def test_g2_sign_the_geometry_supports_is_the_listings():
    leg = load_leg("thesis")
    c = T.g2_sign_check(leg)
    assert c["supported"] == "+"
    assert c["A32_listing"] == pytest.approx(M.THESIS_A[3, 2], rel=0.01)
    # the exact coaxial five-bar is near the listing's stiffness, an order above eq. 5.4's
    assert c["k22_exact"] > 5 * c["k22_eq54"]
    assert abs(c["k22_exact"] / c["k22_listing"] - 1) < 0.3
    assert c["A32_exact"] < -50


# --- eqs. 6.1 / 6.3 ------------------------------------------------------------------------

def test_virtual_leg_reproduces_the_second_order_system():
    v = T.virtual_leg(0.3, 5.0, 2.0)
    wn = 2 * math.pi * 5.0
    # 1/(m s^2 + b s + k) has the poles of s^2 + 2 zeta wn s + wn^2 and static gain 1/k
    assert v.k / v.m == pytest.approx(wn ** 2)
    assert v.b / (2 * math.sqrt(v.k * v.m)) == pytest.approx(0.3)
    assert v.k_dc == pytest.approx(1 / v.k)
    with pytest.raises(ValueError, match="mass"):
        T.virtual_leg(0.3, 5.0, 0.0)


def test_foot_mass_is_the_operational_space_inertia():
    leg = load_leg("thesis")
    q = T.step_end_pose(leg)
    m = T.foot_mass(leg, q)
    # a vertical force F at the foot: tau = J^T F, qdd = D^-1 tau, ydd = J qdd -> F / m
    eps = 1e-6
    J = np.column_stack([(np.array(M.foot_position(leg, q[0] + e0, q[1] + e1))
                          - np.array(M.foot_position(leg, q[0] - e0, q[1] - e1))) / (2 * eps)
                         for e0, e1 in ((eps, 0), (0, eps))])
    D = M.mass_matrix(leg, *q)
    ydd = J @ np.linalg.solve(D, J.T @ np.array([0.0, 1.0]))
    assert m == pytest.approx(1 / ydd[1], rel=1e-6)
    assert 0.1 < m < 20


def test_listing_7_7_says_where_it_fails():
    """Its failures are named, never shown as readings: the listing's constants (fewer than
    two peaks), a second peak that is ripple of the settled tail, and more peaks than an
    oscillation at its own frequency has (the quantized tail's ripple counted as peaks)."""
    # an ideal step: two genuine peaks, no more than its cycles
    r = T.ideal_reading(0.1, 5.0)
    assert r.usable and r.problem is None
    # a well-damped step with the encoder's quantization: its tail's ripple has "peaks"
    t = np.arange(750) * 0.002
    rng = np.random.default_rng(0)
    a = _model(t, 0.8, 50.0, T.STEP_DEG, 0.0, 0.0) + 0.02 * rng.standard_normal(t.size)
    a = np.round(a / 0.03) * 0.03                  # the listing's degrees, one count of 0.03 deg
    y = M.thesis_listing_height(a, -a)
    q = second_order(t, y, method="thesis")
    assert q.n_peaks >= 2 and not q.usable and "ripple" in q.problem
    # many peaks after two genuine ones: usable, but the listing's assumption fails
    a = _model(t, 0.3, 40.0, T.STEP_DEG, 0.0, 0.0)
    a = np.round(a / 0.03) * 0.03 + 0.03 * (np.arange(t.size) % 8 < 4) * (t > 0.8)
    m = second_order(t, M.thesis_listing_height(a, -a), method="thesis")
    assert m.n_peaks > (t[-1] - m.peak_times[0]) * m.fd + 2
    assert m.usable and "findpeaks finds" in m.problem
    # the listing's constants
    flat = second_order(t, M.thesis_listing_height(np.linspace(0, 48, t.size), -np.linspace(0, 48, t.size)),
                        method="thesis")
    assert flat.flagged and not flat.usable and "fewer than two peaks" in flat.problem


def test_bias_and_reach_use_only_what_both_measures_identify():
    rows = [{"gains": (1, 1, 1), "status": "ok", "thesis_zeta": 0.04, "thesis_f_hz": 5.0, "thesis_flagged": False,
             "thesis_usable": True, "thesis_problem": None, "first_peak_deg": 55.0, "zeta": 0.3, "fn": 5.3,
             "fd": 5.05},
            {"gains": (2, 1, 1), "status": "ok", "thesis_zeta": 0.9, "thesis_f_hz": 40.0, "thesis_flagged": False,
             "thesis_usable": False, "thesis_problem": "ripple", "first_peak_deg": 50.0, "zeta": 0.9, "fn": 9.0,
             "fd": 3.9},
            {"gains": (3, 1, 1), "status": "failed", "thesis_zeta": 0.5, "thesis_f_hz": 2.0, "thesis_flagged": False,
             "thesis_usable": True, "thesis_problem": None, "first_peak_deg": 70.0, "zeta": math.nan,
             "fn": math.nan, "fd": math.nan}]
    b = T.bias_summary(rows)
    assert b["points"] == 1 and b["ripple"] == 1 and b["flagged"] == 0
    assert b["zeta_rel_error_min_median_max"][1] == pytest.approx(0.04 / 0.3 - 1)
    reach = T.listing_reach(rows)
    assert reach["points"] == 1 and reach["max_thesis_zeta"] == 0.04 and reach["max_first_peak_deg"] == 55.0
    assert T.nearest_reading(rows, 0.24, 5.0)["gains"] == (1, 1, 1)


def test_angle_count_is_the_records_quantum():
    a = np.round(np.linspace(0, 48, 750) / 0.03) * 0.03
    assert T.angle_count(a) == pytest.approx(0.03)
    assert T.angle_count(np.linspace(0, 48, 750) + 1e-3 * np.sin(np.arange(750))) == 0.0   # not quantized
    assert T.angle_count(np.zeros(10)) == 0.0


def test_a_reading_against_its_target_uses_its_intervals():
    """Reached in the thesis's measure only when both 90 % intervals lie within the
    tolerance; the errors come with their intervals; a failed reading is no reading."""
    t = np.arange(750) * 0.002
    a = _model(t, 0.1, 2 * math.pi * 5.0 / math.sqrt(1 - 0.01), T.STEP_DEG, 0.0, 0.0)
    r = T.read_angles(t, np.round(a / 0.03) * 0.03, -np.round(a / 0.03) * 0.03)
    assert r.usable and r.zeta_interval[0] <= r.zeta <= r.zeta_interval[1]
    ok = T.reading_against(r, (r.zeta, r.fd))
    assert ok["reached"] and ok["error_zeta"] == 0 and ok["error_zeta_interval"][0] < 0 < ok["error_zeta_interval"][1]
    far = T.reading_against(r, (T.TEXT_TARGET[0], r.fd))
    assert not far["reached"] and "zeta" in far["verdict"] and far["error_zeta"] < -0.1
    # just inside the tolerance by the value but not by the interval: not reached
    edge = T.reading_against(r, (r.zeta / (1 + T.THESIS_TOLERANCE) * 1.0001, r.fd))
    assert abs(edge["error_zeta"]) <= T.THESIS_TOLERANCE and not edge["reached"]
    flat = T.read_angles(t, np.linspace(0, 48, t.size), -np.linspace(0, 48, t.size))
    none = T.reading_against(flat, T.TEXT_TARGET)
    assert not none["reached"] and "gives no reading" in none["verdict"] and math.isnan(none["error_zeta"])


def test_reach_carries_the_largest_readings_interval():
    rows = [{"gains": (1, 1, 1), "status": "ok", "thesis_zeta": 0.04, "thesis_zeta_interval": (0.039, 0.041),
             "thesis_f_hz": 5.0, "thesis_flagged": False, "thesis_usable": True, "thesis_problem": None,
             "first_peak_deg": 55.0, "zeta": 0.3},
            {"gains": (2, 1, 1), "status": "ok", "thesis_zeta": 0.03, "thesis_zeta_interval": (0.02, 0.045),
             "thesis_f_hz": 5.0, "thesis_flagged": False, "thesis_usable": True, "thesis_problem": None,
             "first_peak_deg": 54.0, "zeta": 0.35}]
    reach = T.listing_reach(rows)
    assert reach["max_thesis_zeta"] == 0.04 and reach["max_thesis_zeta_interval"] == [0.039, 0.041]
    assert reach["max_thesis_zeta_upper"] == 0.045      # another reading could be read higher by its doubt
    empty = T.listing_reach([])
    assert empty["points"] == 0 and math.isnan(empty["max_thesis_zeta_interval"][0])
