"""The one training loop and a run's state: counters, checkpoint payload, run folder, logging, cost records."""
from .trainer import TrainConfig, TrainingDiverged, train

__all__ = ["TrainConfig", "TrainingDiverged", "train"]
