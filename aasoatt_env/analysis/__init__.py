"""The analysis layer: recorded episodes (rollout, recording), their metrics and plots."""
