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
function; :func:`E1` takes one sine for two, noted there), with two
exceptions: a pair's distance on a step is ``sqrt(x^2 + y^2)`` (numpy's
``abs`` takes ``hypot``: the last bit), and the gatekeeper's braking samples
rotate by a recurrence (:func:`fill_brake`: ~1e-13 of the path's length).
So the results differ from the reference by rounding alone; the repair's
rows keep the sines and cosines (its finite differences compare them with
:func:`sample_at`'s closed form).
"""

from __future__ import annotations

import math

import numpy as np

from aasoatt_env.numba_jit import jit as _jit
from aasoatt_env.numba_jit import nmax as _nmax
from aasoatt_env.safety.backup.paths import MAX_BRAKE_STEPS

__all__ = [
    "E1", "brake1", "brake_time1", "cabs", "candidate1", "fill_brake", "fill_row", "heading_of", "near_obstacles",
    "near_pairs", "pair_closest", "pair_margin", "pair_min", "point1", "rot", "rows_of", "sample_at",
    "segment_margin", "sinc1", "step_margin", "velocity1",
]


_EPS = float(np.finfo(np.float64).eps)
_TWO_PI = 2.0 * np.pi
_PI = float(np.pi)


# --------------------------------------------------------------------------- one robot, closed form
@_jit
def cabs(z):
    """``|z|`` by ``hypot``, as numpy's scalar code takes it."""
    return math.hypot(z.real, z.imag)


@_jit
def sinc1(x):
    """:func:`~aasoatt_env.safety.backup._sinc` of one number."""
    y = _PI * x
    if y == 0.0:
        y = _EPS
    return math.sin(y) / y


@_jit
def E1(x):
    """:func:`~aasoatt_env.safety.backup._E` of one number: ``(e^{ix} - 1) / (ix) = e^{ix/2} sin(x/2) / (x/2)``.

    One ``sin`` serves both factors (numpy's sinc takes the sine of ``pi (x / 2 pi)``, the same
    angle to the last bit).
    """
    h = 0.5 * x
    sh = math.sin(h)
    sc = sh / h if h != 0.0 else 1.0
    return complex(math.cos(h) * sc, sh * sc)


@_jit
def rot(h):
    """``e^{i h}``."""
    return complex(math.cos(h), math.sin(h))


@_jit
def heading_of(diff, theta):
    """``e^{i theta}`` of a wheeled robot (one ``cos`` and ``sin`` for each use of the heading), 0 for a point mass."""
    return rot(theta) if diff else 0j


@_jit
def point1(diff, offset, x, y, heading):
    """:func:`~aasoatt_env.safety.backup._point` of one robot (``heading``: :func:`heading_of` of its angle)."""
    c = complex(x, y)
    return c + offset * heading if diff else c


@_jit
def velocity1(diff, c0, c1, tg, heading, u0, u1):
    """:func:`~aasoatt_env.safety.backup._velocity` of one robot: control-point velocity and yaw rate."""
    if not diff:
        return complex(u0, u1), 0.0
    return heading * (c0 * u0 + c1 * u1), tg * (u0 - u1)


@_jit
def brake_time1(diff, c0, c1, amax, adec, u0, u1):
    """:func:`~aasoatt_env.safety.backup.brake_time` of one robot."""
    s = _nmax(abs(u0), abs(u1))
    speed = cabs(c0 * u0 + c1 * u1) if diff else math.hypot(u0, u1)
    return _nmax(s / amax, speed / adec)


@_jit
def brake1(diff, c0, c1, tg, amax, adec, heading, u0, u1, dt):
    """:func:`~aasoatt_env.safety.backup._brake` of one robot: ``(pdot, omega, rate, steps, reach, bulge)``."""
    T = brake_time1(diff, c0, c1, amax, adec, u0, u1)
    pdot, w = velocity1(diff, c0, c1, tg, heading, u0, u1)
    if not T > 0.0:  # at rest (or T NaN): numpy's arithmetic with moving = False, NaN kept as NaN
        speed = cabs(pdot) * 0.0
        aw = abs(w)
        reach = speed * 0.0 * sinc1(aw * 0.0 / _TWO_PI) + (dt * dt / 8.0) * speed * aw
        bulge = 0.0
        if not diff:
            bulge = (dt / 8.0) * speed * 1.0
            reach = reach + bulge
        return pdot * 0.0, w, 1.0, 0, reach, bulge
    ratio = T / dt
    r1 = max(ratio, 1.0)
    rate = 1.0 / r1
    steps = int(min(max(np.ceil(ratio - 1e-12), 1.0), MAX_BRAKE_STEPS))
    speed = cabs(pdot)
    K = float(steps)
    tau_end = dt * (0.5 + (K - 1.0) * (1.0 - K / (2.0 * r1)))
    aw = abs(w)
    tau_env = _PI / aw if aw * tau_end > _PI else tau_end
    envelope = speed * tau_env * sinc1(aw * tau_env / _TWO_PI)
    reach = envelope + (dt * dt / 8.0) * speed * aw
    bulge = 0.0
    if not diff:
        bulge = (dt / 8.0) * speed * rate
        reach = reach + bulge
    if ratio > MAX_BRAKE_STEPS:  # too long to sample: unbounded
        reach = np.inf
    return pdot, w, rate, steps, reach, bulge


@_jit
def candidate1(diff, c0, c1, tg, amax, adec, p0, theta, heading, u0, u1, du0, du1, dt):
    """One step holding ``du`` then braking (:func:`~aasoatt_env.safety.backup._first_step` and ``_brake``).

    ``heading``: :func:`heading_of` of ``theta``.

    Returns ``(p1, dev, pdot, omega, rate, steps, reach, bulge)`` with ``reach`` the
    candidate's (:func:`~aasoatt_env.safety.backup._candidate_reach`).
    """
    c8 = dt * dt / 8.0
    u10 = u0 + du0 * dt
    u11 = u1 + du1 * dt
    pm, wm = velocity1(diff, c0, c1, tg, heading, 0.5 * (u0 + u10), 0.5 * (u1 + u11))
    p1 = p0 + pm * dt * E1(wm * dt)
    dev = c8 * cabs(pm) * abs(wm)
    if not diff:
        dev = dev + c8 * math.hypot(du0, du1)
    pdot, w, rate, steps, reach, bulge = brake1(diff, c0, c1, tg, amax, adec, heading_of(diff, theta + wm * dt), u10,
                                                 u11, dt)
    return p1, dev, pdot, w, rate, steps, cabs(p1 - p0) + dev + reach, bulge


_RESYNC = 16
"""Samples between the exact rotations of :func:`fill_brake`'s recurrence."""


@_jit
def fill_brake(row_p, row_d, start, p_start, pdot, omega, rate, bulge, has_bulge, dt, length, fast):
    """Braking samples ``row_p[start:length]`` from ``p_start`` and deviations ``row_d[start:length-1]``.

    The operations of :func:`~aasoatt_env.safety.backup._brake_samples` in the same order.
    ``fast``: the rotation ``e^{i omega tau / 2}`` of :func:`E1` by recurrence instead of a
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
    apd = cabs(pdot)
    aw = abs(omega)
    tau = 0.0
    sig_prev = 1.0
    row_p[start] = p_start + (pdot * tau) * E1(omega * tau)
    qw = 0.25 * omega * dt
    z = w = c = 1.0 + 0.0j  # e^{i omega tau / 2}; a step's rotation; the factor from one step's to the next
    if fast:
        w = rot(qw * (2.0 - rate))  # the rotation of step 1: dtau = dt (1 - rate / 2)
        c = rot(-2.0 * qw * rate)
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
            row_p[start + k] = p_start + (pdot * tau) * E1(omega * tau)
        else:
            h = 0.5 * (omega * tau)
            if k % _RESYNC == 0:
                z = rot(h)
                w = rot(qw * (2.0 - (2 * k + 1) * rate))  # step k + 1's
            elif raw > 0.0:  # both ends of the step still decelerating: the recurrence
                z = z * w
                w = w * c
            elif sig_prev > 0.0:  # the step that ends at rest
                z = rot(h)
            if abs(h) < 0.1:
                h2 = h * h
                sc = 1.0 - h2 / 6.0 * (1.0 - h2 / 20.0 * (1.0 - h2 / 42.0))
            else:
                sc = z.imag / h
            row_p[start + k] = p_start + (pdot * tau) * (z * sc)
        sig_prev = sig


@_jit
def fill_row(cur, curd, r, g, k, last, p0, p1, d1, pdot, omega, rate, bulge, has_bulge, dt, need, fast):
    """Row ``r`` of ``cur``/``curd``: robot ``g``'s path on level ``k`` (``need`` samples; ``last``: braking now).

    ``fast``: :func:`fill_brake`'s recurrence.
    """
    if k == last:
        fill_brake(cur[r], curd[r], 0, p0[g], pdot[k, g], omega[k, g], rate[k, g], bulge[k, g], has_bulge,
                    dt, need, fast)
    else:
        cur[r, 0] = p0[g]
        curd[r, 0] = d1[k, g]
        fill_brake(cur[r], curd[r], 1, p1[k, g], pdot[k, g], omega[k, g], rate[k, g], bulge[k, g], has_bulge,
                    dt, need, fast)


@_jit
def sample_at(p0, p1, d1, pdot, omega, rate, steps, bulge, has_bulge, dt, s):
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
    p = p1 + (pdot * tau) * E1(omega * tau)
    a = 1.0 - k * r
    a = 0.0 if a < 0.0 else (1.0 if a > 1.0 else a)
    b = 1.0 - (k + 1.0) * r
    b = 0.0 if b < 0.0 else (1.0 if b > 1.0 else b)
    sig = 0.5 * (a + b)
    d = (dt * dt / 8.0) * cabs(pdot) * (sig * sig) * abs(omega)
    if has_bulge:
        d = d + (bulge if a > 0.0 and k < steps else 0.0)
    return p, d


# --------------------------------------------------------------------------- pairs
@_jit
def segment_margin(qa0, qa1, qc0, qc1, da, dc):
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
def step_margin(cur, curd, na, nc, a, c, static, oc, k):
    """Step ``k``'s :func:`segment_margin` of rows ``a``, ``c`` (or ``a`` and the point ``oc``).

    A row rests beyond its ``n`` samples (its last sample, deviation 0), as the padded numpy rows do.
    """
    ka0, ka1 = min(k, na - 1), min(k + 1, na - 1)
    da = curd[a, k] if k < na - 1 else 0.0
    if static:
        return segment_margin(cur[a, ka0], cur[a, ka1], oc, oc, da, 0.0)
    kc0, kc1 = min(k, nc - 1), min(k + 1, nc - 1)
    dc = curd[c, k] if k < nc - 1 else 0.0
    return segment_margin(cur[a, ka0], cur[a, ka1], cur[c, kc0], cur[c, kc1], da, dc)


@_jit
def pair_min(cur, curd, na, nc, a, c, static, oc, nseg):
    """Smallest margin (before ``- d_s``) over ``nseg`` steps and its step (``pair_margins``); NaN wins."""
    best = np.inf
    kbest = 0
    for k in range(nseg):
        dist = step_margin(cur, curd, na, nc, a, c, static, oc, k)
        if dist != dist:
            return dist, k
        if dist < best:
            best, kbest = dist, k
    return best, kbest


@_jit
def pair_closest(cur, curd, na, nc, a, c, static, oc, nseg, tie):
    """The closest step as ``pair_margins(..., closest=True)`` takes it: the first within ``tie`` of the least."""
    best, kbest = pair_min(cur, curd, na, nc, a, c, static, oc, nseg)
    if best != best:
        return best, kbest
    for k in range(kbest):
        dist = step_margin(cur, curd, na, nc, a, c, static, oc, k)
        if dist <= best + tie:
            return dist, k
    return best, kbest


@_jit
def pair_margin(cur, curd, na, nc, a, c, ds, static, oc):
    """:func:`pair_min` over the pair's own horizon, minus ``ds`` (the gatekeeper's check of one pair)."""
    L = na if static else max(na, nc)
    return pair_min(cur, curd, na, nc, a, c, static, oc, max(L, 2) - 1)[0] - ds


@_jit
def near_pairs(cand, p0, R, radius, group, has_group, sensing_range, slack):
    """:func:`~aasoatt_env.safety.gatekeeper._pairs_near` from candidate pairs ``cand`` ``(P, 2)``."""
    keep = np.zeros(cand.shape[0], dtype=np.bool_)
    P = 0
    for q in range(cand.shape[0]):
        a, c = cand[q, 0], cand[q, 1]
        if has_group and group[a] != group[c]:
            continue
        dist = cabs(p0[a] - p0[c])
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
def near_obstacles(p0, R, radius, group, has_group, oc, orad, ogroup, has_ogroup, slack):
    """:func:`~aasoatt_env.safety.gatekeeper._obstacles_near`: robot-obstacle pairs ``(i, k, d_s)``."""
    n, m = p0.shape[0], oc.shape[0]
    keep = np.zeros((n, m), dtype=np.bool_)
    Q = 0
    for g in range(n):
        for o in range(m):
            if has_group and has_ogroup and group[g] != ogroup[o]:
                continue
            if cabs(p0[g] - oc[o]) < radius[g] + orad[o] + R[g] + slack:
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
def rows_of(n, i, j, oi):
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


