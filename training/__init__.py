"""Training side of the project (never shipped in the extension): the synthetic light stage,
lighting sampling, the dataset, the network, losses, training, export and evaluation."""
