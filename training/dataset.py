"""training.data.dataset under its former name, for training/intrinsic/data.py, which still
imports these names from here. Nothing else should: import training.data.dataset."""

from .data.dataset import SPLITS, LightStageDataset, renderer_version

__all__ = ["SPLITS", "LightStageDataset", "renderer_version"]
