"""Staged training (VAE, then flow), its objectives, loop, data order, checkpoints and DDP."""
