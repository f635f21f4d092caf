"""The relighting engine, free of Blender. ``relight_image`` is the one-image entry point."""


def relight_image(image, light, preset: str = "standard", models_dir=None, **kwargs):
    """See addon.api.relight_image (imported on first use: the extension's start-up stays light)."""
    from .api import relight_image as run

    return run(image, light, preset, models_dir, **kwargs)
