"""Finished runs and sweeps read back: one reader of run folders, one definition of a setting, and the comparisons, reports and fronts built on them."""
