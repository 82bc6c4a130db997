"""Generation from a trained run: inputs (shard window or raw files) -> motion.npz + pictures."""
