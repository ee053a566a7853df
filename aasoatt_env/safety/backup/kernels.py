"""The backup layer's compiled check and repair (numba; imported only through :mod:`aasoatt_env.compiled`).

:func:`gate_full` is :func:`~.gate.gatekeeper`, :func:`repair_full` :func:`~.gate.repair`, on the caller-checked block
of :func:`~.gate.kernel_args`.  Each helper is its named numpy reference in :mod:`.paths` or :mod:`.gate` for one robot,
sample or pair, in its order of operations (but ``hypot`` and :func:`fill_brake`'s recurrence): equal to rounding.
"""

import math

import numpy as np

from aasoatt_env.numba_jit import jit, nclip, nmax
from aasoatt_env.safety.backup.paths import _EPS, MAX_BRAKE_STEPS

__all__ = ["fill_brake", "gate_full", "repair_full"]

OFFSET, TURN_GAIN, MAX_ACCEL, DECEL, RADIUS = 0, 1, 2, 3, 4  # columns of the robots' constants (gate.team_block)
D1, OMEGA, RATE, BULGE, REACH = 0, 1, 2, 3, 4  # columns of a level's floats F (its complex C: step end, velocity)
_PI = float(np.pi)
_RESYNC = 16  # samples between the exact rotations of fill_brake's recurrence


@jit
def cabs(z):
    """``|z|`` by ``hypot``, as numpy's scalar code takes it."""
    return math.hypot(z.real, z.imag)


@jit
def E1(x):
    """``paths._E`` of one number, one sine serving both factors (numpy's sinc takes the same angle)."""
    h = 0.5 * x
    sh = math.sin(h)
    sc = sh / h if h != 0.0 else 1.0
    return complex(math.cos(h) * sc, sh * sc)


@jit
def rot(h):
    """``e^{i h}``."""
    return complex(math.cos(h), math.sin(h))


@jit
def starts(diff, rob, pose):
    """Control points ``(n,)`` and headings ``e^{i theta}`` ``(n,)`` (0 for point masses) of axle poses."""
    n = pose.shape[0]
    p0, hd = np.empty(n, dtype=np.complex128), np.empty(n, dtype=np.complex128)
    for g in range(n):
        hd[g] = rot(pose[g, 2]) if diff else 0j
        c = complex(pose[g, 0], pose[g, 1])
        p0[g] = c + rob[g, OFFSET] * hd[g] if diff else c
    return p0, hd


@jit
def consts(rob, cols, g):
    """Robot ``g``'s constants of the closed forms, by value: input columns, turn gain, acceleration, deceleration."""
    return cols[g, 0], cols[g, 1], rob[g, TURN_GAIN], rob[g, MAX_ACCEL], rob[g, DECEL]


@jit
def velocity1(diff, rc, heading, u0, u1):
    """``paths._velocity`` of a robot (``rc``: its :func:`consts`): control-point velocity and yaw rate."""
    if not diff:
        return complex(u0, u1), 0.0
    return heading * (rc[0] * u0 + rc[1] * u1), rc[2] * (u0 - u1)


@jit
def brake_time1(diff, rc, u0, u1):
    """``paths.brake_time`` of a robot."""
    s = nmax(abs(u0), abs(u1))
    speed = cabs(rc[0] * u0 + rc[1] * u1) if diff else math.hypot(u0, u1)
    return nmax(s / rc[3], speed / rc[4])


@jit
def brake1(diff, rc, heading, u0, u1, dt):
    """``paths.brake`` of a robot: ``(pdot, omega, rate, steps, reach, bulge)`` (NaN kept as numpy keeps it)."""
    T = brake_time1(diff, rc, u0, u1)
    pdot, w = velocity1(diff, rc, heading, u0, u1)
    moving = T > 0.0
    ratio = T / dt if moving else 0.0
    r1 = max(ratio, 1.0)
    steps = int(min(max(np.ceil(ratio - 1e-12), 1.0), MAX_BRAKE_STEPS)) if moving else 0
    rate = 1.0 / r1 if moving else 1.0
    speed = cabs(pdot) if moving else cabs(pdot) * 0.0
    K = float(steps)
    tau_end = dt * (0.5 + (K - 1.0) * (1.0 - K / (2.0 * r1))) if moving else 0.0
    aw = abs(w)
    tau_env = _PI / aw if aw * tau_end > _PI else tau_end
    y = _PI * (aw * tau_env / (2.0 * np.pi))  # paths._sinc
    y = y if y != 0.0 else _EPS
    reach = speed * tau_env * (math.sin(y) / y) + (dt * dt / 8.0) * speed * aw
    bulge = 0.0
    if not diff:
        bulge = (dt / 8.0) * speed * rate
        reach = reach + bulge
    if ratio > MAX_BRAKE_STEPS:  # too long to sample: unbounded
        reach = np.inf
    return (pdot if moving else pdot * 0.0), w, rate, steps, reach, bulge


@jit
def candidate1(diff, rc, p0, theta, heading, u0, u1, du0, du1, dt):
    """``paths.candidate`` of a robot: ``(p1, dev, pdot, omega, rate, steps, reach, bulge)`` (the candidate's reach)."""
    c8 = dt * dt / 8.0
    u10 = u0 + du0 * dt
    u11 = u1 + du1 * dt
    pm, wm = velocity1(diff, rc, heading, 0.5 * (u0 + u10), 0.5 * (u1 + u11))
    p1 = p0 + pm * dt * E1(wm * dt)
    dev = c8 * cabs(pm) * abs(wm)
    if not diff:
        dev = dev + c8 * math.hypot(du0, du1)
    pdot, w, rate, steps, reach, bulge = brake1(diff, rc, rot(theta + wm * dt) if diff else 0j, u10, u11, dt)
    return p1, dev, pdot, w, rate, steps, cabs(p1 - p0) + dev + reach, bulge


@jit
def fill_brake(row_p, row_d, start, p_start, pdot, omega, rate, bulge, has_bulge, dt, length, fast):
    """``paths.brake_samples`` into ``row_p[start:length]`` from ``p_start``, deviations into ``row_d``.

    ``fast``: each decelerating step's rotation is the previous one's times a fixed factor (exact every
    :data:`_RESYNC` samples and at rest): within ~1e-13 of the path's length of the exact samples.
    """
    c8, half_dt, apd, aw = dt * dt / 8.0, 0.5 * dt, cabs(pdot), abs(omega)
    tau, sig_prev = 0.0, 1.0
    row_p[start] = p_start + (pdot * tau) * E1(omega * tau)
    qw = 0.25 * omega * dt
    z = w = c = 1.0 + 0.0j  # e^{i omega tau / 2}; a step's rotation; the factor from one step's to the next
    if fast:
        w = rot(qw * (2.0 - rate))  # step 1's: dtau = dt (1 - rate / 2)
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
            elif raw > 0.0:  # both ends of the step still decelerating
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


@jit
def fill_row(cur, curd, r, g, k, last, p0, C, F, has_bulge, dt, need, fast):
    """Row ``r`` of ``cur``/``curd``: robot ``g``'s path on level ``k`` (``need`` samples; ``last``: braking now)."""
    s = 0 if k == last else 1
    if s:
        cur[r, 0], curd[r, 0] = p0[g], F[k, g, D1]
    fill_brake(cur[r], curd[r], s, p0[g] if k == last else C[k, g, 0], C[k, g, 1], F[k, g, OMEGA], F[k, g, RATE],
               F[k, g, BULGE], has_bulge, dt, need, fast)


@jit
def sample_at(p0, p1, d1, pdot, omega, r, steps, bulge, has_bulge, dt, s):
    """Sample ``s`` of a candidate path and the deviation of step ``s -> s + 1`` (``paths.candidate_samples_at``)."""
    if s == 0:
        return p0, d1
    kf = math.floor(1.0 / r)
    k = float(max(s - 1, 0))
    kc = min(k, kf)
    tau = dt * (kc - 0.5 * r * kc * kc + (0.5 * nclip(1.0 - kf * r, 0.0, 1.0) if k > kf else 0.0))
    p = p1 + (pdot * tau) * E1(omega * tau)
    a, b = nclip(1.0 - k * r, 0.0, 1.0), nclip(1.0 - (k + 1.0) * r, 0.0, 1.0)
    sig = 0.5 * (a + b)
    d = (dt * dt / 8.0) * cabs(pdot) * (sig * sig) * abs(omega)
    if has_bulge:
        d = d + (bulge if a > 0.0 and k < steps else 0.0)
    return p, d


@jit
def segment_margin(qa0, qa1, qc0, qc1, da, dc):
    """Smallest ``|q| - da - dc`` on the segment of relative positions ``qa - qc`` (``gate.pair_margins``' step)."""
    q0 = qa0 - qc0
    q1 = qa1 - qc1
    dr = q1.real - q0.real
    dm = q1.imag - q0.imag
    dd = dr * dr + dm * dm
    dd = dd if dd > 0.0 else 1.0
    t = -(q0.real * dr + q0.imag * dm) / dd
    t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
    x = q0.real + t * dr
    y = q0.imag + t * dm
    return math.sqrt(x * x + y * y) - da - dc


@jit
def step_margin(cur, curd, na, nc, a, c, oc, k):
    """Step ``k``'s :func:`segment_margin` of rows ``a``, ``c`` (``c < 0``: point ``oc``), resting past their own."""
    ka0, ka1 = min(k, na - 1), min(k + 1, na - 1)
    da = curd[a, k] if k < na - 1 else 0.0
    if c < 0:
        return segment_margin(cur[a, ka0], cur[a, ka1], oc, oc, da, 0.0)
    kc0, kc1 = min(k, nc - 1), min(k + 1, nc - 1)
    dc = curd[c, k] if k < nc - 1 else 0.0
    return segment_margin(cur[a, ka0], cur[a, ka1], cur[c, kc0], cur[c, kc1], da, dc)


@jit
def pair_min(cur, curd, na, nc, a, c, oc, nseg, tie):
    """Least margin (before ``- d_s``) over ``nseg`` steps and its step (a NaN first; ``tie >= 0``: ``closest``'s)."""
    best, kbest = np.inf, 0
    for k in range(nseg):
        dist = step_margin(cur, curd, na, nc, a, c, oc, k)
        if dist != dist:
            return dist, k
        if dist < best:
            best, kbest = dist, k
    for k in range(kbest if tie >= 0.0 else 0):
        dist = step_margin(cur, curd, na, nc, a, c, oc, k)
        if dist <= best + tie:
            return dist, k
    return best, kbest


@jit
def pair_margin(cur, curd, na, nc, a, c, ds, oc):
    """:func:`pair_min` over the pair's own horizon, minus ``ds``."""
    L = na if c < 0 else max(na, nc)
    return pair_min(cur, curd, na, nc, a, c, oc, max(L, 2) - 1, -1.0)[0] - ds


@jit
def near(cand, p0, R, rob, group, has_group, sensing_range, oc, orad, ogroup, has_ogroup, slack):
    """``gate.pairs_near`` of ``cand``, then ``gate.obstacles_near`` (``c = -1``): ``(a, c, d_s, centre, loc, M)``."""
    n, m = p0.shape[0], oc.shape[0]
    loc, M = np.full(n, -1, dtype=np.int64), 0  # each robot's row among the M robots in a pair (-1: in none)
    a, c = np.empty(cand.shape[0] + n * m, np.int64), np.empty(cand.shape[0] + n * m, np.int64)
    ds, at = np.empty(a.shape[0]), np.zeros(a.shape[0], np.complex128)
    P = 0
    for q in range(cand.shape[0]):
        g, h = cand[q, 0], cand[q, 1]
        if has_group and group[g] != group[h]:
            continue
        dist = cabs(p0[g] - p0[h])
        if dist <= sensing_range and dist < rob[g, RADIUS] + rob[h, RADIUS] + R[g] + R[h] + slack:
            a[P], c[P], ds[P] = g, h, rob[g, RADIUS] + rob[h, RADIUS]
            for x in (g, h):
                if loc[x] < 0:
                    loc[x], M = M, M + 1
            P += 1
    for g in range(n):
        for o in range(m):
            if has_group and has_ogroup and group[g] != ogroup[o]:
                continue
            if cabs(p0[g] - oc[o]) < rob[g, RADIUS] + orad[o] + R[g] + slack:
                a[P], c[P], ds[P], at[P] = g, -1, rob[g, RADIUS] + orad[o], oc[o]
                if loc[g] < 0:
                    loc[g], M = M, M + 1
                P += 1
    return a[:P], c[:P], ds[:P], at[:P], loc, M


@jit
def _store(C, F, NEED, k, g, base, p1, dev, pdot, w, rate, steps, reach, bulge):
    """Robot ``g``'s path on level ``k``: ``C`` (step end, velocity), ``F`` (``D1 .. REACH``), ``NEED``."""
    C[k, g, 0], C[k, g, 1], NEED[k, g] = p1, pdot, steps + base
    F[k, g, 0], F[k, g, 1], F[k, g, 2], F[k, g, 3], F[k, g, 4] = dev, w, rate, bulge, reach


@jit
def _gate_levels(pose, u, du_c, dt, levels, quick, diff, rob, cols, p0, hd, limit):
    """Every level's inputs ``(nl, n, 2)`` and path parameters ``C, F, NEED`` (``gate._levels``)."""
    n, nl = pose.shape[0], levels.shape[0]
    last = nl - 1
    du_all, C = np.empty((nl, n, 2)), np.empty((nl, n, 2), dtype=np.complex128)
    F, NEED = np.zeros((nl, n, 5)), np.empty((nl, n), dtype=np.int64)
    for g in range(n):  # the backup from now: level `last`
        rc = consts(rob, cols, g)
        den = nmax(brake_time1(diff, rc, u[g, 0], u[g, 1]), dt)
        pdot, w, rate, steps, reach, bulge = brake1(diff, rc, hd[g], u[g, 0], u[g, 1], dt)
        _store(C, F, NEED, last, g, 1, 0j, 0.0, pdot, w, rate, steps, reach, bulge)
        du_all[last, g, 0], du_all[last, g, 1] = -u[g, 0] / den, -u[g, 1] / den
    for k in range(nl - 1):  # one step blending the candidate and the backup, then the backup
        a = levels[k]
        out = False
        for g in range(n):
            b0, b1 = du_all[last, g, 0], du_all[last, g, 1]
            da0, da1 = b0 + a * (du_c[g, 0] - b0), b1 + a * (du_c[g, 1] - b1)
            du_all[k, g, 0], du_all[k, g, 1] = da0, da1
            p1, dev, pdot, w, rate, steps, reach, bulge = candidate1(
                diff, consts(rob, cols, g), p0[g], pose[g, 2], hd[g], u[g, 0], u[g, 1], da0, da1, dt)
            _store(C, F, NEED, k, g, 2, p1, dev, pdot, w, rate, steps, reach, bulge)
            out = out or reach > limit[g]
        if k == 0 and quick and not out:  # no candidate leaves the range: levels (1, 0), rows 0 and last
            keep = np.array([0, last])
            return du_all[keep], C[keep], F[keep], NEED[keep]
    return du_all, C, F, NEED


@jit
def _gate_rounds(lev, broken, limit, p0, C, F, NEED, has_bulge, dt, a, c, ds, at, loc, M, tol, hold):
    """The gatekeeper's rounds (``gate._rounds``): ``lev``, ``broken`` updated in place; ``(margins, rounds)``."""
    n, P, last = lev.shape[0], a.shape[0], NEED.shape[0] - 1
    L = 2
    for g in range(n):
        for k in range(last + 1 if loc[g] >= 0 else 0):
            L = max(L, NEED[k, g])
    cur, curd = np.empty((M, L), dtype=np.complex128), np.empty((M, L - 1))
    tol_p = np.full(P, tol)
    if hold:  # each pair's tolerance the larger of tol and its margin when both members brake now
        for g in range(n):
            if loc[g] >= 0:
                fill_row(cur, curd, loc[g], g, last, last, p0, C, F, has_bulge, dt, NEED[last, g], True)
        for q in range(P):
            g, h = a[q], c[q]
            m = pair_margin(cur, curd, NEED[last, g], 0 if h < 0 else NEED[last, h], loc[g], -1 if h < 0 else loc[h],
                            ds[q], at[q])
            fl = -m if -m > 0.0 else 0.0  # NaN: no floor (numpy's fmax)
            tol_p[q] = max(tol_p[q], fl * (1.0 + 1e-9))
    marg, todo = np.full(P, np.inf), np.ones(P, dtype=np.bool_)
    filled, demote = np.full(n, -1, dtype=np.int64), np.zeros(n, dtype=np.bool_)
    rounds = 0
    while True:
        rounds += 1
        for g in range(n):  # the paths of the robots' current levels: only changed rows are made again
            if loc[g] >= 0 and lev[g] != filled[g]:
                fill_row(cur, curd, loc[g], g, lev[g], last, p0, C, F, has_bulge, dt, NEED[lev[g], g], True)
                filled[g] = lev[g]
        demote[:] = False
        any_demote = False
        for q in range(P):
            if not todo[q]:
                continue
            g, h = a[q], c[q]
            st = h < 0
            m = pair_margin(cur, curd, NEED[lev[g], g], 0 if st else NEED[lev[h], h], loc[g], -1 if st else loc[h],
                            ds[q], at[q])
            marg[q] = -np.inf if m != m else m  # a margin that is not a number fails
            if marg[q] < -tol_p[q]:
                if lev[g] == last and (st or lev[h] == last):  # not brake-safe before: nothing to demote
                    broken[g] = True
                    if not st:
                        broken[h] = True
                for x in (g, h):
                    if x >= 0 and lev[x] != last:
                        demote[x] = any_demote = True
        if not any_demote:
            return marg, rounds
        for g in range(n):  # one level down, then past any level whose path leaves the range limit
            if demote[g]:
                lev[g] += 1
                while lev[g] < last and F[lev[g], g, REACH] > limit[g]:
                    lev[g] += 1
        for q in range(P):
            todo[q] = demote[a[q]] or (c[q] >= 0 and demote[c[q]])


@jit
def gate_full(pose, u, du_c, dt, levels, quick, diff, rob, cols, group, has_group, sensing_range, cand, oc, orad,
              ogroup, has_ogroup, limit, tol, hold):
    """``gatekeeper``: ``(du, braking, broken, share, robot_margin, out_of_range, rounds, n_pairs, margin)``."""
    n = pose.shape[0]
    p0, hd = starts(diff, rob, pose)
    du_all, C, F, NEED = _gate_levels(pose, u, du_c, dt, levels, quick, diff, rob, cols, p0, hd, limit)
    last = NEED.shape[0] - 1
    R, lev = np.empty(n), np.zeros(n, dtype=np.int64)
    broken, out_of_range = np.zeros(n, dtype=np.bool_), np.zeros(n, dtype=np.bool_)
    for g in range(n):
        for k in range(last + 1):
            if F[k, g, REACH] != F[k, g, REACH]:  # a reach that is not a number bounds nothing
                F[k, g, REACH] = np.inf
            R[g] = F[k, g, REACH] if k == 0 else max(R[g], F[k, g, REACH])
        while lev[g] < last and F[lev[g], g, REACH] > limit[g]:  # a level whose path leaves the range is skipped
            lev[g] += 1
        broken[g], out_of_range[g] = F[last, g, REACH] > limit[g], F[0, g, REACH] > limit[g]
    a, c, ds, at, loc, M = near(cand, p0, R, rob, group, has_group, sensing_range, oc, orad, ogroup, has_ogroup, 1e-12)
    robot_margin, rounds = limit.copy(), 0
    if a.shape[0]:
        marg, rounds = _gate_rounds(lev, broken, limit, p0, C, F, NEED, not diff, dt, a, c, ds, at, loc, M, tol,
                                    hold)
        for q in range(a.shape[0]):
            for x in (a[q], c[q]):
                if x >= 0:
                    robot_margin[x] = min(robot_margin[x], marg[q])
    margin = 0.5 * sensing_range  # (each robot's margin is at most its limit)
    for g in range(n):
        margin = min(margin, robot_margin[g])
    du, share = np.empty((n, 2)), np.empty(n)
    for g in range(n):
        du[g, 0], du[g, 1] = du_all[lev[g], g, 0], du_all[lev[g], g, 1]
        share[g] = levels[lev[g] if lev[g] < last else levels.shape[0] - 1]
    return du, lev > 0, broken, share, robot_margin, out_of_range, rounds, a.shape[0], margin


@jit
def _lifts(cur, curd, need, a, c, ds, at, low, m0, kk, target, eps, diff, rob, cols, p0, hd, pose, u, du, dt):
    """The summed least-norm lifts ``(n, 2)`` of the low pairs, by finite differences at their closest steps."""
    P = a.shape[0]
    grad, lift = np.zeros((P, 2, 2)), np.zeros(P)
    for q in range(P):
        if not low[q]:
            continue
        k = kk[q]
        for side in range(1 if c[q] < 0 else 2):
            mv, fx = (a[q], c[q]) if side == 0 else (c[q], a[q])
            if fx < 0:
                qf0 = qf1 = at[q]
                dfx = 0.0
            else:
                qf0, qf1 = cur[fx, min(k, need[fx] - 1)], cur[fx, min(k + 1, need[fx] - 1)]
                dfx = curd[fx, k] if k < need[fx] - 1 else 0.0
            for d in range(2):  # samples k, k + 1 and step k's deviation with input d moved by eps
                p1, dev, pdot, w, rate, steps, _, bulge = candidate1(
                    diff, consts(rob, cols, mv), p0[mv], pose[mv, 2], hd[mv], u[mv, 0], u[mv, 1],
                    du[mv, 0] + (eps if d == 0 else 0.0), du[mv, 1] + (eps if d == 1 else 0.0), dt)
                pa0, dm0 = sample_at(p0[mv], p1, dev, pdot, w, rate, steps, bulge, not diff, dt, k)
                pa1, _ = sample_at(p0[mv], p1, dev, pdot, w, rate, steps, bulge, not diff, dt, k + 1)
                grad[q, side, d] = (segment_margin(pa0, pa1, qf0, qf1, dm0, dfx) - ds[q] - m0[q]) / eps
        nrm = (grad[q, 0, 0] * grad[q, 0, 0] + grad[q, 0, 1] * grad[q, 0, 1]) + (
            grad[q, 1, 0] * grad[q, 1, 0] + grad[q, 1, 1] * grad[q, 1, 1])
        lift[q] = (2.0 * target - m0[q]) / max(nrm, 1e-12)
    step = np.zeros((p0.shape[0], 2))
    for side in range(3):  # in numpy's order: every pair's first member, then second, then the obstacles'
        for q in range(P):
            if low[q] and (c[q] < 0) == (side == 2):
                g, s = (c[q], 1) if side == 1 else (a[q], 0)
                step[g, 0] += lift[q] * grad[q, s, 0]
                step[g, 1] += lift[q] * grad[q, s, 1]
    return step


@jit
def repair_full(pose, u, du_c, lo, hi, dt, diff, rob, cols, group, has_group, sensing_range, cand, oc, orad,
                ogroup, has_ogroup, target, rounds, eps, tie):
    """One ``repair`` call: the nudged candidate ``(n, 2)`` (``tie``: the closest-step tie of ``gate.CLOSEST_TIE``)."""
    n = pose.shape[0]
    du = np.empty((n, 2))
    for g in range(n):
        for d in range(2):
            du[g, d] = min(max(du_c[g, d], lo[g, d]), hi[g, d])
    p0, hd = starts(diff, rob, pose)
    C, F, NEED = np.empty((1, n, 2), dtype=np.complex128), np.zeros((1, n, 5)), np.empty((1, n), dtype=np.int64)
    R = np.empty(n)
    rowp, rowd, made = np.empty((n, 2), dtype=np.complex128), np.empty((n, 1)), np.zeros(n, dtype=np.bool_)
    for _ in range(rounds):
        for g in range(n):  # reach first: only robots with a pair that could come close need paths
            p1, dev, pdot, w, rate, steps, reach, bulge = candidate1(
                diff, consts(rob, cols, g), p0[g], pose[g, 2], hd[g], u[g, 0], u[g, 1], du[g, 0], du[g, 1], dt)
            _store(C, F, NEED, 0, g, 2, p1, dev, pdot, w, rate, steps, reach, bulge)
            R[g] = reach + eps * dt * dt
        a, c, ds, at, loc, _ = near(cand, p0, R, rob, group, has_group, sensing_range, oc, orad, ogroup, has_ogroup,
                            2.0 * target)
        if a.shape[0] == 0:
            break
        L = 2
        for g in range(n):
            L = max(L, NEED[0, g]) if loc[g] >= 0 else L
        if L > rowp.shape[1]:
            rowp, rowd = np.empty((n, L), dtype=np.complex128), np.empty((n, L - 1))
            made[:] = False
        for g in range(n):  # the candidate paths of robots in pairs, each kept until its input changes
            if loc[g] >= 0 and not made[g]:
                fill_row(rowp, rowd, g, g, 0, 1, p0, C, F, not diff, dt, NEED[0, g], False)
                made[g] = True
        P = a.shape[0]
        low, m0, kk = np.zeros(P, dtype=np.bool_), np.empty(P), np.empty(P, dtype=np.int64)
        for q in range(P):  # the pairs whose margin is below target, at their closest steps
            g, h = a[q], c[q]
            nh = 0 if h < 0 else NEED[0, h]
            if pair_margin(rowp, rowd, NEED[0, g], nh, g, h, ds[q], at[q]) < target:
                low[q] = True
                best, kk[q] = pair_min(rowp, rowd, NEED[0, g], nh, g, h, at[q], L - 1, tie)
                m0[q] = best - ds[q]
        if not low.any():
            break
        step = _lifts(rowp, rowd, NEED[0], a, c, ds, at, low, m0, kk, target, eps, diff, rob, cols, p0, hd, pose,
                      u, du, dt)
        if not (step != 0.0).any():
            break
        for g in range(n):
            for d in range(2):
                v = min(max(du[g, d] + step[g, d], lo[g, d]), hi[g, d])
                if v != du[g, d]:
                    made[g] = False  # its path is made again when asked for
                du[g, d] = v
    return du
