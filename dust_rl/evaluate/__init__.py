"""Closed-loop evaluation: ``dust-rl eval`` (:mod:`.closed_loop`), its report and rollout videos."""

from dust_rl.evaluate.closed_loop import EvalConfig, evaluate

__all__ = ["EvalConfig", "evaluate"]
