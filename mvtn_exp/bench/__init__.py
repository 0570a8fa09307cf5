"""Benchmarks of the renderer: speed and extra peak memory (``mvtn-bench``, see ``mvtn_exp.cli.bench``).

* ``memory.PeakMemory``: extra peak memory of a block (CUDA allocator stats, or sampled RSS on CPU).
* ``dense``: a brute-force dense K=1 face search, the timing reference for ``search_faces``.
* ``render_bench``: the benchmark grid, Markdown tables and raw JSON.
* ``grad_quality``: camera gradients (autograd) against central finite differences, per renderer
  setting, and near the pole (``python -m mvtn_exp.bench.grad_quality``).
"""
