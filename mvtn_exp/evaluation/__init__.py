"""mvtn-eval: a checkpoint's model evaluated on the test split, with rotation, occlusion and retrieval modes."""
