"""User-facing tools behind scripts/: demo orchestration, benchmarks, evaluation."""
