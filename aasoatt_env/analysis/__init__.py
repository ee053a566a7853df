"""The analysis layer: rollouts, recording, metrics and plots.

:mod:`~aasoatt_env.analysis.rollout` (recorded episodes), :mod:`~aasoatt_env.analysis.recording`
(recording an env), :mod:`~aasoatt_env.analysis.metrics` and :mod:`~aasoatt_env.analysis.plotting`.
"""
