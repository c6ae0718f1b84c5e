"""splat_train package."""
