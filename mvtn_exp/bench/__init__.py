"""Benchmarks of the renderer: speed and extra peak memory (``mvtn-bench``, see ``mvtn_exp.cli.bench``).

* ``runtime.memory.PeakMemory`` (used here): extra peak memory of a block (CUDA allocator stats, or sampled RSS on CPU).
* ``dense``: a brute-force dense K=1 face search, the timing reference for ``search_faces``.
* ``render_bench``: the benchmark grid; ``scenes`` (its tori, point clouds and renderers), ``timing``
  (its clocks), ``render_report`` (targets, Markdown tables and raw JSON); ``modules`` (the paper's
  module table), ``scaling`` (curves), ``edge_error`` (soft edges against the every-face reference).
* ``step_ratio``: learned against fixed views per training step; ``loader_bench``: data loading.

The research probes behind ``docs/results`` (axis views, the view landscape, camera-gradient
quality, ``prob_cutoff``) live in ``scripts/studies/``.
"""
