"""Every colour space Blender offers a strip is converted to scene light, with the OpenColorIO
configuration Blender itself uses."""

import os

import bpy
import numpy as np


def test_every_strip_colour_space_is_converted(extension):
    from portrait_relight.addon import colour

    items = [i.identifier for i in bpy.types.ColorManagedInputColorspaceSettings.bl_rna
             .properties["name"].enum_items]
    assert {"ACEScg", "ACES2065-1", "ACEScct", "AgX Log", "Rec.2100-PQ", "sRGB"} <= set(items)
    px = np.linspace(0.0, 1.0, 12, dtype=np.float32).reshape(2, 2, 3)
    for name in items:
        out = colour.to_linear(px, colour.lookup(name))
        assert np.isfinite(out).all() and out.shape == px.shape, name


def test_the_extension_uses_blenders_own_configuration(extension):
    from portrait_relight.addon import colour

    if os.environ.get("OCIO"):
        assert colour.config_path() == os.environ["OCIO"]
    else:
        want = os.path.join(bpy.utils.resource_path('LOCAL'), "datafiles", "colormanagement",
                            "config.ocio")
        assert colour.config_path() == want
