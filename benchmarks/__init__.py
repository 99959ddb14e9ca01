"""The benchmarks: ``python -m benchmarks <subcommand>`` (``--help`` lists them); results in ``benchmarks/results``."""
