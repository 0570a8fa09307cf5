"""Shapes and datasets: containers, readers, caches, the embedded synthetic datasets and collation."""
