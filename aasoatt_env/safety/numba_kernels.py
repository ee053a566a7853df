"""The backup layer's compiled kernels (numba; imported only through :mod:`aasoatt_env.compiled`).

The same loops as :func:`~aasoatt_env.safety.gatekeeper.gatekeeper` and
:func:`~aasoatt_env.safety.repair.repair`, written once per pair and sample:

- :func:`gate_full`: one gatekeeper call (closed-form set-up per robot and
  level, the pairs that could meet, the rounds, the result);
- :func:`repair_full`: one repair call (its rounds of finite-difference lifts).

Both take the team, pair and obstacle block of
:func:`~aasoatt_env.safety.gatekeeper._kernel_args` (``diff, offset, cols,
turn_gain, max_wheel_accel, brake_decel, radius, group, has_group,
sensing_range, candidate pairs, obstacle centres (complex), radii, groups,
has_groups``), checked there: numba does not check bounds.  Every helper
repeats numpy's operations in numpy's order (the names say which numpy
function; :func:`_E1` takes one sine for two, noted there), with two
exceptions: a pair's distance on a step is ``sqrt(x^2 + y^2)`` (numpy's
``abs`` takes ``hypot``: the last bit), and the gatekeeper's braking samples
rotate by a recurrence (:func:`_fill_brake`: ~1e-13 of the path's length).
So the results differ from the reference by rounding alone; the repair's
rows keep the sines and cosines (its finite differences compare them with
:func:`_sample_at`'s closed form).
"""

from __future__ import annotations

import math

import numpy as np

from aasoatt_env.numba_jit import jit as _jit
from aasoatt_env.numba_jit import nmax as _nmax

__all__ = ["gate_full", "repair_full"]


_EPS = float(np.finfo(np.float64).eps)
_TWO_PI = 2.0 * np.pi
_PI = float(np.pi)
MAX_BRAKE_STEPS = 100_000
"""The value of :data:`aasoatt_env.safety.backup.MAX_BRAKE_STEPS` (a test checks they agree)."""


# --------------------------------------------------------------------------- one robot, closed form
@_jit
def _cabs(z):
    """``|z|`` by ``hypot``, as numpy's scalar code takes it."""
    return math.hypot(z.real, z.imag)


@_jit
def _sinc1(x):
    """:func:`~aasoatt_env.safety.backup._sinc` of one number."""
    y = _PI * x
    if y == 0.0:
        y = _EPS
    return math.sin(y) / y


@_jit
def _E1(x):
    """:func:`~aasoatt_env.safety.backup._E` of one number: ``(e^{ix} - 1) / (ix) = e^{ix/2} sin(x/2) / (x/2)``.

    One ``sin`` serves both factors (numpy's sinc takes the sine of ``pi (x / 2 pi)``, the same
    angle to the last bit).
    """
    h = 0.5 * x
    sh = math.sin(h)
    sc = sh / h if h != 0.0 else 1.0
    return complex(math.cos(h) * sc, sh * sc)


@_jit
def _rot(h):
    """``e^{i h}``."""
    return complex(math.cos(h), math.sin(h))


@_jit
def _heading(diff, theta):
    """``e^{i theta}`` of a wheeled robot (one ``cos`` and ``sin`` for each use of the heading), 0 for a point mass."""
    return _rot(theta) if diff else 0j


@_jit
def _point1(diff, offset, x, y, heading):
    """:func:`~aasoatt_env.safety.backup._point` of one robot (``heading``: :func:`_heading` of its angle)."""
    c = complex(x, y)
    return c + offset * heading if diff else c


@_jit
def _velocity1(diff, c0, c1, tg, heading, u0, u1):
    """:func:`~aasoatt_env.safety.backup._velocity` of one robot: control-point velocity and yaw rate."""
    if not diff:
        return complex(u0, u1), 0.0
    return heading * (c0 * u0 + c1 * u1), tg * (u0 - u1)


@_jit
def _brake_time1(diff, c0, c1, amax, adec, u0, u1):
    """:func:`~aasoatt_env.safety.backup.brake_time` of one robot."""
    s = _nmax(abs(u0), abs(u1))
    speed = _cabs(c0 * u0 + c1 * u1) if diff else math.hypot(u0, u1)
    return _nmax(s / amax, speed / adec)


@_jit
def _brake1(diff, c0, c1, tg, amax, adec, heading, u0, u1, dt):
    """:func:`~aasoatt_env.safety.backup._brake` of one robot: ``(pdot, omega, rate, steps, reach, bulge)``."""
    T = _brake_time1(diff, c0, c1, amax, adec, u0, u1)
    pdot, w = _velocity1(diff, c0, c1, tg, heading, u0, u1)
    if not T > 0.0:  # at rest (or T NaN): numpy's arithmetic with moving = False, NaN kept as NaN
        speed = _cabs(pdot) * 0.0
        aw = abs(w)
        reach = speed * 0.0 * _sinc1(aw * 0.0 / _TWO_PI) + (dt * dt / 8.0) * speed * aw
        bulge = 0.0
        if not diff:
            bulge = (dt / 8.0) * speed * 1.0
            reach = reach + bulge
        return pdot * 0.0, w, 1.0, 0, reach, bulge
    ratio = T / dt
    r1 = max(ratio, 1.0)
    rate = 1.0 / r1
    steps = int(min(max(np.ceil(ratio - 1e-12), 1.0), MAX_BRAKE_STEPS))
    speed = _cabs(pdot)
    K = float(steps)
    tau_end = dt * (0.5 + (K - 1.0) * (1.0 - K / (2.0 * r1)))
    aw = abs(w)
    tau_env = _PI / aw if aw * tau_end > _PI else tau_end
    envelope = speed * tau_env * _sinc1(aw * tau_env / _TWO_PI)
    reach = envelope + (dt * dt / 8.0) * speed * aw
    bulge = 0.0
    if not diff:
        bulge = (dt / 8.0) * speed * rate
        reach = reach + bulge
    if ratio > MAX_BRAKE_STEPS:  # too long to sample: unbounded
        reach = np.inf
    return pdot, w, rate, steps, reach, bulge


@_jit
def _candidate1(diff, c0, c1, tg, amax, adec, p0, theta, heading, u0, u1, du0, du1, dt):
    """One step holding ``du`` then braking (:func:`~aasoatt_env.safety.backup._first_step` and ``_brake``).

    ``heading``: :func:`_heading` of ``theta``.

    Returns ``(p1, dev, pdot, omega, rate, steps, reach, bulge)`` with ``reach`` the
    candidate's (:func:`~aasoatt_env.safety.backup._candidate_reach`).
    """
    c8 = dt * dt / 8.0
    u10 = u0 + du0 * dt
    u11 = u1 + du1 * dt
    pm, wm = _velocity1(diff, c0, c1, tg, heading, 0.5 * (u0 + u10), 0.5 * (u1 + u11))
    p1 = p0 + pm * dt * _E1(wm * dt)
    dev = c8 * _cabs(pm) * abs(wm)
    if not diff:
        dev = dev + c8 * math.hypot(du0, du1)
    pdot, w, rate, steps, reach, bulge = _brake1(diff, c0, c1, tg, amax, adec, _heading(diff, theta + wm * dt), u10,
                                                 u11, dt)
    return p1, dev, pdot, w, rate, steps, _cabs(p1 - p0) + dev + reach, bulge


_RESYNC = 16
"""Samples between the exact rotations of :func:`_fill_brake`'s recurrence."""


@_jit
def _fill_brake(row_p, row_d, start, p_start, pdot, omega, rate, bulge, has_bulge, dt, length, fast):
    """Braking samples ``row_p[start:length]`` from ``p_start`` and deviations ``row_d[start:length-1]``.

    The operations of :func:`~aasoatt_env.safety.backup._brake_samples` in the same order.
    ``fast``: the rotation ``e^{i omega tau / 2}`` of :func:`_E1` by recurrence instead of a
    sine and cosine per sample.  While the robot decelerates, the step's time ``dtau`` falls
    by ``dt * rate`` per step, so each step's rotation is the previous one's times one fixed
    factor; both are taken exactly every :data:`_RESYNC` samples and where the speed reaches
    0, and the ``sin(h) / h`` factor comes from the rotation (``|h| >= 0.1``) or its series.
    The samples then differ from the exact ones by ~``1e-13`` of the path's length (the
    rounding of ~30 products), far below the check's tolerance
    (:data:`~aasoatt_env.safety.repair.GATE_TOL`, 5e-10 m).
    """
    c8 = dt * dt / 8.0
    half_dt = 0.5 * dt
    apd = _cabs(pdot)
    aw = abs(omega)
    tau = 0.0
    sig_prev = 1.0
    row_p[start] = p_start + (pdot * tau) * _E1(omega * tau)
    qw = 0.25 * omega * dt
    z = w = c = 1.0 + 0.0j  # e^{i omega tau / 2}; a step's rotation; the factor from one step's to the next
    if fast:
        w = _rot(qw * (2.0 - rate))  # the rotation of step 1: dtau = dt (1 - rate / 2)
        c = _rot(-2.0 * qw * rate)
    for k in range(1, length - start):
        raw = 1.0 - k * rate
        sig = 0.0 if raw < 0.0 else (1.0 if raw > 1.0 else raw)
        tau = tau + half_dt * (sig_prev + sig)
        s = 0.5 * (sig_prev + sig)
        d = c8 * apd * (s * s) * aw
        if has_bulge and sig_prev > 0.0:
            d = d + bulge
        row_d[start + k - 1] = d
        if not fast:
            row_p[start + k] = p_start + (pdot * tau) * _E1(omega * tau)
        else:
            h = 0.5 * (omega * tau)
            if k % _RESYNC == 0:
                z = _rot(h)
                w = _rot(qw * (2.0 - (2 * k + 1) * rate))  # step k + 1's
            elif raw > 0.0:  # both ends of the step still decelerating: the recurrence
                z = z * w
                w = w * c
            elif sig_prev > 0.0:  # the step that ends at rest
                z = _rot(h)
            if abs(h) < 0.1:
                h2 = h * h
                sc = 1.0 - h2 / 6.0 * (1.0 - h2 / 20.0 * (1.0 - h2 / 42.0))
            else:
                sc = z.imag / h
            row_p[start + k] = p_start + (pdot * tau) * (z * sc)
        sig_prev = sig


@_jit
def _fill_row(cur, curd, r, g, k, last, p0, p1, d1, pdot, omega, rate, bulge, has_bulge, dt, need, fast):
    """Row ``r`` of ``cur``/``curd``: robot ``g``'s path on level ``k`` (``need`` samples; ``last``: braking now).

    ``fast``: :func:`_fill_brake`'s recurrence.
    """
    if k == last:
        _fill_brake(cur[r], curd[r], 0, p0[g], pdot[k, g], omega[k, g], rate[k, g], bulge[k, g], has_bulge,
                    dt, need, fast)
    else:
        cur[r, 0] = p0[g]
        curd[r, 0] = d1[k, g]
        _fill_brake(cur[r], curd[r], 1, p1[k, g], pdot[k, g], omega[k, g], rate[k, g], bulge[k, g], has_bulge,
                    dt, need, fast)


@_jit
def _sample_at(p0, p1, d1, pdot, omega, rate, steps, bulge, has_bulge, dt, s):
    """Sample ``s`` of a candidate path and the deviation of step ``s -> s + 1``, in closed form.

    :func:`~aasoatt_env.safety.backup.candidate_samples_at` for one sample.
    """
    if s == 0:
        return p0, d1
    r = rate
    kf = math.floor(1.0 / r)
    k = float(max(s - 1, 0))
    kc = min(k, kf)
    extra = 0.0
    if k > kf:
        extra = 1.0 - kf * r
        extra = 0.5 * (0.0 if extra < 0.0 else (1.0 if extra > 1.0 else extra))
    tau = dt * (kc - 0.5 * r * kc * kc + extra)
    p = p1 + (pdot * tau) * _E1(omega * tau)
    a = 1.0 - k * r
    a = 0.0 if a < 0.0 else (1.0 if a > 1.0 else a)
    b = 1.0 - (k + 1.0) * r
    b = 0.0 if b < 0.0 else (1.0 if b > 1.0 else b)
    sig = 0.5 * (a + b)
    d = (dt * dt / 8.0) * _cabs(pdot) * (sig * sig) * abs(omega)
    if has_bulge:
        d = d + (bulge if a > 0.0 and k < steps else 0.0)
    return p, d


# --------------------------------------------------------------------------- pairs
@_jit
def _segment_margin(qa0, qa1, qc0, qc1, da, dc):
    """Smallest ``|q| - da - dc`` on the segment of relative positions ``qa - qc`` (``pair_margins``' step)."""
    q0 = qa0 - qc0
    q1 = qa1 - qc1
    dr = q1.real - q0.real
    dm = q1.imag - q0.imag
    dd = dr * dr + dm * dm
    if not dd > 0.0:
        dd = 1.0
    t = -(q0.real * dr + q0.imag * dm) / dd
    t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
    x = q0.real + t * dr
    y = q0.imag + t * dm
    return math.sqrt(x * x + y * y) - da - dc


@_jit
def _step_margin(cur, curd, na, nc, a, c, static, oc, k):
    """Step ``k``'s :func:`_segment_margin` of rows ``a``, ``c`` (or ``a`` and the point ``oc``).

    A row rests beyond its ``n`` samples (its last sample, deviation 0), as the padded numpy rows do.
    """
    ka0, ka1 = min(k, na - 1), min(k + 1, na - 1)
    da = curd[a, k] if k < na - 1 else 0.0
    if static:
        return _segment_margin(cur[a, ka0], cur[a, ka1], oc, oc, da, 0.0)
    kc0, kc1 = min(k, nc - 1), min(k + 1, nc - 1)
    dc = curd[c, k] if k < nc - 1 else 0.0
    return _segment_margin(cur[a, ka0], cur[a, ka1], cur[c, kc0], cur[c, kc1], da, dc)


@_jit
def _pair_min(cur, curd, na, nc, a, c, static, oc, nseg):
    """Smallest margin (before ``- d_s``) over ``nseg`` steps and its step (``pair_margins``); NaN wins."""
    best = np.inf
    kbest = 0
    for k in range(nseg):
        dist = _step_margin(cur, curd, na, nc, a, c, static, oc, k)
        if dist != dist:
            return dist, k
        if dist < best:
            best, kbest = dist, k
    return best, kbest


@_jit
def _pair_closest(cur, curd, na, nc, a, c, static, oc, nseg, tie):
    """The closest step as ``pair_margins(..., closest=True)`` takes it: the first within ``tie`` of the least."""
    best, kbest = _pair_min(cur, curd, na, nc, a, c, static, oc, nseg)
    if best != best:
        return best, kbest
    for k in range(kbest):
        dist = _step_margin(cur, curd, na, nc, a, c, static, oc, k)
        if dist <= best + tie:
            return dist, k
    return best, kbest


@_jit
def _pair_margin(cur, curd, na, nc, a, c, ds, static, oc):
    """:func:`_pair_min` over the pair's own horizon, minus ``ds`` (the gatekeeper's check of one pair)."""
    L = na if static else max(na, nc)
    return _pair_min(cur, curd, na, nc, a, c, static, oc, max(L, 2) - 1)[0] - ds


@_jit
def _near_pairs(cand, p0, R, radius, group, has_group, sensing_range, slack):
    """:func:`~aasoatt_env.safety.gatekeeper._pairs_near` from candidate pairs ``cand`` ``(P, 2)``."""
    keep = np.zeros(cand.shape[0], dtype=np.bool_)
    P = 0
    for q in range(cand.shape[0]):
        a, c = cand[q, 0], cand[q, 1]
        if has_group and group[a] != group[c]:
            continue
        dist = _cabs(p0[a] - p0[c])
        if dist > sensing_range:
            continue
        if dist < radius[a] + radius[c] + R[a] + R[c] + slack:
            keep[q] = True
            P += 1
    i = np.empty(P, dtype=np.int64)
    j = np.empty(P, dtype=np.int64)
    ds = np.empty(P)
    P = 0
    for q in range(cand.shape[0]):
        if keep[q]:
            i[P], j[P] = cand[q, 0], cand[q, 1]
            ds[P] = radius[cand[q, 0]] + radius[cand[q, 1]]
            P += 1
    return i, j, ds


@_jit
def _near_obstacles(p0, R, radius, group, has_group, oc, orad, ogroup, has_ogroup, slack):
    """:func:`~aasoatt_env.safety.gatekeeper._obstacles_near`: robot-obstacle pairs ``(i, k, d_s)``."""
    n, m = p0.shape[0], oc.shape[0]
    keep = np.zeros((n, m), dtype=np.bool_)
    Q = 0
    for g in range(n):
        for o in range(m):
            if has_group and has_ogroup and group[g] != ogroup[o]:
                continue
            if _cabs(p0[g] - oc[o]) < radius[g] + orad[o] + R[g] + slack:
                keep[g, o] = True
                Q += 1
    oi = np.empty(Q, dtype=np.int64)
    ok = np.empty(Q, dtype=np.int64)
    ods = np.empty(Q)
    Q = 0
    for g in range(n):
        for o in range(m):
            if keep[g, o]:
                oi[Q], ok[Q], ods[Q] = g, o, radius[g] + orad[o]
                Q += 1
    return oi, ok, ods


@_jit
def _rows_of(n, i, j, oi):
    """Buffer rows for the robots in pairs: ``loc`` ``(n,)`` (-1: none), the robots of the rows, their count."""
    loc = np.full(n, -1, dtype=np.int64)
    M = 0
    for q in range(i.shape[0]):
        for g in (i[q], j[q]):
            if loc[g] < 0:
                loc[g] = M
                M += 1
    for q in range(oi.shape[0]):
        if loc[oi[q]] < 0:
            loc[oi[q]] = M
            M += 1
    rob = np.empty(M, dtype=np.int64)
    for g in range(n):
        if loc[g] >= 0:
            rob[loc[g]] = g
    return loc, rob, M


# --------------------------------------------------------------------------- gatekeeper
@_jit
def _gate_rounds(lev, broken, reach, limit, need, p0, p1, d1, pdot, omega, rate, bulge, has_bulge, dt,
                i, j, ds, oi, ok, ods, oc, tol, hold):
    """The gatekeeper's rounds (:func:`~aasoatt_env.safety.gatekeeper.gatekeeper`, after its set-up).

    Parameters
    ----------
    lev, broken : numpy.ndarray
        ``(n,)`` int64 starting levels (range condition applied) and bool broken flags; updated in place.
    reach : numpy.ndarray
        ``(levels, n)`` path reaches (NaN already made inf); ``limit`` ``(n,)`` the range limits.
    need : numpy.ndarray
        ``(levels, n)`` int64 samples each robot's path needs on each level.
    p0 : numpy.ndarray
        ``(n,)`` complex control points; ``p1``, ``d1`` ``(levels, n)`` the first step's end and
        deviation per blend level (row ``last`` unused).
    pdot, omega, rate, bulge : numpy.ndarray
        ``(levels, n)`` braking parameters per level (``_Brake``; ``bulge`` zeros for wheeled robots).
    i, j, ds : numpy.ndarray
        Robot pairs to check and their safety distances; ``oi, ok, ods`` robot-obstacle pairs with
        obstacle centres ``oc`` (complex).
    tol : float
        Accepted violation [m]; ``hold``: the ``hold_violations`` floors.

    Returns
    -------
    tuple
        ``(marg, omarg, rounds)``: the pairs' margins on the final levels (NaN reported as -inf).
    """
    n = lev.shape[0]
    last = reach.shape[0] - 1
    P, Q = i.shape[0], oi.shape[0]
    loc, rob, M = _rows_of(n, i, j, oi)
    L = 2
    for r in range(M):
        for k in range(last + 1):
            L = max(L, need[k, rob[r]])
    cur = np.empty((M, L), dtype=np.complex128)
    curd = np.empty((M, L - 1))
    tol_p = np.full(P, tol)
    tol_o = np.full(Q, tol)
    if hold:  # each pair's own floor: its margin when both members brake now
        for r in range(M):
            g = rob[r]
            _fill_row(cur, curd, r, g, last, last, p0, p1, d1, pdot, omega, rate, bulge, has_bulge, dt,
                      need[last, g], True)
        for q in range(P):
            m = _pair_margin(cur, curd, need[last, i[q]], need[last, j[q]], loc[i[q]], loc[j[q]], ds[q], False, 0j)
            fl = -m if -m > 0.0 else 0.0  # NaN: no floor (numpy's fmax); the larger of floor and tol (gatekeeper)
            tol_p[q] = max(tol_p[q], fl * (1.0 + 1e-9))
        for q in range(Q):
            m = _pair_margin(cur, curd, need[last, oi[q]], 0, loc[oi[q]], 0, ods[q], True, oc[ok[q]])
            fl = -m if -m > 0.0 else 0.0
            tol_o[q] = max(tol_o[q], fl * (1.0 + 1e-9))
    marg = np.full(P, np.inf)
    omarg = np.full(Q, np.inf)
    todo = np.ones(P, dtype=np.bool_)
    otodo = np.ones(Q, dtype=np.bool_)
    filled = np.full(M, -1, dtype=np.int64)
    demote = np.zeros(n, dtype=np.bool_)
    rounds = 0
    while True:
        rounds += 1
        for r in range(M):  # the paths of the robots' current levels: only changed rows are made again
            g = rob[r]
            if lev[g] != filled[r]:
                _fill_row(cur, curd, r, g, lev[g], last, p0, p1, d1, pdot, omega, rate, bulge, has_bulge, dt,
                          need[lev[g], g], True)
                filled[r] = lev[g]
        demote[:] = False
        any_demote = False
        for q in range(P):
            if not todo[q]:
                continue
            a, c = i[q], j[q]
            m = _pair_margin(cur, curd, need[lev[a], a], need[lev[c], c], loc[a], loc[c], ds[q], False, 0j)
            if m != m:  # a margin that is not a number verifies nothing: it fails
                m = -np.inf
            marg[q] = m
            if m < -tol_p[q]:
                if lev[a] == last and lev[c] == last:  # not brake-safe before: nothing to demote
                    broken[a] = True
                    broken[c] = True
                if lev[a] != last:
                    demote[a] = True
                    any_demote = True
                if lev[c] != last:
                    demote[c] = True
                    any_demote = True
        for q in range(Q):
            if not otodo[q]:
                continue
            a = oi[q]
            m = _pair_margin(cur, curd, need[lev[a], a], 0, loc[a], 0, ods[q], True, oc[ok[q]])
            if m != m:
                m = -np.inf
            omarg[q] = m
            if m < -tol_o[q]:
                if lev[a] == last:
                    broken[a] = True
                else:
                    demote[a] = True
                    any_demote = True
        if not any_demote:
            break
        for g in range(n):  # one level down, then past any level whose path leaves the range limit
            if demote[g]:
                lev[g] += 1
                while lev[g] < last and reach[lev[g], g] > limit[g]:
                    lev[g] += 1
        for q in range(P):
            todo[q] = demote[i[q]] or demote[j[q]]
        for q in range(Q):
            otodo[q] = demote[oi[q]]
    return marg, omarg, rounds


@_jit
def gate_full(pose, u, du_c, dt, levels_in, quick, diff, offset, cols, tg, amax, adec, radius, group, has_group,
              sensing_range, cand, oc, orad, ogroup, has_ogroup, limit, tol, hold):
    """The whole :func:`~aasoatt_env.safety.gatekeeper.gatekeeper` for one call (its set-up, pairs and rounds).

    Parameters
    ----------
    pose, u, du_c : numpy.ndarray
        Axle poses ``(n, 3)``, wheel speeds and candidate inputs ``(n, 2)``.
    dt : float
        Physics step [s].
    levels_in : numpy.ndarray
        The shares tried, 1 first, the blend levels descending, 0 (the backup) last.
    quick : bool
        The gatekeeper's ``quick`` (blend levels only where a candidate leaves the range limit).
    diff, ..., has_ogroup
        The block of :func:`~aasoatt_env.safety.gatekeeper._kernel_args` (module docstring);
        ``cand`` holds every pair of one group within ``sensing_range`` (a superset is fine).
    limit : numpy.ndarray
        :func:`~aasoatt_env.safety.backup.reach_limit` ``(n,)``.
    tol, hold : float, bool
        The gatekeeper's ``tol`` and ``hold_violations``.

    Returns
    -------
    tuple
        ``(du, braking, broken, share, robot_margin, out_of_range, rounds, n_pairs, margin)``:
        the fields of :class:`~aasoatt_env.safety.gatekeeper.GateResult`.
    """
    n = pose.shape[0]
    nl_full = levels_in.shape[0]
    last_full = nl_full - 1
    p0 = np.empty(n, dtype=np.complex128)
    du_all = np.empty((nl_full, n, 2))
    P1 = np.empty((nl_full, n), dtype=np.complex128)
    D1 = np.zeros((nl_full, n))
    PD = np.empty((nl_full, n), dtype=np.complex128)
    OM = np.empty((nl_full, n))
    RT = np.empty((nl_full, n))
    NEED = np.empty((nl_full, n), dtype=np.int64)
    RE = np.empty((nl_full, n))
    BU = np.zeros((nl_full, n))
    HD = np.empty(n, dtype=np.complex128)
    for g in range(n):  # the backup from now: level `last`
        c0, c1 = cols[g, 0], cols[g, 1]
        HD[g] = _heading(diff, pose[g, 2])
        p0[g] = _point1(diff, offset[g], pose[g, 0], pose[g, 1], HD[g])
        T = _brake_time1(diff, c0, c1, amax[g], adec[g], u[g, 0], u[g, 1])
        pdot, w, rate, steps, reach, bulge = _brake1(diff, c0, c1, tg[g], amax[g], adec[g], HD[g], u[g, 0], u[g, 1],
                                                     dt)
        PD[last_full, g], OM[last_full, g], RT[last_full, g] = pdot, w, rate
        NEED[last_full, g], RE[last_full, g], BU[last_full, g] = steps + 1, reach, bulge
        den = _nmax(T, dt)
        du_all[last_full, g, 0] = -u[g, 0] / den
        du_all[last_full, g, 1] = -u[g, 1] / den
    nl = nl_full
    for k in range(nl_full - 1):  # one step blending the candidate and the backup, then the backup
        a = levels_in[k]
        out = False
        for g in range(n):
            b0, b1 = du_all[last_full, g, 0], du_all[last_full, g, 1]
            da0 = b0 + a * (du_c[g, 0] - b0)
            da1 = b1 + a * (du_c[g, 1] - b1)
            du_all[k, g, 0], du_all[k, g, 1] = da0, da1
            p1, dev, pdot, w, rate, steps, reach, bulge = _candidate1(
                diff, cols[g, 0], cols[g, 1], tg[g], amax[g], adec[g], p0[g], pose[g, 2], HD[g], u[g, 0], u[g, 1],
                da0, da1, dt)
            P1[k, g], D1[k, g], PD[k, g], OM[k, g], RT[k, g] = p1, dev, pdot, w, rate
            NEED[k, g], RE[k, g], BU[k, g] = steps + 2, reach, bulge
            out = out or reach > limit[g]
        if k == 0 and quick and not out:
            nl = 2  # no candidate leaves the range: the blends would change nothing below
            break
    if nl != nl_full:  # levels (1, 0): rows 0 and last
        keep = np.array([0, last_full])
        du_all, P1, D1, PD, OM, RT, NEED, RE, BU = (du_all[keep], P1[keep], D1[keep], PD[keep], OM[keep],
                                                     RT[keep], NEED[keep], RE[keep], BU[keep])
    last = nl - 1
    R = np.empty(n)
    lev = np.zeros(n, dtype=np.int64)
    broken = np.zeros(n, dtype=np.bool_)
    out_of_range = np.zeros(n, dtype=np.bool_)
    for g in range(n):
        for k in range(nl):
            if RE[k, g] != RE[k, g]:  # a reach that is not a number bounds nothing: unbounded
                RE[k, g] = np.inf
            R[g] = RE[k, g] if k == 0 else max(R[g], RE[k, g])
        while lev[g] < last and RE[lev[g], g] > limit[g]:  # a level whose path leaves the range is skipped
            lev[g] += 1
        broken[g] = RE[last, g] > limit[g]
        out_of_range[g] = RE[0, g] > limit[g]
    pi, pj, pds = _near_pairs(cand, p0, R, radius, group, has_group, sensing_range, 1e-12)
    oi, ok, ods = _near_obstacles(p0, R, radius, group, has_group, oc, orad, ogroup, has_ogroup, 1e-12)
    margin = 0.5 * sensing_range
    for g in range(n):
        margin = min(margin, limit[g])
    robot_margin = limit.copy()
    rounds = 0
    P, Q = pi.shape[0], oi.shape[0]
    if P + Q > 0:
        marg, omarg, rounds = _gate_rounds(lev, broken, RE, limit, NEED, p0, P1, D1, PD, OM, RT, BU, not diff, dt,
                                          pi, pj, pds, oi, ok, ods, oc, tol, hold)
        for q in range(P):
            robot_margin[pi[q]] = min(robot_margin[pi[q]], marg[q])
            robot_margin[pj[q]] = min(robot_margin[pj[q]], marg[q])
        for q in range(Q):
            robot_margin[oi[q]] = min(robot_margin[oi[q]], omarg[q])
        for g in range(n):
            margin = min(margin, robot_margin[g])
    du = np.empty((n, 2))
    share = np.empty(n)
    for g in range(n):
        du[g, 0] = du_all[lev[g], g, 0]
        du[g, 1] = du_all[lev[g], g, 1]
        share[g] = levels_in[lev[g] if lev[g] < last else last_full]
    return du, lev > 0, broken, share, robot_margin, out_of_range, rounds, P + Q, margin


@_jit
def _moved_step(diff, cols, tg, amax, adec, p0, hd, pose, u, du, g, d, eps, dt, k):
    """Samples ``k``, ``k + 1`` and step ``k``'s deviation of robot ``g``'s path with input ``d`` moved by ``eps``.

    :func:`~aasoatt_env.safety.backup.candidate_samples_at` for the repair's finite difference.
    """
    e0 = du[g, 0] + (eps if d == 0 else 0.0)
    e1 = du[g, 1] + (eps if d == 1 else 0.0)
    p1, dev, pdot, w, rate, steps, _, bulge = _candidate1(
        diff, cols[g, 0], cols[g, 1], tg[g], amax[g], adec[g], p0[g], pose[g, 2], hd[g], u[g, 0], u[g, 1], e0, e1,
        dt)
    pa0, dm0 = _sample_at(p0[g], p1, dev, pdot, w, rate, steps, bulge, not diff, dt, k)
    pa1, _ = _sample_at(p0[g], p1, dev, pdot, w, rate, steps, bulge, not diff, dt, k + 1)
    return pa0, pa1, dm0


# --------------------------------------------------------------------------- repair
@_jit
def repair_full(pose, u, du_c, lo, hi, dt, diff, offset, cols, tg, amax, adec, radius, group, has_group,
                sensing_range, cand, oc, orad, ogroup, has_ogroup, target, rounds, eps, tie):
    """:func:`~aasoatt_env.safety.repair.repair` for one call: the nudged candidate ``(n, 2)``.

    The same rounds in the same order: the low pairs' finite-difference gradients at their
    closest steps (``tie``: :data:`~aasoatt_env.safety.gatekeeper.CLOSEST_TIE`), their least-norm
    lifts summed robot by robot as ``numpy.add.at`` does, the clip to ``[lo, hi]``.

    Parameters
    ----------
    pose, u, du_c, lo, hi : numpy.ndarray
        Axle poses ``(n, 3)``; wheel speeds, candidate inputs and their bounds ``(n, 2)``.
    dt : float
        Physics step [s].
    diff, ..., has_ogroup
        The block of :func:`~aasoatt_env.safety.gatekeeper._kernel_args` (module docstring).
    target, rounds, eps, tie
        The repair's ``target``, ``rounds`` and ``eps``, and the closest-step tie.
    """
    n = pose.shape[0]
    du = np.empty((n, 2))
    for g in range(n):
        for d in range(2):
            du[g, d] = min(max(du_c[g, d], lo[g, d]), hi[g, d])
    p0 = np.empty(n, dtype=np.complex128)
    hd = np.empty(n, dtype=np.complex128)
    for g in range(n):
        hd[g] = _heading(diff, pose[g, 2])
        p0[g] = _point1(diff, offset[g], pose[g, 0], pose[g, 1], hd[g])
    P1 = np.empty((1, n), dtype=np.complex128)
    D1 = np.empty((1, n))
    PD = np.empty((1, n), dtype=np.complex128)
    OM = np.empty((1, n))
    RT = np.empty((1, n))
    BU = np.empty((1, n))
    NEED = np.empty(n, dtype=np.int64)
    R = np.empty(n)
    slack = 2.0 * target
    ee = eps * dt * dt
    # each robot's candidate path (row g), made once and kept until its input changes (numpy's _PathCache)
    Lc = 2
    rowp = np.empty((n, Lc), dtype=np.complex128)
    rowd = np.empty((n, Lc - 1))
    made = np.zeros(n, dtype=np.bool_)
    used = np.zeros(n, dtype=np.bool_)
    for _ in range(rounds):
        for g in range(n):  # reach first: only robots with a pair that could come close need paths
            p1, dev, pdot, w, rate, steps, reach, bulge = _candidate1(
                diff, cols[g, 0], cols[g, 1], tg[g], amax[g], adec[g], p0[g], pose[g, 2], hd[g], u[g, 0], u[g, 1],
                du[g, 0], du[g, 1], dt)
            P1[0, g], D1[0, g], PD[0, g], OM[0, g], RT[0, g], BU[0, g] = p1, dev, pdot, w, rate, bulge
            NEED[g], R[g] = steps + 2, reach + ee
        i, j, ds = _near_pairs(cand, p0, R, radius, group, has_group, sensing_range, slack)
        oi, ok, ods = _near_obstacles(p0, R, radius, group, has_group, oc, orad, ogroup, has_ogroup, slack)
        P, Q = i.shape[0], oi.shape[0]
        if P + Q == 0:
            break
        used[:] = False
        for q in range(P):
            used[i[q]] = True
            used[j[q]] = True
        for q in range(Q):
            used[oi[q]] = True
        L = 2
        for g in range(n):
            if used[g]:
                L = max(L, NEED[g])
        if L > Lc:
            Lc = L
            rowp = np.empty((n, Lc), dtype=np.complex128)
            rowd = np.empty((n, Lc - 1))
            made[:] = False
        for g in range(n):
            if used[g] and not made[g]:
                _fill_row(rowp, rowd, g, g, 0, 1, p0, P1, D1, PD, OM, RT, BU, not diff, dt, NEED[g], False)
                made[g] = True
        cur, curd = rowp, rowd
        # the low pairs: margin below target; their margin and closest step over the whole rows
        low = np.zeros(P, dtype=np.bool_)
        m0 = np.empty(P)
        kk = np.empty(P, dtype=np.int64)
        nlow = 0
        for q in range(P):
            a, c = i[q], j[q]
            if _pair_margin(cur, curd, NEED[a], NEED[c], a, c, ds[q], False, 0j) < target:
                low[q] = True
                nlow += 1
                best, k = _pair_closest(cur, curd, NEED[a], NEED[c], a, c, False, 0j, L - 1, tie)
                m0[q], kk[q] = best - ds[q], k
        olow = np.zeros(Q, dtype=np.bool_)
        om0 = np.empty(Q)
        okk = np.empty(Q, dtype=np.int64)
        for q in range(Q):
            a = oi[q]
            if _pair_margin(cur, curd, NEED[a], 0, a, 0, ods[q], True, oc[ok[q]]) < target:
                olow[q] = True
                nlow += 1
                best, k = _pair_closest(cur, curd, NEED[a], 0, a, 0, True, oc[ok[q]], L - 1, tie)
                om0[q], okk[q] = best - ods[q], k
        if nlow == 0:
            break
        # gradients at the closest step: that step's samples of one member with one input moved by eps
        gi = np.zeros((P, 2))
        gj = np.zeros((P, 2))
        lift = np.zeros(P)
        for q in range(P):
            if not low[q]:
                continue
            k = kk[q]
            for side in range(2):
                mv, fx = (i[q], j[q]) if side == 0 else (j[q], i[q])
                qf0, qf1 = cur[fx, min(k, NEED[fx] - 1)], cur[fx, min(k + 1, NEED[fx] - 1)]
                dfx = curd[fx, k] if k < NEED[fx] - 1 else 0.0
                for d in range(2):
                    pa0, pa1, dm0 = _moved_step(diff, cols, tg, amax, adec, p0, hd, pose, u, du, mv, d, eps, dt, k)
                    mg = _segment_margin(pa0, pa1, qf0, qf1, dm0, dfx) - ds[q]
                    if side == 0:
                        gi[q, d] = (mg - m0[q]) / eps
                    else:
                        gj[q, d] = (mg - m0[q]) / eps
            nrm = (gi[q, 0] * gi[q, 0] + gi[q, 1] * gi[q, 1]) + (gj[q, 0] * gj[q, 0] + gj[q, 1] * gj[q, 1])
            lift[q] = (2.0 * target - m0[q]) / max(nrm, 1e-12)
        go = np.zeros((Q, 2))
        olift = np.zeros(Q)
        for q in range(Q):
            if not olow[q]:
                continue
            k, mv = okk[q], oi[q]
            for d in range(2):
                pa0, pa1, dm0 = _moved_step(diff, cols, tg, amax, adec, p0, hd, pose, u, du, mv, d, eps, dt, k)
                mg = _segment_margin(pa0, pa1, oc[ok[q]], oc[ok[q]], dm0, 0.0) - ods[q]
                go[q, d] = (mg - om0[q]) / eps
            olift[q] = (2.0 * target - om0[q]) / max(go[q, 0] * go[q, 0] + go[q, 1] * go[q, 1], 1e-12)
        # the lifts add up robot by robot, in numpy's order (every pair's first member, then second, then obstacles)
        step = np.zeros((n, 2))
        for q in range(P):
            if low[q]:
                step[i[q], 0] += lift[q] * gi[q, 0]
                step[i[q], 1] += lift[q] * gi[q, 1]
        for q in range(P):
            if low[q]:
                step[j[q], 0] += lift[q] * gj[q, 0]
                step[j[q], 1] += lift[q] * gj[q, 1]
        for q in range(Q):
            if olow[q]:
                step[oi[q], 0] += olift[q] * go[q, 0]
                step[oi[q], 1] += olift[q] * go[q, 1]
        moved = False
        for g in range(n):
            for d in range(2):
                if step[g, d] != 0.0:
                    moved = True
        if not moved:
            break
        for g in range(n):
            for d in range(2):
                v = min(max(du[g, d] + step[g, d], lo[g, d]), hi[g, d])
                if v != du[g, d]:
                    made[g] = False  # its path is made again when asked for
                du[g, d] = v
    return du
