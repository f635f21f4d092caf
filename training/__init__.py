"""Training side of the project (never shipped in the extension): the synthetic light stage
(lightstage/), the samples (data/), the network and its losses (model/), training, export and
reproduction (run/), evaluation (eval/) and the Portrait preset's model (intrinsic/)."""
