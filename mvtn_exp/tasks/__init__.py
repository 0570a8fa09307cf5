"""Task heads and their metrics: classification, retrieval, robustness."""
