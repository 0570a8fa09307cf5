"""Training engine: the one loop (``trainer``), checkpoints (``checkpoint``) and seeding (``seeding``)."""
from .trainer import TrainConfig, TrainingDiverged, train

__all__ = ["TrainConfig", "TrainingDiverged", "train"]
