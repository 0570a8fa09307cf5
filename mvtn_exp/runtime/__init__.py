"""What every process of a run stands on: the distributed world, seeds, peak memory, and checkpoint files."""
