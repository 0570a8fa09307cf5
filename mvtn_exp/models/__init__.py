"""The multi-view networks C, their backbones, the point encoders of G, and C's training helpers."""
