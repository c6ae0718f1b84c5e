"""Experiments: studies of quality (held-out PSNR, SSIM, LPIPS, depth accuracy) and the page of
current results. Speed and memory are measured in ``benchmarks/``. See experiments/README.md.

Run from the clone (not shipped by ``pip install``):

    python -m experiments.sparse_views ...    # the sparse-view grid: recipes and seeds on held-apart scenes
    python -m experiments.results_doc         # docs/results.md from the records
"""
