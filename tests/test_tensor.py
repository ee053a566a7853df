"""The torch filter and env (:mod:`aasoatt_env.tensor`) against the numpy ones, on CPU (and CUDA where present)."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from aasoatt_env.model import dynamics  # noqa: E402
from aasoatt_env.model.params import make_team  # noqa: E402
from aasoatt_env.safety import FilterConfig, SafetyFilter, barriers  # noqa: E402
from aasoatt_env.tensor.filter import (  # noqa: E402
    BACKUP,
    BACKUP_CHECKS,
    GROUPED,
    RELAXED,
    UNSAFE,
    SafetyLayer,
    filter_step,
)
from aasoatt_env.tensor.model import TensorTeam  # noqa: E402

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device on this machine (torch.cuda.is_available() is False)"))]


def random_states(rng: np.random.Generator, count: int, n: int) -> list[dict]:
    """Team states near contact: jittered grids 1.1-2.2 m apart, random headings, speeds, nominals, memory."""
    team = make_team("paper", n)
    side = int(np.ceil(np.sqrt(n)))
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)[:n].astype(float)
    out = []
    for _ in range(count):
        p = grid * rng.uniform(1.1, 2.2) + rng.uniform(-0.05, 0.05, (n, 2))
        th = rng.uniform(-np.pi, np.pi, n)
        u = rng.normal(0.0, rng.choice([0.3, 1.0, 3.0]), (n, 2))
        oc, orad = rng.uniform(-1.0, 5.0, (2, 2)), rng.uniform(0.2, 0.5, 2)
        if (np.hypot(*(p[:, None] - oc[None]).transpose(2, 0, 1)) - orad - 0.7).min() < 0.0:
            oc = oc + 50.0  # (no start inside an obstacle; the control point is 0.2 m ahead of the axle)
        out.append(dict(pose=dynamics.pose_from_point(team, p, th), u=u, nom=rng.normal(0.0, 20.0, (n, 2)),
                        pd=p + rng.normal(0.0, 0.5, (n, 2)), vd=rng.normal(0.0, 0.8, (n, 2)), oc=oc, orad=orad,
                        avoiding=rng.random(n) < 0.3))
    return out


def numpy_answers(states: list[dict], cfg: FilterConfig, n: int):
    team = make_team("paper", n)
    f = SafetyFilter(team, cfg)
    res = []
    for s in states:
        f.reset(team)
        f._dl.avoiding = s["avoiding"].copy()  # the trigger's memory, as the previous step left it
        f._x = np.zeros((n, 2))
        kin = dynamics.kinematics(team, s["pose"], s["u"])
        lo, hi = dynamics.input_bounds(team, s["u"], cfg.dt)
        res.append(f.step(kin, s["u"], s["pose"][:, 2], s["nom"], lo, hi, reference=(s["pd"], s["vd"]),
                          obstacles=(s["oc"], s["orad"]))[1])
    return team, res


def tensor_answers(team, states: list[dict], cfg: FilterConfig, device="cpu", dtype=torch.float64,
                   backup_check: str | None = None):
    def stack(key):
        return torch.as_tensor(np.stack([s[key] for s in states]), device=device)

    return filter_step(TensorTeam.from_team(team, dtype, device), cfg, stack("pose").to(dtype), stack("u").to(dtype),
                       stack("nom").to(dtype), stack("pd").to(dtype), stack("vd").to(dtype),
                       (stack("oc").to(dtype), stack("orad").to(dtype)), stack("avoiding"), backup_check)


@pytest.mark.parametrize("device", DEVICES)
def test_the_filter_equals_the_numpy_decentralised_filter_where_it_answers_by_the_robots_own_qps(device):
    """1,000+ team states (12 robots, 2 obstacles) in one batched call: the numpy filter's ``du`` to 1e-9 wherever its
    status is ``solved``, the same trigger memory and triggered robots; where it relaxed too (both run the same
    least-violation code from the same start, :mod:`~aasoatt_env.safety.solvers.polygons`), those robots flagged
    ``RELAXED``."""
    rng = np.random.default_rng(0)
    n = 12
    states = random_states(rng, 1500, n)
    cfg = FilterConfig(mode="decentralized", backup=False, negotiate=False, kernel="numpy")
    team, ref = numpy_answers(states, cfg, n)
    out = tensor_answers(team, states, cfg, device)
    du, status = out.du.cpu().numpy(), out.status.cpu().numpy()
    solved = np.array([r.status == "solved" for r in ref])
    assert solved.sum() >= 1000
    ref_du = np.stack([r.du for r in ref])
    assert np.abs(du[solved] - ref_du[solved]).max() <= 1e-9
    assert (status[solved] == 0).all()
    assert np.array_equal(out.avoiding.cpu().numpy()[solved], np.stack([r.avoiding for r in ref])[solved])
    assert np.array_equal(out.triggered.cpu().numpy(), np.stack([r.triggered for r in ref]))
    assert np.stack([r.intervened for r in ref])[solved].mean() > 0.3  # the rows bind: not the nominal clipped
    assert ((status[~solved] & RELAXED) > 0).any()
    assert np.abs(du - ref_du).max() <= 1e-9


def test_a_rotation_gain_that_float32_cannot_hold_is_applied_in_float64():
    """``zeta = 1.1`` (not a float32 number): the float64 filter's ``du`` equals the numpy filter's to 1e-9 on the
    robots the trigger rotates, so the gain is not rounded through float32 on the way."""
    rng = np.random.default_rng(1)
    n = 12
    states = random_states(rng, 300, n)
    cfg = FilterConfig(mode="decentralized", backup=False, negotiate=False, kernel="numpy", zeta=1.1)
    team, ref = numpy_answers(states, cfg, n)
    out = tensor_answers(team, states, cfg)
    solved = np.array([r.status == "solved" for r in ref])
    triggered = np.stack([r.triggered for r in ref]) & solved[:, None]
    assert triggered.sum() >= 100
    assert np.abs(out.du.numpy()[triggered] - np.stack([r.du for r in ref])[triggered]).max() <= 1e-9


def test_a_step_with_no_robot_or_obstacle_in_range_answers_each_robot_by_its_box():
    """Teams whose robots are all out of each other's sensing range, no obstacles (so no barrier row at all): the
    answer is each robot's nominal projected onto its box, as the numpy filter's."""
    rng = np.random.default_rng(4)
    n = 4
    states = random_states(rng, 20, n)
    for s in states:
        s["pose"][:, :2] *= 10.0  # 11-22 m apart, D = 3 m
        s["oc"], s["orad"] = np.zeros((0, 2)), np.zeros(0)
    cfg = FilterConfig(mode="decentralized", backup=False, negotiate=False, kernel="numpy")
    team, ref = numpy_answers(states, cfg, n)
    out = tensor_answers(team, states, cfg)
    assert np.abs(out.du.numpy() - np.stack([r.du for r in ref])).max() <= 1e-9
    assert (out.status.numpy() == 0).all()


@pytest.mark.parametrize("check", BACKUP_CHECKS)
def test_a_team_gets_the_same_answer_alone_as_in_a_batch(check):
    """Either backup check, its horizon and the negotiation groups are each team's own: 64 team states near contact,
    behind the defaults (``backup=True``, ``negotiate=True``), filtered in one batch and one team at a time: the same
    status and ``du`` to 1e-12 (1e-9 in an inconsistent group, whose least-violation QP the batch solves with the
    others)."""
    rng = np.random.default_rng(7)
    n = 8
    states = random_states(rng, 64, n)
    for i, s in enumerate(states):
        s["u"] *= 1.0 + 3.0 * (i % 4)  # teams of very different speeds (so different braking horizons)
    cfg = FilterConfig(mode="decentralized")
    team = make_team("paper", n)
    both = tensor_answers(team, states, cfg, backup_check=check)
    assert int((both.status & BACKUP).sum()) > 0
    assert int((both.status & GROUPED).sum()) > 0
    for i, s in enumerate(states):
        alone = tensor_answers(team, [s], cfg, backup_check=check)
        assert torch.equal(alone.status[0], both.status[i])
        tol = torch.where((both.status[i] & (GROUPED | RELAXED)) == (GROUPED | RELAXED), 1e-9, 1e-12)
        assert ((alone.du[0] - both.du[i]).abs().amax(-1) <= tol).all()


def test_negotiation_groups_equal_the_numpy_filters_and_inconsistent_ones_are_flagged():
    """``negotiate=True`` (the default): 1,200 team states where the trigger's memory flags robots near contact, so
    most teams form negotiation groups; the torch filter solves them by the numpy filter's solver. Wherever the numpy
    filter's status is ``solved`` every robot's ``du`` agrees to 1e-9, grouped ones included (flagged ``GROUPED``);
    exactly the teams whose group is inconsistent (numpy: ``relaxed``) have ``GROUPED | RELAXED`` robots, and every
    robot's status bits are the numpy filter's ``flags``; the trigger memory agrees everywhere."""
    rng = np.random.default_rng(1)
    n = 12
    states = random_states(rng, 1200, n)
    cfg = FilterConfig(mode="decentralized", backup=False, negotiate=True, kernel="numpy")
    team, ref = numpy_answers(states, cfg, n)
    out = tensor_answers(team, states, cfg)
    du, status = out.du.numpy(), out.status.numpy()
    grouped = status & GROUPED > 0
    solved = np.array([r.status == "solved" for r in ref])
    assert solved.sum() >= 800 and grouped[solved].sum() >= 2000
    assert np.abs(du[solved] - np.stack([r.du for r in ref])[solved]).max() <= 1e-9
    group_relaxed = np.array([r.message.endswith(": relaxed") for r in ref])
    assert group_relaxed.sum() >= 20
    assert np.array_equal((grouped & (status & RELAXED > 0)).any(axis=1), group_relaxed)
    assert np.array_equal(status, np.stack([r.flags for r in ref]))
    assert np.array_equal(out.avoiding.numpy(), np.stack([r.avoiding for r in ref]))


def test_the_filter_with_the_numpy_backup_layer_equals_the_numpy_filter():
    """``backup=True`` with ``backup_check="numpy"`` (a CPU's default): 1,200 team states at three speed scales, some
    not brake-safe: every robot's ``du`` equals the numpy filter's to 1e-9 (its backup layer braked and repaired
    some of them), ``BACKUP`` on exactly the robots it braked, ``UNSAFE`` in exactly the teams it calls unsafe."""
    rng = np.random.default_rng(3)
    n = 12
    states = random_states(rng, 1200, n)
    for i, s in enumerate(states):
        s["u"] *= 1.0 + 2.0 * (i % 3)
    cfg = FilterConfig(mode="decentralized", negotiate=False, kernel="numpy")
    team, ref = numpy_answers(states, cfg, n)
    out = tensor_answers(team, states, cfg, backup_check="numpy")
    status = out.status.numpy()
    assert np.abs(out.du.numpy() - np.stack([r.du for r in ref])).max() <= 1e-9
    braked = np.stack([r.backup for r in ref])
    assert braked.sum() >= 50 and np.array_equal(status & BACKUP > 0, braked)
    unsafe = np.array([not r.safe for r in ref])
    assert 0 < unsafe.sum() < 200 and np.array_equal((status & UNSAFE > 0).any(axis=1), unsafe)
    assert np.array_equal(status, np.stack([r.flags for r in ref]))


@pytest.mark.slow
@pytest.mark.parametrize("compiled", [False, True])
def test_closed_loop_behind_the_numpy_backup_layer_equals_the_pettingzoo_env(compiled):
    """Two random_goals teams of 8 spun up and then driven at full throttle (the ``spin_up`` adversary, every 200
    steps) for 600 steps behind the defaults with ``negotiate=False``, by the torch or the compiled stages: the backup
    layer brakes, some QPs relax, and the positions stay within 1e-6 m of the PettingZoo env's behind the numpy
    filter, in float64. (With groups, an inconsistent group's relaxed answer depends on the solver's path through the
    batch's problem: not compared.)"""
    from aasoatt_env.sim.env import AASOATTParallelEnv
    from aasoatt_env.tensor.env import make_tensor_env

    n, opts = 8, dict(negotiate=False)
    tenv = make_tensor_env("random_goals", 2, n, dtype=torch.float64, max_steps=200, backup_check="numpy",
                           compiled=compiled, **opts)
    tenv.reset(seed=0)
    envs = []
    for b in range(2):
        e = AASOATTParallelEnv("random_goals", num_robots=n, max_steps=200)
        e.set_control_filter(SafetyFilter(mode="decentralized", **opts))
        e.reset(seed=b)
        envs.append(e)
    rng = np.random.default_rng(0)
    worst, braked, relaxed = 0.0, 0, 0
    for t in range(600):
        if t % 200 == 0:
            sign = rng.choice([-1.0, 1.0], (2, n, 1))
        act = np.concatenate((sign, -sign), -1) if t % 200 < 120 else np.ones((2, n, 2))
        _, _, _, _, info = tenv.step(torch.as_tensor(act))
        braked += int(info["backup"].sum())
        relaxed += int((info["status"] & RELAXED > 0).sum())
        for b, e in enumerate(envs):
            _, _, _, trunc, _ = e.step({a: act[b, i].astype(np.float32) for i, a in enumerate(e.possible_agents)})
            if trunc[e.possible_agents[0]]:
                e.reset()
            worst = max(worst, float(np.abs(e.positions - tenv.kin.p[b].numpy()).max()))
    assert worst <= 1e-6 and braked > 20 and relaxed > 0


def test_gradients_match_finite_differences_away_from_active_set_boundaries():
    """``torch.autograd.gradcheck`` (float64) of the filtered action w.r.t. nominal, pose and wheel speeds on states
    where rows bind; a state within 1e-6 of an active-set boundary (a kink) is skipped."""
    rng = np.random.default_rng(1)
    n = 6
    team = make_team("paper", n)
    layer = SafetyLayer(team, backup=False, negotiate=False)
    base = np.array([[0, 0], [1.1, 0.1], [2.3, 0], [0, 1.2], [1.2, 1.3], [2.5, 1.1]], dtype=float)
    checked = 0
    for _ in range(12):
        p = base + rng.uniform(-0.05, 0.05, (n, 2))
        pose = torch.tensor(dynamics.pose_from_point(team, p, rng.uniform(-np.pi, np.pi, n)))[None]
        u = torch.tensor(rng.normal(0, 2, (n, 2)))[None]
        nom = torch.tensor(rng.normal(0, 15, (n, 2)))[None]
        pd, vd = torch.tensor(p)[None], torch.zeros(1, n, 2, dtype=torch.float64)
        out = filter_step(layer.team, layer.config, pose, u, nom, pd, vd)
        if not out.intervened.any() or (out.status != 0).any():
            continue
        step = 1e-6 * torch.randn_like(nom)
        near = [filter_step(layer.team, layer.config, pose, u, nom + d * step, pd, vd).du for d in (1.0, -1.0)]
        if (near[0] + near[1] - 2.0 * out.du).abs().max() > 1e-9:  # second difference: a kink within reach
            continue
        args = tuple(a.clone().requires_grad_() for a in (pose, u, nom))
        assert torch.autograd.gradcheck(lambda a, b, c, pd=pd, vd=vd: layer(a, b, c, pd, vd), args, eps=1e-7,
                                        atol=1e-5, rtol=1e-4)
        checked += 1
    assert checked >= 5


def _tracking_actions(p, v, p_d, v_d, adot, A, solve, amax=60.0):
    """Wheel actions of the paper's tracking law ``a = k3 (p_d - p) + k4 (v_d - v)`` (k3 = 1, k4 = 4)."""
    return solve(A, (1.0 * (p_d - p) + 4.0 * (v_d - v) - adot)[..., None])[..., 0] / amax


@pytest.mark.slow
@pytest.mark.parametrize("compiled", [False, True])
@pytest.mark.parametrize("negotiate", [False, True])
@pytest.mark.parametrize("device", DEVICES)
def test_closed_loop_500_steps_equals_the_pettingzoo_env_behind_the_numpy_filter(device, negotiate, compiled):
    """Two random_goals teams of 8 (seeds 0, 1) behind the filter for 500 steps, 200-step episodes (auto-reset twice),
    where some robots' QPs are infeasible (relaxed) at some steps, and (``negotiate=True``) some robots are answered
    by their negotiation groups, by the torch or the compiled stages: positions within 1e-6 m, observations and
    rewards equal, in float64."""
    if compiled and device != "cpu":
        pytest.skip("the compiled stages run on a CPU only")
    from aasoatt_env.sim.env import AASOATTParallelEnv
    from aasoatt_env.tensor.env import make_tensor_env

    n, seed, opts = 8, 0, dict(backup=False, negotiate=negotiate)
    tenv = make_tensor_env("random_goals", 2, n, device=device, dtype=torch.float64, max_steps=200, compiled=compiled,
                           **opts)
    obs_t, _ = tenv.reset(seed=seed)
    envs = []
    for b in range(2):
        e = AASOATTParallelEnv("random_goals", num_robots=n, max_steps=200)
        e.set_control_filter(SafetyFilter(mode="decentralized", kernel="numpy", **opts))
        o, _ = e.reset(seed=seed + b)
        assert np.array_equal(np.stack([o[a] for a in e.possible_agents]), obs_t[b].cpu().numpy())
        envs.append(e)
    worst, resets, relaxed, grouped = 0.0, 0, 0, 0
    for _ in range(500):
        acts = [_tracking_actions(e.kinematics.p, e.kinematics.v, *e.reference[:2], e.kinematics.adot_u,
                                  e.kinematics.A, np.linalg.solve) for e in envs]
        k = tenv.kin
        A = torch.stack((torch.stack((k.a00, k.a01), -1), torch.stack((k.a10, k.a11), -1)), -2)
        obs_t, rew_t, _, trunc_t, info = tenv.step(_tracking_actions(k.p, k.v, *tenv.ref[:2], k.adot, A,
                                                                     torch.linalg.solve))
        assert (info["status"] & ~(RELAXED | GROUPED) == 0).all()
        relaxed += int((info["status"] & RELAXED).sum())
        grouped += int((info["status"] & GROUPED > 0).sum())
        for b, e in enumerate(envs):
            o, r, _, tr, _ = e.step({a: acts[b][i] for i, a in enumerate(e.possible_agents)})
            assert np.abs(np.array(list(r.values())) - rew_t[b].cpu().numpy()).max() <= 1e-9
            if tr[e.possible_agents[0]]:
                o, _ = e.reset()
                resets += 1
                assert bool(trunc_t[b].all()) and bool(info["reset"][b])
            worst = max(worst, float(np.abs(e.positions - tenv.kin.p[b].cpu().numpy()).max()))
            assert np.abs(np.stack([o[a] for a in e.possible_agents]) - obs_t[b].cpu().numpy()).max() <= 1e-5
    assert resets == 4 and worst <= 1e-6 and relaxed > 0 and (grouped > 0) == negotiate


@pytest.mark.parametrize("compiled", [False, True])
def test_point_actions_follow_the_pettingzoo_env_in_point_mode(compiled):
    """``action_mode="point"``: the tracking law as control-point accelerations (units of ``max_point_accel``) for two
    random_goals teams of 6 behind the filter, 150 steps of 100 ms, by the torch or the compiled stages: positions
    within 1e-6 m of the PettingZoo env's."""
    from aasoatt_env.sim.env import AASOATTParallelEnv
    from aasoatt_env.tensor.env import make_tensor_env

    n, opts = 6, dict(backup=False, negotiate=False)
    tenv = make_tensor_env("random_goals", 2, n, dtype=torch.float64, action_mode="point", decision_interval=20,
                           max_steps=150, compiled=compiled, **opts)
    tenv.reset(seed=5)
    envs = []
    for b in range(2):
        e = AASOATTParallelEnv("random_goals", num_robots=n, action_mode="point", decision_interval=20,
                               max_steps=150)
        e.set_control_filter(SafetyFilter(mode="decentralized", kernel="numpy", **opts))
        e.reset(seed=5 + b)
        envs.append(e)
    amax = float(tenv.team.max_point_accel[0])
    worst = 0.0
    for _ in range(149):  # (the 150th ends the episodes: auto-reset)
        acts = torch.clamp((1.0 * (tenv.ref[0] - tenv.kin.p) + 4.0 * (tenv.ref[1] - tenv.kin.v)) / amax, -1.0, 1.0)
        tenv.step(acts)
        for b, e in enumerate(envs):
            e.step({a: acts[b, i].numpy() for i, a in enumerate(e.possible_agents)})
            worst = max(worst, float(np.abs(e.positions - tenv.kin.p[b].numpy()).max()))
    assert worst <= 1e-6
    home = torch.sqrt(((tenv.kin.p - tenv.goals) ** 2).sum(-1)) < 0.5
    assert float(home.double().mean()) >= 0.75  # most robots tracked home: the actions drove them


def test_a_loss_through_the_filter_trains_a_policy_to_need_less_correction():
    """A linear policy (nominal from the relative goal direction) trained by Adam on ``|filter(nominal) - nominal|^2``
    minus progress: the filter's mean correction falls to under half of the start's within 60 updates."""
    torch.manual_seed(0)
    rng = np.random.default_rng(3)
    n = 6
    team = make_team("paper", n)
    layer = SafetyLayer(team, backup=False, negotiate=False)
    states = random_states(rng, 32, n)
    pose = torch.tensor(np.stack([s["pose"] for s in states]))
    u = torch.zeros(32, n, 2, dtype=torch.float64)
    p = pose[..., :2]
    goal = torch.tensor(np.stack([s["pd"] for s in states]))
    feats = torch.cat((goal - p, torch.ones(32, n, 1, dtype=torch.float64)), -1)
    policy = torch.nn.Linear(3, 2, dtype=torch.float64)
    with torch.no_grad():
        policy.weight.fill_(40.0)
        policy.bias.fill_(30.0)
    opt = torch.optim.Adam(policy.parameters(), lr=2.0)

    def correction():
        nom = policy(feats)
        du = layer(pose, u, nom, goal, torch.zeros_like(goal))
        return ((du - nom) ** 2).sum(-1).mean(), nom

    first = float(correction()[0].detach())
    for _ in range(60):
        loss, nom = correction()
        opt.zero_grad()
        (loss + 1e-3 * (nom ** 2).sum(-1).mean()).backward()
        opt.step()
    assert float(correction()[0].detach()) < 0.5 * first


@pytest.mark.slow
@pytest.mark.parametrize("check, compiled", [("torch", False), ("numpy", False), ("numpy", True)])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_braking_check_keeps_chasing_teams_apart(dtype, check, compiled):
    """Six teams of 8 with 4 obstacles, every robot chasing another at full acceleration for 300 steps behind the
    torch filter's defaults (``backup=True``) with either check, or by the compiled stages: no pair closer than
    ``d_s - 1 mm``, and the check braked someone."""
    from aasoatt_env.tensor.env import make_tensor_env
    from agents.adversaries_torch import adversary_actions

    env = make_tensor_env("random_goals", 6, 8, dtype=dtype, random_obstacles=4, backup_check=check,
                          compiled=compiled)
    env.reset(seed=0)
    gen = torch.Generator().manual_seed(0)
    kind = torch.tensor([3, 4, 3, 4, 0, 1])  # chase_nearest, chase_target, spin_up, burst
    state = {"target": (torch.arange(8)[None] + torch.randint(1, 8, (6, 8), generator=gen)) % 8}
    low, braked = float("inf"), 0
    with torch.no_grad():
        for t in range(300):
            _, _, _, _, info = env.step(adversary_actions(env, t, kind, gen, state))
            low = min(low, float(info["clearance"].min()))
            braked += int(info["backup"].sum())
    assert low >= -1e-3 and braked > 0


def _goal_seeking(repair: bool) -> tuple[float, float, float]:
    """Eight teams of 6 driven at the bound toward their goals for 40 decisions (100 ms) behind the torch filter:
    the share of robot-decisions braked, robots within 0.5 m of their goal, the smallest surface gap."""
    from aasoatt_env.tensor.env import make_tensor_env

    env = make_tensor_env("random_goals", 8, 6, dtype=torch.float64, decision_interval=20, action_mode="point",
                          backup_repair=repair, backup_check="torch")
    env.reset(seed=7)
    braked, low = 0, float("inf")
    with torch.no_grad():
        for _ in range(40):
            a = (3.0 * (env.goals - env.kin.p) - 3.0 * env.kin.v) / env.team.max_point_accel[:, None]
            _, _, _, _, info = env.step(a.clamp(-1.0, 1.0))
            braked += int(info["backup"].sum())
            low = min(low, float(info["clearance"].min()))
    near = torch.sqrt(((env.kin.p - env.goals) ** 2).sum(-1)) < 0.5
    return braked / (40 * 48), float(near.float().mean()), low


def test_the_repair_nudges_where_the_check_would_brake():
    """The torch check with ``backup_repair=True`` (default): less than half the robot-decisions braked and more
    robots near their goals than the check alone, with no pair closer than ``d_s - 1 mm`` either way (the check still
    decides)."""
    alone, repaired = _goal_seeking(False), _goal_seeking(True)
    assert alone[0] > 0.05 and repaired[0] < alone[0] / 2
    assert repaired[1] > alone[1]
    assert alone[2] >= -1e-3 and repaired[2] >= -1e-3


def test_torchrl_adapter_passes_check_env_specs_and_resets_finished_teams():
    """``TorchRLTensorEnv``: TorchRL's spec check, the ``agents`` group, and an 80-step rollout of 30-step
    episodes (two partial resets)."""
    pytest.importorskip("torchrl", reason="torchrl is not installed (it is in the dev extra)")
    from torchrl.envs.utils import check_env_specs

    from aasoatt_env.errors import ConfigError
    from aasoatt_env.tensor.torchrl_env import TorchRLTensorEnv

    env = TorchRLTensorEnv("random_goals", num_envs=3, num_robots=4, max_steps=30)
    check_env_specs(env)
    env.set_seed(3)
    td = env.rollout(80, break_when_any_done=False)
    assert td["next", "agents", "observation"].shape == (3, 80, 4, env.env.obs_dim)
    assert td["next", "agents", "reward"].shape == (3, 80, 4, 1) and td["next", "done"].shape == (3, 80, 1)
    done_at = torch.nonzero(td["next", "done"].all(-1).all(0)).flatten().tolist()
    assert done_at == [29, 59]
    # after a reset the team is at the start of its next layout: at rest
    assert float(td["agents", "observation"][:, 30, :, 4:6].abs().max()) == 0.0
    # a seed is used once: the next rollout goes on with each team's generator (new layouts, reproducibly)
    again = env.rollout(2)["agents", "observation"][:, 0]
    assert not torch.equal(again, td["agents", "observation"][:, 0])
    twin = TorchRLTensorEnv("random_goals", num_envs=3, num_robots=4, max_steps=30)
    twin.set_seed(3)
    twin.rollout(80, break_when_any_done=False)
    assert torch.equal(twin.rollout(2)["agents", "observation"][:, 0], again)
    with pytest.raises(ConfigError, match="seed: got -1"):
        env.set_seed(-1)


@pytest.mark.parametrize("check", BACKUP_CHECKS)
def test_differentiable_env_passes_gradients_from_rewards_to_actions(check):
    """``differentiable=True``: a reward two steps later has a finite, non-zero gradient w.r.t. the first actions,
    and so do the observations, the clearance and the correction (lengths of 0, such as a robot's distance to itself,
    a relative speed of robots at rest or a correction where the filter does not intervene, have gradient 0, not
    NaN); by default ``step`` records no graph."""
    from aasoatt_env.tensor.env import make_tensor_env

    env = make_tensor_env("random_goals", 2, 4, dtype=torch.float64, differentiable=True, backup_check=check)
    env.reset(seed=0)
    act = torch.zeros(2, 4, 2, dtype=torch.float64)
    act[:, 0] = 1.0  # (robots 1 to 3 stay at rest: rows of zero relative speed)
    act.requires_grad_(True)
    env.step(act)
    obs, rew, _, _, info = env.step(act.detach())
    for name, out in (("reward", rew), ("observations", obs), ("clearance", info["clearance"]),
                      ("correction", info["correction"])):
        (g,) = torch.autograd.grad(out.sum(), act, retain_graph=True)
        assert torch.isfinite(g).all(), name
        assert g.abs().sum() > 0 or name == "correction", name
    plain = make_tensor_env("circle_swap", 2, 4, dtype=torch.float64, radius=2.0)
    plain.reset(seed=0)
    assert not plain.step(act)[1].requires_grad


def test_bad_settings_are_refused_naming_the_argument(monkeypatch):
    from aasoatt_env.errors import ActionError, ConfigError, ResetNeeded
    from aasoatt_env.tensor.env import make_tensor_env

    for kwargs, name in ((dict(num_envs=0), "num_envs"), (dict(dtype=torch.int32), "dtype"),
                         (dict(mode="centralized"), "mode"), (dict(deadlock="yield"), "deadlock"),
                         (dict(action_mode="torque"), "action_mode: got 'torque'")):
        with pytest.raises(ConfigError, match=name):
            make_tensor_env("random_goals", **{"num_robots": 4, **kwargs})
    paper = barriers.BARRIERS["aasoatt"]
    monkeypatch.setitem(barriers.BARRIERS, "mine", barriers.Barrier(paper.rows, paper.value, "mine"))  # numpy only
    with pytest.raises(ConfigError, match="barrier: got 'mine', registered without array_api=True"):
        make_tensor_env("random_goals", num_robots=4, barrier="mine")
    for kwargs, name in ((dict(decision_interval=0), "decision_interval: got 0"),
                         (dict(max_steps=0), "max_steps: got 0"), (dict(num_neighbors=-1), "num_neighbors: got -1"),
                         (dict(sensing_range=float("nan")), "sensing_range: got nan"),
                         (dict(collision_tolerance=float("nan")), "collision_tolerance: got nan"),
                         (dict(differentiable="no"), "differentiable: got 'no'"), (dict(filter="yes"), "filter: got"),
                         (dict(compiled="yes"), "compiled: got 'yes'"),
                         (dict(compiled=True, differentiable=True), "compiled: got True, but differentiable=True"),
                         (dict(compiled=True, backup_check="torch"), "compiled: got True, but backup_check='torch'"),
                         (dict(filter={"dt": 0.01}), "dt: got 0.01 in filter")):
        with pytest.raises(ConfigError, match=name):
            make_tensor_env("random_goals", **{"num_robots": 4, **kwargs})
    monkeypatch.setattr("aasoatt_env.tensor.env.numba_available", lambda: False)
    with pytest.raises(ConfigError, match="compiled: got True, but the compiled kernels .* need numba"):
        make_tensor_env("random_goals", num_robots=4, compiled=True)
    assert not make_tensor_env("random_goals", num_robots=4).compiled  # (None: the torch stages without numba)
    monkeypatch.undo()
    env = make_tensor_env("random_goals", 2, 4)
    assert env.compiled
    with pytest.raises(ResetNeeded, match=r"step\(\): call reset\(\) first"):
        env.step(torch.zeros(2, 4, 2))
    with pytest.raises(ConfigError, match="seed: got -1"):
        env.reset(seed=-1)
    env.reset(seed=0)
    for actions, match in ((torch.zeros(2, 3, 2), r"actions: got shape \(2, 3, 2\)"),
                           (torch.zeros(2, 4, 2, dtype=torch.bool), "dtype torch.bool"),
                           (torch.zeros(2, 4, 2, dtype=torch.complex64), "dtype torch.complex64"),
                           (None, "actions: got None"), (torch.full((2, 4, 2), float("nan")), r"actions\[0, 0\]: got "
                                                        "non-finite"),
                           (torch.tensor([0.0, 3e38]).repeat(2, 4, 1), r"actions\[0, 0\]: got .* a nominal within")):
        with pytest.raises(ActionError, match=match):
            env.step(actions)
    bare = make_tensor_env("random_goals", 2, 4, filter=False)
    bare.reset(seed=0)
    with pytest.raises(ActionError, match=r"actions\[1, 2\]: got \[1.5, 0.0\], expected values in \[-1, 1\]"):
        bare.step(torch.zeros(2, 4, 2).index_put_((torch.tensor(1), torch.tensor(2), torch.tensor(0)),
                                                 torch.tensor(1.5)))
    with pytest.raises(ConfigError, match=r"done: got a torch.bool tensor of shape \(2, 4\), expected bool of shape"):
        bare.reset_done(torch.ones(2, 4, dtype=torch.bool))


def test_the_filter_refuses_inputs_the_numpy_filter_refuses_naming_them():
    """``filter_step``: a NaN, infinite or huge (beyond 1e9) number, a negative obstacle radius, a shape off the
    team's ``(B, N, .)``, an input that is not a real tensor or is on another device than the team's get a
    :class:`StateError` naming the input and the entry, as ``SafetyFilter.step`` does; a layer of another dtype or
    mode than it has, or on the data-less 'meta' device, is refused."""
    from aasoatt_env.errors import ConfigError, StateError

    rng = np.random.default_rng(2)
    states = random_states(rng, 3, 4)
    team = make_team("paper", 4)
    cfg = FilterConfig(mode="decentralized")
    out = tensor_answers(team, states, cfg)
    assert torch.isfinite(out.du).all()
    for key, k, value, match in (("nom", 2, np.nan, r"nominal: got \[nan, nan\] for team 1, robot 2"),
                                 ("nom", 2, 1e30, r"nominal: got \[1e\+30, 1e\+30\] for team 1, robot 2"),
                                 ("pose", 2, np.inf, r"pose: got \[inf, inf, inf\] for team 1, robot 2"),
                                 ("orad", 1, np.nan, r"obstacles radii: got nan for team 1, obstacle 1"),
                                 ("orad", 1, -1.3, r"obstacles radii: got -1.3 for team 1, obstacle 1, expected a "
                                                   "radius >= 0")):
        bad = [dict(s) for s in states]
        bad[1][key] = bad[1][key].copy()
        bad[1][key][k] = value
        with pytest.raises(StateError, match=match):
            tensor_answers(team, bad, cfg)
    with pytest.raises(StateError, match=r"pose: got shape \(3, 4, 3\), expected \(3, 5, 3\)"):
        tensor_answers(make_team("paper", 5), states, cfg)
    layer = SafetyLayer(team, cfg)
    args = [torch.as_tensor(np.stack([s[k] for s in states])) for k in ("pose", "u", "nom", "pd", "vd")]
    with pytest.raises(StateError, match="v_d: got array"):
        layer(*args[:4], args[4].numpy())
    with pytest.raises(StateError, match="nominal: got a tensor on meta, expected the team's device cpu"):
        layer(*args[:2], args[2].to("meta"), *args[3:])
    with pytest.raises(StateError, match=r"avoiding: got a torch.float32 tensor of shape \(3, 4\) on cpu, expected a "
                       r"torch.bool tensor of shape \(3, 4\) on cpu"):
        layer(*args, avoiding=torch.zeros(3, 4))
    with pytest.raises(StateError, match=r"avoiding: got a torch.bool tensor of shape \(3, 4\) on meta"):
        layer(*args, avoiding=torch.zeros(3, 4, dtype=torch.bool, device="meta"))
    for kwargs, match in ((dict(dtype=torch.int64), "dtype: got torch.int64"), (dict(device="bogus"), "device: got"),
                          (dict(device="meta"), "device: got 'meta', expected a device whose tensors hold values"),
                          (dict(config=FilterConfig(mode="centralized")), "mode: got 'centralized'"),
                          (dict(config={"mode": "decentralized"}, mode="centralized"), "mode: got 'centralized', "
                           "but the filter's configuration says 'decentralized'")):
        with pytest.raises(ConfigError, match=match):
            SafetyLayer(team, **kwargs)


def test_settings_the_env_shares_with_the_filter_reach_it():
    """The env's ``dt`` is the filter's; the filter's own settings (its sensing range) come through ``filter``; a
    clipping bare env clips; a scenario of fixed size builds with its own number of robots."""
    from aasoatt_env.tensor.env import make_tensor_env

    env = make_tensor_env("random_goals", 1, 4, dt=0.01, sensing_range=1.0, filter={"sensing_range": 2.0})
    assert env.dt == env.config.dt == 0.01 and env.sensing_range == 1.0 and env.config.sensing_range == 2.0
    bare = make_tensor_env("random_goals", 1, 4, filter=False, clip_actions=True)
    bare.reset(seed=0)
    u0 = bare.u.clone()
    bare.step(torch.full((1, 4, 2), 5.0))
    wheel = bare.team.max_wheel_accel
    assert torch.allclose(bare.u - u0, (wheel * bare.dt).expand(1, 4)[..., None].expand(1, 4, 2))
    swap = make_tensor_env("position_swap", 1)
    assert swap.reset(seed=0)[0].shape[:2] == (1, 4)


def test_layouts_the_float32_guarantee_does_not_cover_are_refused():
    """A layout 1e5 m from the origin: refused in float32 (positions 8 mm apart there), accepted in float64; starts
    that overlap are refused as by the PettingZoo env."""
    from aasoatt_env.errors import ConfigError, ScenarioError
    from aasoatt_env.sim.references import LinearReference
    from aasoatt_env.sim.scenarios import get_scenario
    from aasoatt_env.tensor.env import make_tensor_env

    def custom(x: float, gap: float):
        starts = np.array([[x, x], [x + gap, x]])
        return get_scenario("custom", starts=starts, reference=LinearReference(starts, starts[::-1].copy(), 5.0))

    with pytest.raises(ConfigError, match=r"dtype: got torch.float32 for a layout reaching 100003 m"):
        make_tensor_env(custom(1e5, 3.0), 1).reset(seed=0)
    assert make_tensor_env(custom(1e5, 3.0), 1, dtype=torch.float64).reset(seed=0)[0].isfinite().all()
    with pytest.raises(ScenarioError, match="starts: robots 0 and 1 overlap"):
        make_tensor_env(custom(0.0, 0.1), 1).reset(seed=0)


@pytest.mark.parametrize("scenario, kwargs", [("random_goals", dict(random_obstacles=3)), ("circle_swap", {})])
def test_team_b_after_reset_seed_s_is_the_pettingzoo_layout_of_seed_s_plus_b(scenario, kwargs):
    from aasoatt_env.sim.env import AASOATTParallelEnv
    from aasoatt_env.tensor.env import make_tensor_env

    env = make_tensor_env(scenario, 3, 6, dtype=torch.float64, **kwargs)
    obs, _ = env.reset(seed=10)
    for b in range(3):
        ref = AASOATTParallelEnv(scenario, num_robots=6, **kwargs)
        o, _ = ref.reset(seed=10 + b)
        assert np.array_equal(env.kin.p[b].numpy(), ref.positions)
        assert np.array_equal(env._st["goals"][b].numpy(), ref.goals)
        assert np.array_equal(env._st["oc"][b].numpy(), ref.obstacles[0])
        assert np.array_equal(obs[b].numpy(), np.stack([o[a] for a in ref.possible_agents]))


def test_torchrl_mappo_runs_one_iteration_and_reports_held_out_teams(tmp_path):
    """``train.torchrl_mappo``: one PPO iteration on two 3-robot teams changes the policy and reports finite
    rewards and held-out success/collisions; the command refuses to overwrite its report."""
    pytest.importorskip("torchrl", reason="torchrl is not installed (it is in the dev extra)")
    from train import torchrl_mappo

    report = torchrl_mappo.train(100, 2, 3, 0, True, eval_every=1, eval_teams=2, log=lambda *_: None, steps=50,
                                 max_steps=10)
    assert report["policy_change"] > 0.0
    assert [r["frames"] for r in report["iterations"]] == [100]
    assert math.isfinite(report["iterations"][0]["mean_reward"])
    last = report["evaluations"][-1]
    assert 0.0 <= last["success"] <= 1.0 and last["robots_collided"] == 0 and last["teams"] == 2
    out = tmp_path / "run"
    out.mkdir()
    (out / "report.json").write_text("{}")
    with pytest.raises(SystemExit):
        torchrl_mappo.main(["--frames", "100", "--out", str(out)])
    with pytest.raises(SystemExit):  # (a file: refused before training)
        torchrl_mappo.main(["--frames", "100", "--out", str(out / "report.json")])


def _stiff_aasoatt(g, q):
    """A user's barrier: eqn.7-8 with a margin on the right-hand side, written with the inputs' namespace."""
    from aasoatt_env.model.geometry import namespace

    rhs, keep = barriers.BARRIERS["aasoatt"].rows(g, q)
    return rhs - 0.5 * namespace(rhs).abs(rhs), keep


@pytest.mark.parametrize("barrier", ["braking", "distance", "gated_distance", "adaptive_distance", "user"])
def test_every_registered_barrier_equals_the_numpy_filter(barrier, monkeypatch):
    """The other registered barriers' rows (eqn.n4, nn5, n5/n6 with its gate, n7, and one a user registers with
    ``array_api=True``), one source for both: the numpy decentralised filter's ``du`` to 1e-9 where it answers by
    the robots' own QPs, to 1e-6 where it relaxed (flagged ``RELAXED``)."""
    if barrier == "user":
        monkeypatch.setitem(barriers.BARRIERS, "user", barriers.Barrier(
            _stiff_aasoatt, barriers.BARRIERS["aasoatt"].value, "test", array_api=True))
    rng = np.random.default_rng(2)
    n = 8
    states = random_states(rng, 300, n)
    cfg = FilterConfig(mode="decentralized", backup=False, negotiate=False, kernel="numpy", barrier=barrier)
    team, ref = numpy_answers(states, cfg, n)
    out = tensor_answers(team, states, cfg)
    du, ref_du = out.du.numpy(), np.stack([r.du for r in ref])
    solved = np.array([r.status == "solved" for r in ref])
    assert solved.sum() >= 10 and np.stack([r.intervened for r in ref])[solved].mean() > 0.1
    assert np.abs(du[solved] - ref_du[solved]).max() <= 1e-9
    differs = (np.abs(du - ref_du).max(axis=2) > 1e-9) & ~solved[:, None]
    assert (out.status.numpy()[differs] & RELAXED).all() and np.abs(du - ref_du).max() <= 1e-6


@pytest.mark.parametrize("compiled", [False, True])
def test_a_decision_of_several_physics_steps_is_reported_over_all_of_them_as_by_the_pettingzoo_env(compiled):
    """``decision_interval > 1``: the clearance (so the reward's collision term) is the least over the decision's
    physics steps and ``intervened`` any of them, as the PettingZoo env's, by the torch or the compiled stages: four
    bare circle_swap robots driven through each other within 1 s decisions (apart again at their ends); a filtered
    team's flags at 100 ms."""
    from aasoatt_env.sim.env import AASOATTParallelEnv
    from aasoatt_env.tensor.env import make_tensor_env

    def pair(filt, **kw):
        tenv = make_tensor_env("circle_swap", 1, 4, dtype=torch.float64, radius=2.0, action_mode="point",
                               filter=filt and dict(backup=False, negotiate=False), compiled=compiled, **kw)
        tenv.reset(seed=0)
        e = AASOATTParallelEnv("circle_swap", num_robots=4, radius=2.0, action_mode="point", **kw)
        if filt:
            e.set_control_filter(SafetyFilter(mode="decentralized", kernel="numpy", backup=False, negotiate=False))
        e.reset(seed=0)
        return tenv, e

    for filt, kw in ((False, dict(decision_interval=200, max_steps=10)), (True, dict(decision_interval=20))):
        tenv, e = pair(filt, **kw)
        collided = hit = 0
        for _ in range(8):
            act = torch.clamp(2.0 * (tenv.ref[0] - tenv.kin.p) + 4.0 * (tenv.ref[1] - tenv.kin.v), -1.0, 1.0)
            _, rew, _, _, info = tenv.step(act)
            _, r, _, _, i = e.step({a: act[0, k].numpy() for k, a in enumerate(e.possible_agents)})
            assert np.abs(np.array(list(r.values())) - rew[0].numpy()).max() <= 1e-9
            assert np.abs(np.array([v["clearance"] for v in i.values()]) - info["clearance"][0].numpy()).max() <= 1e-9
            collided += int((info["clearance"] < -1e-3).sum())
            if filt:
                flags = np.any([o.intervened for o in e.filter_outputs], axis=0)
                assert np.array_equal(flags, info["intervened"][0].numpy())
                hit += int((flags & ~e.filter_outputs[-1].intervened).sum())
        assert collided > 0 if not filt else hit > 0


def test_the_surface_gap_has_a_finite_gradient_where_rows_are_padded_or_lengths_are_zero():
    """``FilterOut.gap``: a robot with fewer robots in range than another (its table padded, here with itself), two
    robots at one point and a robot on an obstacle's centre give finite gradients w.r.t. the poses, not NaN."""
    team = make_team("paper", 3)
    layer = SafetyLayer(team, backup=False, negotiate=False)
    for p, obstacles in ((np.array([[10.0, 0.0], [0.0, 0.0], [1.0, 0.0]]), None),
                         (np.array([[0.0, 0.0], [0.0, 0.0], [1.5, 0.0]]), None),
                         (np.array([[0.0, 0.0], [5.0, 0.0], [9.0, 0.0]]),
                          (torch.zeros(1, 1, 2, dtype=torch.float64), torch.zeros(1, 1, dtype=torch.float64)))):
        pose = torch.tensor(dynamics.pose_from_point(team, p, np.zeros(3)))[None].requires_grad_()
        zeros = torch.zeros(1, 3, 2, dtype=torch.float64)
        out = filter_step(layer.team, layer.config, pose, zeros, zeros + 5.0, torch.tensor(p)[None], zeros, obstacles)
        (g,) = torch.autograd.grad(out.gap.sum(), pose)
        assert torch.isfinite(g).all() and torch.isfinite(out.gap).all()


@pytest.mark.parametrize("flag, value", [("--frames", "-4"), ("--frames", "0"), ("--teams", "0"), ("--steps", "0"),
                                         ("--minibatches", "0"), ("--eval-every", "0"), ("--epochs", "-1"),
                                         ("--seed", "-1"), ("--robots", "0")])
def test_torchrl_mappo_refuses_counts_below_one_naming_the_flag(flag, value, capsys, tmp_path):
    """Refused by the parser, naming the flag, before any work."""
    pytest.importorskip("torchrl", reason="torchrl is not installed (it is in the dev extra)")
    from train import torchrl_mappo

    with pytest.raises(SystemExit):
        torchrl_mappo.main([flag, value, "--out", str(tmp_path)])
    assert f"argument {flag}: got {value}, expected an integer >=" in capsys.readouterr().err


def test_a_finished_team_is_not_stepped_on_and_torchrl_mappo_measures_each_team_at_its_own_end():
    """``autoreset=False``: stepping a team whose episode ended raises ``ResetNeeded`` naming it (as the numpy batched
    env). ``torchrl_mappo.evaluate`` of held-out teams whose episodes end at different decisions (19 and 22) measures
    success and the mean correction of each team over its own episode, as counted here by hand."""
    pytest.importorskip("torchrl", reason="torchrl is not installed (it is in the dev extra)")
    from tensordict.nn import TensorDictModule

    from aasoatt_env.errors import ResetNeeded
    from aasoatt_env.tensor.env import make_tensor_env
    from train import torchrl_mappo
    from train.torchrl_mappo import GROUP, HELDOUT_SEED

    short = make_tensor_env("random_goals", 3, 2, filter=False, max_steps=2)
    short.autoreset = False
    short.reset(seed=0)
    short.step(torch.zeros(3, 2, 2))
    short.reset_done(torch.tensor([True, False, False]))
    assert short.step(torch.zeros(3, 2, 2))[3].tolist() == [[False] * 2, [True] * 2, [True] * 2]
    with pytest.raises(ResetNeeded, match=r"step\(\): team\(s\) \[1, 2\] finished their episode \(autoreset=False\)"):
        short.step(torch.zeros(3, 2, 2))

    quick = dict(speed=3.0, settle_time=0.6)
    env = torchrl_mappo.make_env(3, 2, HELDOUT_SEED, **quick)
    td = env.reset()
    scale = env.env.team.max_point_accel[:, None]

    class Track(torch.nn.Module):  # the paper's law (k3 = 1, k4 = 4) from the observation, in units of the bound
        def forward(self, o):
            return (o[..., 12:14] + 4.0 * (o[..., 10:12] - o[..., 4:6]) - o[..., 0:2]) / scale.to(o.dtype)

    actor = TensorDictModule(Track(), in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "action")])
    ends = env.env._st["max_steps"].tolist()
    assert ends == [22, 19, 22]
    home, corr = [], []
    for k in range(max(ends)):
        td = env.step(actor(td))["next"]
        corr += [float(c) for b in range(3) if k < ends[b] for c in td[GROUP, "correction"][b]]
        home += [bool(d < env.env.reward_config.goal_tolerance) for b in range(3) if k + 1 == ends[b]
                 for d in torch.linalg.norm(env.env.kin.p[b] - env.env.goals[b], dim=-1)]
        if bool(td["done"].any()) and k + 1 < max(ends):
            td = env.reset(td.set("_reset", td["done"].clone()))
    report = torchrl_mappo.evaluate(actor, 3, 2, **quick)
    assert report["teams"] == 3 and report["robots_collided"] == 0 and 0 < sum(home) < 6
    assert report["success"] == pytest.approx(sum(home) / 6, abs=1e-7)
    assert report["correction"] == pytest.approx(sum(corr) / len(corr), rel=1e-7)


def test_torchrl_mappo_reports_the_librarys_errors_in_one_line(capsys, tmp_path):
    """A value the library refuses (a team too large) is one line and exit status 2, not a traceback."""
    pytest.importorskip("torchrl", reason="torchrl is not installed (it is in the dev extra)")
    from train import torchrl_mappo

    assert torchrl_mappo.main(["--robots", "200000", "--frames", "64", "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert err.strip() == ("python -m train.torchrl_mappo: error: num_robots: got 200000, expected an integer in "
                           "[1, 100000]")


def test_the_compiled_stages_observe_large_teams_within_their_own_team():
    """Two random_goals teams of 210 robots (past the brute-force neighbour search: a tree per team) by the compiled
    and the torch stages, float64: the same observations and clearance after reset and 3 bare steps."""
    from aasoatt_env.tensor.env import make_tensor_env

    envs = [make_tensor_env("random_goals", 2, 210, dtype=torch.float64, filter=False, compiled=c)
            for c in (False, True)]
    outs = [e.reset(seed=3)[0] for e in envs]
    assert torch.allclose(outs[0], outs[1], atol=1e-5, rtol=0)
    for _ in range(3):
        got = [e.step(torch.full((2, 210, 2), 0.5, dtype=torch.float64)) for e in envs]
        assert torch.allclose(got[0][0], got[1][0], atol=1e-5, rtol=0)
        assert torch.allclose(got[0][4]["clearance"], got[1][4]["clearance"], atol=1e-9, rtol=0)
