"""Benchmarks printing one JSON object each (``scmbridge bench ...``). Speed targets live here, not in tests."""
