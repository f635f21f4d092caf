"""The paper's network: the encoder-decoder, its losses, and the flow warping of the temporal
loss."""
