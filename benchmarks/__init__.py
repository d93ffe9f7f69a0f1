"""hybridpgo benchmarks: ``python -m benchmarks --help`` (STYLE.md §8)."""
