"""Task heads and their metrics (classification now; retrieval and robustness later)."""
