"""The frame cache: one command builds it; cached samples equal on-the-fly samples."""

import numpy as np
import pytest
import torch

from addon.errors import InputError

RES, PAIRS = 32, 2


@pytest.fixture(scope="module")
def cache(shared_data, tmp_path_factory):
    from training.data.build_cache import build
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("cache")
    r = build("train", RES, PAIRS, out, data_root=shared_data, progress=None)
    assert r["bytes"] > 0
    return out


def test_cached_samples_equal_on_the_fly_samples_of_the_same_pool(cache, shared_data):
    from training.data.dataset import LightStageDataset
    cached = LightStageDataset("train", RES, seed=3, length=20, data_root=shared_data,
                               cache_dir=cache)
    live = LightStageDataset("train", RES, seed=3, length=20, data_root=shared_data, pool=PAIRS)
    assert cached.pool == PAIRS
    used = set()
    for idx in range(6):
        a, b = cached[idx], live[idx]
        used.add(cached.draw(idx)[0])
        assert set(a) == set(b)
        for k in a:
            assert a[k].dtype == np.float32 and a[k].shape == b[k].shape, k
            # float16 transfer: each term rounds by at most 2**-11 relative
            tol = float(np.abs(b[k]).max()) * 2e-3 + 1e-7
            np.testing.assert_allclose(a[k], b[k], rtol=0, atol=tol, err_msg=k)
        assert np.abs(a["img_t_i"]).max() > 0
    assert used == set(range(PAIRS))  # both pairs were exercised


def test_pairs_do_not_depend_on_the_seed(shared_data):
    from training.data.dataset import LightStageDataset
    a = LightStageDataset("train", RES, seed=1, data_root=shared_data, pool=4).pair_scene(3)
    b = LightStageDataset("train", RES, seed=2, data_root=shared_data, pool=4).pair_scene(3)
    assert a[1] == b[1] and a[0].ident.id == b[0].ident.id and a[0].cam == b[0].cam


def test_rebuilding_keeps_existing_pairs(cache, shared_data):
    from training.data.build_cache import build
    from training.data.dataset import cache_folder
    files = sorted(cache_folder(cache, "train", RES).glob("pair_*.bin"))
    stamps = [p.stat().st_mtime_ns for p in files]
    build("train", RES, PAIRS, cache, data_root=shared_data, progress=None)
    assert [p.stat().st_mtime_ns for p in files] == stamps


def test_missing_or_incomplete_caches_say_how_to_build_them(cache, shared_data, tmp_path):
    from training.data.dataset import LightStageDataset, cache_folder
    with pytest.raises(InputError, match="build_cache"):
        LightStageDataset("train", RES, data_root=shared_data, cache_dir=tmp_path)
    with pytest.raises(InputError, match="holds 2 pairs"):
        LightStageDataset("train", RES, data_root=shared_data, cache_dir=cache, pool=5)
    folder = cache_folder(tmp_path, "train", RES)
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_text((cache_folder(cache, "train", RES)
                                           / "manifest.json").read_text())
    with pytest.raises(InputError, match="incomplete"):
        LightStageDataset("train", RES, data_root=shared_data, cache_dir=tmp_path)


def test_a_cache_from_another_renderer_version_is_rerendered(cache, shared_data):
    import json

    from training.data.build_cache import build
    from training.data.dataset import cache_folder
    folder = cache_folder(cache, "train", RES)
    man = json.loads((folder / "manifest.json").read_text())
    (folder / "manifest.json").write_text(json.dumps({**man, "renderer": "older"}))
    first = folder / "pair_000000.bin"
    before = first.stat().st_mtime_ns
    build("train", RES, PAIRS, cache, data_root=shared_data, progress=None)
    assert first.stat().st_mtime_ns != before
    assert json.loads((folder / "manifest.json").read_text())["renderer"] == man["renderer"]
