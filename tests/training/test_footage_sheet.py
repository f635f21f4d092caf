"""The real-footage contact sheet: one clip, two frames, one lighting, through the product pipeline.

The footage is local-only data (../shared/data/footage); everything is written under tmp_path."""

import hashlib
import math
import os
import pathlib

import numpy as np
import pytest

from addon import pipeline
from addon.errors import InputError
from training.eval import footage_sheet as fs
from training.lightstage.png import read_png

ROOT = pathlib.Path(__file__).resolve().parents[2]
DRAFT = ROOT / "models" / "relight-draft.json"


def _stamp(path):
    return hashlib.sha256(path.read_bytes()).hexdigest(), os.stat(path).st_mtime_ns


def test_sheet_for_one_clip_two_frames_one_lighting(shared_data, tmp_path, capsys):
    clip = shared_data / "footage" / "d0.mp4"
    before = _stamp(clip)
    out = tmp_path / "footage"
    rc = fs.main(["--models", str(DRAFT), "--out", str(out), "--frames", "2", "--clips", "d0",
                  "--lightings", "key-left", "--data", str(shared_data)])
    assert rc == 0
    assert _stamp(clip) == before, "the source footage must never be modified"

    run_dir = out / "d0" / "key-left" / "relight-draft"
    assert [pathlib.Path(pipeline.relit_path(run_dir, i)).is_file() for i in (0, 1)] == [True, True]
    sheet = read_png(out / "sheet.png")
    # Two columns (input, key-left) of TILE boxes with one gutter; the light-vector header row,
    # then one clip row below a gutter.
    assert sheet.shape == (fs.HEADER_H + fs.GAP + fs.TILE[1], 2 * fs.TILE[0] + fs.GAP, 3)
    # d0 is square: each tile holds a TILE[1] x TILE[1] frame, centred in its box.
    y0, x0 = fs.HEADER_H + fs.GAP, (fs.TILE[0] - fs.TILE[1]) // 2
    input_tile = sheet[y0:, x0:x0 + fs.TILE[1]].astype(int)
    relit_tile = sheet[y0:, fs.TILE[0] + fs.GAP + x0:][:, :fs.TILE[1]].astype(int)
    assert input_tile.std() > 20 and relit_tile.std() > 20  # pictures, not empty boxes
    assert np.abs(input_tile - relit_tile).mean() > 1  # the relit frame is not the input

    seq = read_png(out / "sequence.png")  # input, |d input|, relit, |d relit|: two frames each
    assert seq.shape == (4 * fs.SEQ_TILE[1] + 3 * fs.GAP, 2 * fs.SEQ_TILE[0] + fs.GAP, 3)
    printed = capsys.readouterr().out
    assert str(out / "sheet.png") in printed and "fps" in printed


def test_unknown_clip_or_lighting_is_a_clear_error(shared_data, tmp_path):
    with pytest.raises(InputError, match="Unknown clip nope; choose from d0"):
        fs.make_sheets(fs.parse_args(["--clips", "nope", "--out", str(tmp_path),
                                      "--data", str(shared_data)]))
    with pytest.raises(InputError, match="Unknown lighting moon"):
        fs.make_sheets(fs.parse_args(["--lightings", "moon", "--out", str(tmp_path),
                                      "--data", str(shared_data)]))
    assert not any(tmp_path.iterdir())  # refused before anything was written


def test_missing_footage_folder_says_where_it_looked(tmp_path):
    with pytest.raises(InputError, match="No footage"):
        fs.make_sheets(fs.parse_args(["--data", str(tmp_path), "--out", str(tmp_path / "o")]))


def test_balance_follows_the_bright_side_inside_the_matte():
    img = np.full((8, 12, 3), 0.2, np.float32)
    img[:, :6] = 0.6                      # image left three times as bright
    img[:, 10:] = 50.0                    # outside the matte: must not count
    matte = np.zeros((8, 12), np.float32)
    matte[:, 2:10] = 1.0                  # centre column 6 splits 2..5 | 6..9
    assert fs.balance(img, matte) == pytest.approx(3.0)
    assert fs.balance(img[:, ::-1], matte[:, ::-1]) == pytest.approx(1 / 3)
    assert np.isnan(fs.balance(img, np.zeros_like(matte)))  # no portrait: no figure


def test_lightings_point_where_they_say(shared_data):
    """The key lamp is on the camera's left (light-frame -X), the rim lamp's main power behind
    (-Z), the warm sun on the right and warmer than it is blue."""
    by_name = {lt.name: lt for lt in fs.LIGHTINGS}
    from addon import lightvec

    def mean_direction(light):
        power = (light * lightvec.solid_angles()[..., None]).sum(-1)
        return (power[..., None] * lightvec.directions()).sum((0, 1)) / power.sum()

    key = mean_direction(fs.light_vector(by_name["key-left"], shared_data))
    rim = fs.light_vector(by_name["rim-blue"], shared_data)
    sun = fs.light_vector(by_name["sun-warm"], shared_data)
    assert key[0] < -0.3 and key[2] > 0.3
    assert mean_direction(rim)[2] < 0
    assert mean_direction(sun)[0] > 0.2
    total = lightvec.total_power(sun)
    assert total[0] > total[2]


def test_skin_chroma_ignores_exposure_and_sees_greyed_skin():
    rng = np.random.default_rng(0)
    skin = np.array([0.6, 0.4, 0.3], np.float32) * rng.uniform(0.5, 1.0, (32, 32, 1))
    skin = skin.astype(np.float32)
    matte = np.ones((32, 32), np.float32)
    base = fs.skin_chroma(skin, matte, skin)
    assert base > 0.05
    assert fs.skin_chroma(skin * 3.0, matte, skin) == pytest.approx(base, rel=1e-5)
    grey = skin.mean(axis=2, keepdims=True)
    assert fs.skin_chroma(0.5 * skin + 0.5 * grey, matte, skin) == pytest.approx(base / 2, rel=1e-3)
    assert np.isnan(fs.skin_chroma(skin, np.zeros_like(matte), skin))  # no subject


def test_shadow_warmth_reads_the_hue_of_the_skin_the_light_darkens():
    """Half the skin darkened 4x at its own colour: no warmth, whatever the exposure; the same
    half also turned redder (red x1.3, blue /1.3): log(1.69); nothing darkened: nan."""
    rng = np.random.default_rng(0)
    skin = np.array([0.6, 0.4, 0.3], np.float32) * rng.uniform(0.5, 1.0, (32, 32, 1))
    skin = skin.astype(np.float32)
    matte = np.ones((32, 32), np.float32)
    dark = np.ones((32, 32, 1), np.float32)
    dark[:, :16] = 0.25
    assert fs.shadow_warmth(skin * dark * 2.0, matte, skin) == pytest.approx(0.0, abs=1e-6)
    warm = np.where(dark < 1.0, np.array([1.3, 1.0, 1 / 1.3], np.float32), 1.0)
    assert fs.shadow_warmth(skin * dark * warm, matte, skin) == pytest.approx(math.log(1.69),
                                                                             rel=1e-4)
    assert np.isnan(fs.shadow_warmth(skin, matte, skin))
