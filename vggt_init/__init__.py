"""vggt_init package."""
