"""Colour spaces a Blender strip can declare, converted to scene linear (linear Rec.709).

Every colour space of Blender's OpenColorIO configuration is converted by OpenColorIO itself
(the PyOpenColorIO wheel, bundled with the extension), with the very configuration Blender uses:
``$OCIO`` when set, else the one the extension registers from Blender (``use_config``), else the
``bpy`` module's own ``datafiles/colormanagement/config.ocio``. That covers ACEScg, ACES2065-1,
ACEScc/cct, AgX and Filmic Log, the display spaces with their view transforms, Rec.2100 PQ and HLG.

The common spaces (sRGB, Rec.1886, the linear gamuts) keep hand-written fast paths: a lookup
table per code value and Blender 5.0's own matrices (each space's ``from_scene_reference`` matrix
out of CIE XYZ D65). tests/core/test_colour.py holds them to OpenColorIO's results, and
``python -m bench.pipeline_1080p --colour-options`` measures what they save.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import pathlib
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError

# Rec.709 / sRGB luminance weights (linear RGB -> Y): the one copy; callers build the arrays they
# need from it (float32 or float64) so every use keeps its exact values.
REC709_LUMA = (0.2126, 0.7152, 0.0722)

# XYZ (D65) -> RGB matrices, rows as in config.ocio (out = M @ xyz).
XYZ_TO_REC709 = np.array([[3.2409699, -1.5373832, -0.4986108],
                          [-0.9692436, 1.8759675, 0.0415551],
                          [0.0556301, -0.2039770, 1.0569715]])
XYZ_TO_P3D65 = np.array([[2.4934969, -0.9313836, -0.4027108],
                         [-0.8294890, 1.7626641, 0.0236247],
                         [0.0358458, -0.0761724, 0.9568845]])
XYZ_TO_REC2020 = np.array([[1.7166512, -0.3556708, -0.2533663],
                           [-0.6666844, 1.6164812, 0.0157685],
                           [0.0176399, -0.0427706, 0.9421031]])
XYZ_TO_EGAMUT = np.array([[1.5250528, -0.3159135, -0.1226583],
                          [-0.5091526, 1.3333274, 0.1382844],
                          [0.0957153, 0.0508974, 0.7879558]])
# Blender's luts/xyz_E_to_D65.spimtx (a chromatic adaptation of XYZ from illuminant E to D65).
XYZ_E_TO_D65 = np.array([[0.95318743, -0.02659057, 0.02387315],
                         [-0.03824666, 1.02884062, 0.00940604],
                         [0.00260677, -0.00303325, 1.08925647]])


def _to_709(xyz_to_space: np.ndarray) -> np.ndarray:
    return XYZ_TO_REC709 @ np.linalg.inv(xyz_to_space)


@dataclass(frozen=True)
class ColourSpace:
    """How to bring a declared colour space to linear Rec.709."""
    name: str
    curve: str                 # 'linear' | 'srgb' | 'gamma24' | 'ocio' (OpenColorIO's processor)
    matrix: np.ndarray | None  # 3x3 to linear Rec.709 after the curve; None = identity
    is_data: bool = False      # Non-Color: numbers, not light (treated as linear, with a note)
    processor: object = field(default=None, compare=False, repr=False)  # OCIO CPU processor


_IDENTITY = None
SPACES = {
    s.name: s for s in (
        ColourSpace("sRGB", "srgb", _IDENTITY),
        ColourSpace("Linear Rec.709", "linear", _IDENTITY),
        ColourSpace("Non-Color", "linear", _IDENTITY, is_data=True),
        ColourSpace("Rec.1886", "gamma24", _IDENTITY),
        ColourSpace("Rec.2020", "gamma24", _to_709(XYZ_TO_REC2020)),
        ColourSpace("Display P3", "srgb", _to_709(XYZ_TO_P3D65)),
        ColourSpace("Linear Rec.2020", "linear", _to_709(XYZ_TO_REC2020)),
        ColourSpace("Linear DCI-P3 D65", "linear", _to_709(XYZ_TO_P3D65)),
        ColourSpace("Linear FilmLight E-Gamut", "linear", _to_709(XYZ_TO_EGAMUT)),
        ColourSpace("Linear CIE-XYZ D65", "linear", XYZ_TO_REC709),
        ColourSpace("Linear CIE-XYZ E", "linear", XYZ_TO_REC709 @ XYZ_E_TO_D65),
    )
}
# Older and alternative names Blender and OCIO configs use for the same spaces.
ALIASES = {
    "Linear": "Linear Rec.709", "Linear BT.709": "Linear Rec.709", "lin_rec709_scene":
    "Linear Rec.709", "scene_linear": "Linear Rec.709", "Raw": "Non-Color",
    "Non-Colour Data": "Non-Color", "Generic Data": "Non-Color", "Utility - Raw": "Non-Color",
    "BT.1886": "Rec.1886", "XYZ": "Linear CIE-XYZ D65", "Linear CIE-XYZ I-E": "Linear CIE-XYZ E",
    "srgb_rec709_scene": "sRGB", "Utility - sRGB - Texture": "sRGB",
}


SCENE_LINEAR = "Linear Rec.709"  # what every space is converted to (Blender's scene_linear role)
_CONFIG: list[str | None] = [None]  # set by use_config (the extension, from Blender)


def use_config(path: str | os.PathLike | None) -> None:
    """Convert with this OpenColorIO configuration (the extension passes Blender's own)."""
    _CONFIG[0] = None if path is None else str(path)
    _ocio_config.cache_clear()
    ocio_space.cache_clear()


def config_path() -> str | None:
    """The OpenColorIO configuration Blender uses: $OCIO, else the one ``use_config`` set, else
    the bpy module's own (found on disk, without importing bpy)."""
    env = os.environ.get("OCIO")
    if env:
        return env
    if _CONFIG[0]:
        return _CONFIG[0]
    spec = importlib.util.find_spec("bpy")
    for folder in spec.submodule_search_locations or () if spec else ():
        hits = sorted(pathlib.Path(folder).glob("*/datafiles/colormanagement/config.ocio"))
        if hits:
            return str(hits[-1])
    return None


@functools.lru_cache(maxsize=2)
def _ocio_config(path: str):
    import PyOpenColorIO as ocio

    return ocio.Config.CreateFromFile(path)


def ocio_names() -> list[str]:
    """Every colour space of the configuration in use ([] without OpenColorIO or a config)."""
    path = config_path()
    if path is None or importlib.util.find_spec("PyOpenColorIO") is None:
        return []
    return [cs.getName() for cs in _ocio_config(path).getColorSpaces()]


@functools.lru_cache(maxsize=64)
def ocio_space(name: str, path: str) -> ColourSpace:
    """The ColourSpace converting ``name`` to scene linear through OpenColorIO's own processor,
    with the configuration at ``path``; KeyError when the configuration lacks the name. lookup
    uses it where no fast path exists."""
    config = _ocio_config(path)
    cs = config.getColorSpace(name)
    if cs is None:
        raise KeyError(name)
    import PyOpenColorIO as ocio

    # lossless: the default optimisation approximates powers (errors of 1e-5 on sRGB)
    proc = config.getProcessor(cs.getName(), SCENE_LINEAR).getOptimizedCPUProcessor(
        ocio.OPTIMIZATION_LOSSLESS)
    return ColourSpace(cs.getName(), "ocio", None, bool(cs.isData()), proc)


def lookup(name: str) -> ColourSpace:
    """The ColourSpace for a Blender colour-space name (or an alias OpenColorIO knows), or an
    InputError saying what to do."""
    key = ALIASES.get(name, name)
    space = SPACES.get(key)
    if space is not None:
        return space
    path = config_path()
    if importlib.util.find_spec("PyOpenColorIO") is None:
        raise InputError(f"The strip's colour space '{name}' needs OpenColorIO, which is not "
                         "installed (it comes with the extension's zip; reinstall the extension, "
                         "or `pip install opencolorio` where the bpy module runs).")
    if path is None or not pathlib.Path(path).is_file():
        raise InputError(f"The strip's colour space '{name}' needs Blender's OpenColorIO "
                         f"configuration, which was not found ({path or 'no $OCIO, no Blender'}); "
                         "set $OCIO to the config.ocio Blender uses.")
    try:
        return ocio_space(key, path)
    except KeyError:
        known = ", ".join(ocio_names())
        raise InputError(f"The strip's colour space '{name}' is not in Blender's colour "
                         f"configuration ({path}); set the strip's colour space to the one the "
                         f"file was written in. Known: {known}.") from None
    except Exception as err:  # noqa: BLE001 - OpenColorIO's own exception types
        raise InputError(f"OpenColorIO cannot convert '{name}' to scene linear ({err}); set the "
                         "strip's colour space to the one the file was written in.") from None


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 piecewise decode; negative values are mirrored so the curve stays odd."""
    x = np.asarray(x, dtype=np.float32)
    a = np.abs(x)
    lin = np.where(a <= 0.04045, a / 12.92, ((a + 0.055) / 1.055) ** 2.4)
    return (np.sign(x) * lin).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    a = np.abs(x)
    enc = np.where(a <= 0.0031308, a * 12.92, 1.055 * a ** (1 / 2.4) - 0.055)
    return (np.sign(x) * enc).astype(np.float32)


def _decode_curve(x: np.ndarray, curve: str) -> np.ndarray:
    if curve == "srgb":
        return srgb_to_linear(x)
    if curve == "gamma24":
        x = np.asarray(x, dtype=np.float32)
        return (np.sign(x) * np.abs(x) ** 2.4).astype(np.float32)
    return np.asarray(x, dtype=np.float32)


def integer_lut(space: ColourSpace, bits: int) -> np.ndarray:
    """A (2**bits,) float32 table from code value to linear (curve only, before the matrix).

    Integer footage is decoded through this table: one gather per pixel instead of a power."""
    return _lut(space.curve, bits)


@functools.lru_cache(maxsize=8)
def _lut(curve: str, bits: int) -> np.ndarray:
    codes = np.arange(2 ** bits, dtype=np.float64) / (2 ** bits - 1)
    lut = _decode_curve(codes, curve).astype(np.float32)
    lut.flags.writeable = False  # shared between calls
    return lut


def to_linear(pixels: np.ndarray, space: ColourSpace, gain: float = 1.0) -> np.ndarray:
    """(H, W, 3) pixels in ``space`` to a new float32 array of linear Rec.709, times ``gain``.

    uint8/uint16 pixels are normalised to [0, 1] code values; float pixels are taken as they are.
    For integer pixels the gain is folded into the lookup table (no extra pass)."""
    px = np.asarray(pixels)
    if space.curve == "ocio":
        lin = _code_values(px).reshape(-1, 3).copy()
        space.processor.applyRGB(lin)
        lin = lin.reshape(px.shape)
        if gain != 1.0:
            lin *= np.float32(gain)
        return lin
    if px.dtype == np.uint8 or px.dtype == np.uint16:
        lut = integer_lut(space, 8 * px.dtype.itemsize)
        lin = (lut * np.float32(gain) if gain != 1.0 else lut)[px]
        gain = 1.0
    else:
        lin = _decode_curve(px, space.curve)
        if np.shares_memory(lin, px):  # never scale or repair the caller's array
            lin = lin.copy()
    if space.matrix is not None:
        lin = lin @ space.matrix.T.astype(np.float32)
    lin = np.ascontiguousarray(lin, dtype=np.float32)
    if gain != 1.0:
        lin *= np.float32(gain)
    return lin


def _code_values(px: np.ndarray) -> np.ndarray:
    """float32 values: integers normalised to [0, 1] code values, floats as they are."""
    if px.dtype == np.uint8 or px.dtype == np.uint16:
        return px.astype(np.float32) * np.float32(1.0 / np.iinfo(px.dtype).max)
    return np.asarray(px, np.float32)


_BAND = 1 << 18  # values per lookup chunk: keeps numpy's index temporary in cache (~2x faster)


def to_linear_planar(planes: np.ndarray, space: ColourSpace, gain: float = 1.0) -> np.ndarray:
    """Channels-first (3, H, W) pixels in ``space`` to a new (3, H, W) float32 array of linear
    Rec.709 times ``gain``: the pipeline's fast path (same values as ``to_linear``, up to the
    rounding of the gamut matrix product)."""
    px = np.asarray(planes)
    if px.ndim != 3 or px.shape[0] != 3:
        raise ValueError(f"planes must be (3, H, W), got {px.shape}")
    if space.curve == "ocio":
        import PyOpenColorIO as ocio

        out = np.array(_code_values(px), np.float32, order="C", copy=True)
        h, w = px.shape[1:]
        space.processor.apply(ocio.PlanarImageDesc(out[0], out[1], out[2], w, h))
        if gain != 1.0:
            out *= np.float32(gain)
        return out
    out = np.empty(px.shape, np.float32)
    if px.dtype == np.uint8 or px.dtype == np.uint16:
        lut = integer_lut(space, 8 * px.dtype.itemsize)
        lut = lut * np.float32(gain) if gain != 1.0 else lut
        flat_in, flat_out = px.reshape(3, -1), out.reshape(3, -1)
        for c in range(3):
            for s in range(0, flat_in.shape[1], _BAND):
                # mode="clip": no bounds check (codes always fit the table), and numpy does
                # not buffer ``out`` as it does for mode="raise" (2x faster)
                np.take(lut, flat_in[c, s:s + _BAND], out=flat_out[c, s:s + _BAND], mode="clip")
        gain = 1.0
    else:
        out[...] = _decode_curve(px, space.curve)
    if space.matrix is not None:
        flat = out.reshape(3, -1)
        flat[...] = space.matrix.astype(np.float32) @ flat
    if gain != 1.0:
        out *= np.float32(gain)
    return out
