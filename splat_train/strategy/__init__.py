"""How the model grows: the strategy interface (:mod:`splat_train.strategy.base`), the strategies
(:mod:`splat_train.strategy.densify`, 3DGS's clone / split / prune; :mod:`splat_train.strategy.mcmc`,
relocation under a cap) and their configs (:mod:`splat_train.strategy.configs`, light: no torch)."""
