"""training.data.lighting_sampling under its former name, for training/intrinsic/data.py, which
still imports it from here. Nothing else should: import training.data.lighting_sampling."""

from .data.lighting_sampling import environment_bank, hdri_pool, sample_g, sample_h

__all__ = ["environment_bank", "hdri_pool", "sample_g", "sample_h"]
