"""Browser viewer for trained models: ``python -m splat_train view`` (see :mod:`.server`).

The page renders with Spark (``@sparkjsdev/spark``) on three.js, installed by
``scripts/install.sh`` with npm into ``splat_train/view/npm/node_modules`` (git-ignored, pinned by
the committed ``package.json`` and ``package-lock.json``); nothing is fetched from a CDN.
"""
