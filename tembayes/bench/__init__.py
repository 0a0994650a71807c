"""The virtual bench: synthetic batches with known truth for development, tests and benchmarks."""

from tembayes.bench.bench import TEC1_12706, BenchConfig, draw_truth, run_experiment, simulate_batch

__all__ = ["TEC1_12706", "BenchConfig", "draw_truth", "run_experiment", "simulate_batch"]
