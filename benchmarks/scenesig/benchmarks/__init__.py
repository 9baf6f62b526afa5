"""Benchmark scripts, one module each with ``main(argv) -> int`` printing JSON (as scikit-learn keeps them).

Run them as ``scenesig bench NAME ARGS...`` (the registry is :data:`scenesig.commands.bench.BENCHMARKS`).
Benchmarks may import any package; nothing imports ``benchmarks``.
"""
