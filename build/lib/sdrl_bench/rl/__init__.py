"""Agents trained with stable-baselines3, judged in the real env: training, evaluation, the
transfer orchestration (both arms, real-arm reuse), experts and policy maps."""
