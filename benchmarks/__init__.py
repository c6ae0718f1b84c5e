"""Benchmarks: ``python -m benchmarks`` runs them all and prints one table.

Modules: bench_rasterizer (fast CPU rasterizer vs the dense reference), bench_vggt (VGGT-1B
fp32 vs bf16 with random weights, speed/memory only), bench_cell (one pipeline cell's stage
breakdown), and the aggregator in ``__main__`` (JSON with commit and machine, ``--compare``).
See benchmarks/README.md.
"""
