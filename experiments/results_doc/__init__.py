"""docs/results.md, generated from the studies' records under ``experiments/records/`` and the
GPU benchmarks' under ``benchmarks/records/``.

    python -m experiments.results_doc [--doc docs/results.md] [--records experiments/records]
        [--bench-records benchmarks/records]

One renderer per section (:mod:`experiments.results_doc.sections`), in the fixed order of
:data:`SECTIONS`: a heading, the figures from the section's records, the command that makes
them, a few lines of fixed text. A section whose record is missing is left out and named with
its command at the end of the page (:mod:`experiments.results_doc.page`), as are the figures no
record holds. ``tests/test_results_doc.py`` regenerates the page and compares it with the
committed one, so the page cannot drift from the records.
"""

from __future__ import annotations

from experiments.results_doc import sections as S
from experiments.results_doc.page import BENCH_RECORDS, DOC, RECORDS, Section, render_page

__all__ = ["SECTIONS", "render_page", "DOC", "RECORDS", "BENCH_RECORDS"]


def _seed_command(name: str):
    return lambda records: S._registration(name, records)[1]


SECTIONS = (
    Section("Training recipes on scenes they were not tuned on (`docs/results-sparse-views.md`)",
            "`python -m experiments.sparse_views run --role evaluation --work WORK`, "
            "`python -m experiments.sparse_views floor --work WORK`, then `python -m experiments.sparse_views summary`",
            S.SUMMARY, S.sparse_views),
    Section("The default recipe against 3DGS as released, on captures measured before",
            _seed_command("baselines_released"), "baselines_released/baselines_released.json", S.baselines_released),
    Section("The default recipe against DropGaussian and 3DGS-MCMC as released, on captures measured before",
            _seed_command("released_dropgaussian_mcmc"), "released_dropgaussian_mcmc/released_dropgaussian_mcmc.json",
            S.released_dropgaussian_mcmc),
    Section("Dense seeds from multi-view stereo (`mvs`) on unseen captures",
            _seed_command("mvs_fill_seed"), "mvs_fill_seed/mvs_fill_seed.json", S.mvs_fill_seed),
    Section("Dense seeds from multi-view stereo, before the fill, on the evaluation scenes",
            _seed_command("mvs_seed"), "sparse_views/mvs_seed.json", S.mvs_seed),
    Section("The dense seed's fill and Bridge stride, on tuning scenes",
            "`python -m experiments.sparse_views --records experiments/records/mvs_tuning run --role tuning "
            "--scenes llff__horns tnt__Train --n 3 --seeds 0 --iterations 3000 --work WORK --recipes VARIANTS`, each "
            "variant `NAME='{\"recipe\": \"paper-seedcode\", ...}'` as its record's config holds it",
            S.MVS_TUNING_RUNS + "/", S.mvs_tuning),
    Section("The field's LLFF 3-view protocol", S.llff_command, S.LLFF_RUNS + "/", S.llff_protocol),
    Section("Both evaluation protocols (`docs/protocols.md`)",
            "`snakemake --cores 2 --configfile config/protocols_fern.yaml`, or on a GPU machine "
            "`python experiments/protocols.py prepare DEST` then `python experiments/protocols.py run DEST --out OUT "
            "--device cuda`", S.PROTOCOLS, S.protocols),
    Section("On one GPU", "`python -m benchmarks --gpu`, or `bash scripts/gpu_run.sh OUT_DIR`", S.GPU, S.gpu, bench=True),
    Section("Do the backends train to the same result?",
            "`python -m benchmarks.backend_semantics --cell W/llff__fern_n3 --variants visibility clamp999 "
            "clamp999+op --seeds $(seq 0 14) --recipe sparse --out backend_semantics.json`",
            S.SEMANTICS, S.backends, bench=True),
    Section("VGGT at many frames on one GPU",
            "`python benchmarks/vggt_frames.py --minutes 10 --out vggt_frames.json` on a CUDA machine; the search "
            "alone: `python -m benchmarks --gpu --gpu-parts vggt_search`", S.GPU, S.vggt, bench=True),
    Section("Robustness (`docs/robustness.md`)",
            "`python -m pytest -q tests/test_robustness_catalogue.py` and the tests the catalogue names",
            "", S.robustness),
)
