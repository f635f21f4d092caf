"""Typed errors that carry a message an artist can act on.

Operators catch ``RelightError`` and report ``str(err)``; anything else is a bug and is allowed to
surface as a traceback in the console (never swallowed)."""


class RelightError(Exception):
    """Base class: ``str(err)`` says what went wrong and what to do about it."""


class InputError(RelightError):
    """The footage, HDRI or other user input cannot be used as given."""


class LightingError(RelightError):
    """The lighting description (HDRI, lamps, light vector) is invalid."""


class ModelError(RelightError):
    """The ONNX model is missing, corrupt, or has a contract this add-on does not know."""


class OutputError(RelightError):
    """The output folder cannot be written, or holds another run."""


class DependencyError(RelightError):
    """A bundled dependency (onnxruntime, OpenEXR, PyAV, threadpoolctl) is missing or broken."""


class Cancelled(RelightError):
    """The user cancelled a run; finished frames are kept and the run can be resumed."""
