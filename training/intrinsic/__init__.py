"""The intrinsic model: buffers supervised by the light stage, relit by the renderer in addon/."""
