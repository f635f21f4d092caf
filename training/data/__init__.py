"""The training data: light-stage samples, the paper's lighting sampling, the frame cache, the fixed
test set and the demo clip."""
