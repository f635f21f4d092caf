"""Runs: training a network (``python -m training.run.train``), exporting it to ONNX with its model
card (``training.run.export``) and reproducing a shipped model from its card
(``training.run.reproduce``)."""
