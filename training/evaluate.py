"""training.eval's evaluation under its former name, for training/intrinsic/export.py, which still
imports these names from here. Nothing else should: import training.eval.evaluate (the protocol),
training.eval.metrics or training.eval.predictors."""

from .eval.evaluate import card_metrics, heldout_dataset
from .eval.predictors import product_predictor

__all__ = ["card_metrics", "heldout_dataset", "product_predictor"]

if __name__ == "__main__":
    raise SystemExit("training.evaluate is now: python -m training.eval.evaluate")
