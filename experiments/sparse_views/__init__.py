"""Sparse-view training benchmark: tuning scenes and evaluation scenes kept apart.

The protocol file ``experiments/sparse_views/scenes.yaml`` names every scene with its role:
*tuning* scenes are the only ones on which a recipe's values may be chosen; *evaluation*
scenes are run once the values are frozen, and the table reports them. Every cell is the
LLFF sparse-view protocol (docs/protocols.md): every 8th image held out, n training views spread
over the rest, reference cameras for all images, seed points triangulated from the n training
views only (the ``posed`` initialiser), so that the recipes are compared on training alone.

    python -m experiments.sparse_views run --role tuning --recipes paper sparse --seeds 0 1 2
    python -m experiments.sparse_views run --role evaluation --iterations 3000
    python -m experiments.sparse_views summary        # records -> summary.json + docs/results tables

Each run writes one record (``experiments/records/sparse_views/runs/*.json``); ``summary``
rebuilds ``experiments/records/sparse_views/summary.json`` and ``docs/results-sparse-views.md``
from whatever records exist, so the table is regenerated, never edited.
"""
