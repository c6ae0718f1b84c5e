"""The training parts: the interface the trainer calls (:mod:`splat_train.parts.base`), the parts
(dropout, depth prior, regularisers, binocular consistency, opacity decay, pose refinement), their
configs and registry (:mod:`splat_train.parts.configs`, light: no torch) and a run's list of them
(:mod:`splat_train.parts.compose`)."""
