"""The synthetic dynamic light stage: ICT-FaceKit heads with hair, torso and materials, animated at
25 fps, rasterised to G-buffers and shaded one light at a time for a 114-light stage.

Modules: assets (head model, hair shell, torso, labels), subject (identities, performances,
camera), geometry (posing, G-buffer, exact flow), raster (torch z-buffer), materials (skin and
other surfaces), shading (shadows, GGX, hair, subsurface), layout (the 114 lights), scene (one
subject and camera: frames and shading), png (picture output).
"""
