"""hybridpgo benchmarks: ``python -m benchmarks --help`` (docs/contributing.md#benchmarks)."""
