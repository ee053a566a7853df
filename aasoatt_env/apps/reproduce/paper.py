"""The paper's published numbers (Sec. V), from its LaTeX source, keyed by the equation labels of the methods."""

from __future__ import annotations

__all__ = ["COMPARE_CA", "METRICS", "TABLE1", "TABLE2", "TABLE2_VIOLATED", "TABLE3"]

#: The four invasiveness metrics, in the paper's order.
METRICS: tuple[str, ...] = ("intervention_time", "rmse", "mae", "std")


def _rows(metrics: tuple[str, ...], rows: dict[str, tuple[float, ...]]) -> dict[str, dict[str, float]]:
    return {key: dict(zip(metrics, values)) for key, values in rows.items()}


_T1 = ("rmse", "mae", "std")

#: Table I, single-robot tracking: ``TABLE1[trajectory][controller] = {"rmse", "mae", "std"}``.
TABLE1: dict[str, dict[str, dict[str, float]]] = {
    "straight": _rows(_T1, {"SBC k3=10": (0.2000, 0.1987, 0.0230), "SBC k3=80": (0.0259, 0.0254, 0.0051),
                            "ours k3=1": (0.0267, 0.0203, 0.0173)}),
    "sine": _rows(_T1, {"SBC k3=10": (0.4923, 0.4857, 0.0799), "SBC k3=80": (0.0657, 0.0629, 0.0191),
                        "ours k3=1": (0.0640, 0.0372, 0.0521)}),
    "circle": _rows(_T1, {"SBC k3=10": (0.4108, 0.4056, 0.0651), "SBC k3=80": (0.0568, 0.0549, 0.0144),
                          "ours k3=1": (0.0619, 0.0404, 0.0468)}),
}

#: The inline 4-tuples of "Comparison of CA strategies" (N = 10, radius 6, 12 s), per method.
COMPARE_CA: dict[str, dict[str, float]] = _rows(METRICS, {
    "eqn.n4": (4.3500, 0.7689, 0.4810, 0.5998), "ours": (4.4850, 0.7888, 0.4982, 0.6115),
    "eqn.n5": (4.5300, 0.7062, 0.3820, 0.5940), "eqn.nn5": (4.5500, 0.8257, 0.4683, 0.6801),
    "eqn.n7": (10.4150, 2.7623, 2.2492, 1.6036)})

_T2_N = (20, 25, 30, 35, 39)

#: Table II (N = 20..39, radius 6, 12 s): ``TABLE2[method][metric][N]``; None where the paper prints "-".
TABLE2: dict[str, dict[str, dict[int, float | None]]] = {
    "eqn.n4": {"rmse": dict(zip(_T2_N, (1.1983, 1.3005, 1.4055, None, None))),
               "mae": dict(zip(_T2_N, (0.8465, 0.9709, 1.1026, None, None))),
               "std": dict(zip(_T2_N, (0.8482, 0.8653, 0.8717, None, None))),
               "intervention_time": dict(zip(_T2_N, (7.4650, 8.5150, 10.1200, None, None)))},
    "ours": {"rmse": dict(zip(_T2_N, (1.1407, 1.2988, 1.4381, 2.0293, 2.9324))),
             "mae": dict(zip(_T2_N, (0.8092, 0.9730, 1.1288, 1.6680, 2.5260))),
             "std": dict(zip(_T2_N, (0.8040, 0.8604, 0.8910, 1.1558, 1.4894))),
             "intervention_time": dict(zip(_T2_N, (7.2850, 8.8250, 10.0150, 11.3900, 11.9900)))},
}

#: Table II's footnote: the N for which the paper reports a safety violation, per method.
TABLE2_VIOLATED: dict[str, tuple[int, ...]] = {"eqn.n4": (35, 39), "ours": ()}

#: Table III (N = 20..60, radius 10, 20 s): ``TABLE3[N][strategy] = {"intervention_time", "rmse", "mae", "std"}``.
TABLE3: dict[int, dict[str, dict[str, float]]] = {n: _rows(METRICS, row) for n, row in {
    20: {"eqn.12a": (6.9450, 0.7805, 0.4277, 0.6529), "eqn.12b": (7.1750, 1.0364, 0.6204, 0.8302),
         "eqn.13": (7.4600, 0.8699, 0.4831, 0.7234)},
    30: {"eqn.12a": (11.1500, 0.9713, 0.6034, 0.7612), "eqn.12b": (10.1450, 1.2187, 0.8450, 0.8782),
         "eqn.13": (10.0800, 1.0462, 0.6448, 0.8238)},
    40: {"eqn.12a": (14.9750, 1.1155, 0.7701, 0.8070), "eqn.12b": (13.0900, 1.3643, 1.0416, 0.8812),
         "eqn.13": (13.0300, 1.2061, 0.8009, 0.9017)},
    50: {"eqn.12a": (18.6800, 1.2439, 0.9239, 0.8329), "eqn.12b": (16.3650, 1.5311, 1.2674, 0.8591),
         "eqn.13": (16.7950, 1.3076, 0.9172, 0.9320)},
    60: {"eqn.12a": (19.7400, 1.4536, 1.1483, 0.8914), "eqn.12b": (19.3350, 1.8085, 1.5748, 0.8891),
         "eqn.13": (18.6150, 1.4795, 1.1080, 0.9804)},
}.items()}
